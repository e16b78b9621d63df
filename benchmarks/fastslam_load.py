"""Load on the central FastSLAM service: N simulated robots at 10 Hz through a real router, 200 particles.

Starts ``fleetslam router`` and ``fleetslam central`` as processes, then publishes ``--robots`` simulated
robots (world ``--world``) from this process as the robot processes would (liveliness token, RobotInfo,
odometry and scans at real time, reliable with congestion control BLOCK). The central service's own
stats give the latency of every message: from its arrival in the service to the end of its handling
(queue wait included; ``latency_ms_p99``), the time spent in the filter (``compute_ms``) and the time a
message waited in the reorder buffer for the other robots (``hold_ms``). The worst p99 over the run
(after ``--warmup`` s) is reported, with the count of processed messages and the queue depth.

    .venv/bin/python benchmarks/fastslam_load.py [--robots 10] [--rate 10] [--particles 200]
        [--duration 60] [--association nn] [--reorder-window-s 0.1] [--out FILE]
"""

from __future__ import annotations

import argparse
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import zenoh

from schemas.contract import OdomEvent, ScanEvent
from robots.simulator import simulate
from schemas.codec import decode, encode
from schemas.config import FleetSettings
from schemas.keys import Keys
from schemas.messages import ServiceStats
from schemas.transport import StreamPublisher, declare_robot_tokens, open_session
from report import emit

REPO = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for_port(port: int, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
            return
        except OSError:
            time.sleep(0.05)
    raise RuntimeError(f"router did not listen on port {port}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robots", type=int, default=10)
    parser.add_argument("--rate", type=float, default=10.0, help="scan and odometry rate of each robot (Hz)")
    parser.add_argument("--particles", type=int, default=200)
    parser.add_argument("--association", default="nn")
    parser.add_argument("--world", default="random")
    parser.add_argument("--duration", type=float, default=60.0, help="seconds of robot time (published at real time)")
    parser.add_argument("--warmup", type=float, default=5.0)
    parser.add_argument("--reorder-window-s", type=float, default=0.1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out")
    args = parser.parse_args()

    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    prefix = f"load{port}"
    env = {**os.environ, "FLEETSLAM_ZENOH_CONNECT": endpoint, "FLEETSLAM_PREFIX": prefix, "PYTHONUNBUFFERED": "1"}
    logs = Path(args.out).with_suffix(".logs") if args.out else Path("/tmp") / f"fastslam_load_{port}"
    logs.mkdir(parents=True, exist_ok=True)
    children = []

    def start(name: str, *words: str) -> subprocess.Popen:
        handle = open(logs / f"{name}.log", "w")
        child = subprocess.Popen([sys.executable, "-m", "services.cli", *words], env=env, cwd=REPO,
                                 stdout=handle, stderr=subprocess.STDOUT)
        children.append(child)
        return child

    data = simulate(args.world, robots=args.robots, seed=args.seed, duration=args.duration, rate=args.rate)
    keys = Keys(prefix)
    stats: list[tuple[float, ServiceStats]] = []
    lock = threading.Lock()
    try:
        start("router", "router", "--listen", endpoint)
        wait_for_port(port, timeout=20.0)
        start("central", "central", "--particles", str(args.particles), "--association", args.association,
              "--reorder-window-s", str(args.reorder_window_s), "--seed", str(args.seed))
        session = open_session(FleetSettings(zenoh_connect=endpoint, prefix=prefix))

        def on_stats(sample: zenoh.Sample) -> None:
            with lock:
                stats.append((time.monotonic(), decode(sample.payload.to_bytes(), ServiceStats)))

        subscriber = session.declare_subscriber(keys.stats("central"), on_stats)
        deadline = time.monotonic() + 30
        while not stats and time.monotonic() < deadline:
            time.sleep(0.05)
        if not stats:
            raise RuntimeError(f"the central service did not start; see {logs}")
        tokens = [token for rid in data.robots for token in declare_robot_tokens(session, keys, rid)]
        info = {rid: StreamPublisher(session, keys.info(rid)) for rid in data.robots}
        pubs = {(rid, s): StreamPublisher(session, keys.robot(rid, s)) for rid in data.robots for s in ("odom", "scan")}
        for rid, log in data.robots.items():
            info[rid].put(encode(log.info))
        time.sleep(0.5)
        sent = 0
        wall0 = time.monotonic()
        t0 = data.start_stamp
        started = None
        for event in data.events():
            due = wall0 + (event.stamp - t0)
            now = time.monotonic()
            if due > now:
                time.sleep(due - now)
            if isinstance(event, OdomEvent):
                pubs[(event.robot_id, "odom")].put(event.to_message())
            elif isinstance(event, ScanEvent):
                pubs[(event.robot_id, "scan")].put(event.to_message(with_ids=False))
            sent += 1
            if started is None and event.stamp - t0 >= args.warmup:
                started = time.monotonic()
        publish_s = time.monotonic() - wall0
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            with lock:
                last = stats[-1][1]
            if last.extra.get("processed", 0) >= sent and last.extra.get("buffered", 1) == 0:
                break
            time.sleep(0.2)
        drained_s = time.monotonic() - wall0 - publish_s
        for token in tokens:
            token.undeclare()
        with lock:
            window = [s for t, s in stats if started is not None and t >= started]
            last = stats[-1][1]
        subscriber.undeclare()
        session.close()
    finally:
        for child in reversed(children):
            if child.poll() is None:
                child.send_signal(signal.SIGTERM)
        for child in reversed(children):
            try:
                child.wait(timeout=15)
            except subprocess.TimeoutExpired:
                child.kill()

    def worst(name: str) -> float | None:
        values = [s.extra.get(name) for s in window if s.extra.get(name) is not None]
        return round(max(values), 2) if values else None

    report = {
        "settings": vars(args),
        "messages_sent": sent, "messages_per_s": round(sent / publish_s, 1),
        "processed": int(last.extra.get("processed", 0)), "rejected": last.rejected,
        "publish_s": round(publish_s, 1), "drain_after_publish_s": round(drained_s, 2),
        "latency_ms_p99_worst": round(max(s.latency_ms_p99 for s in window), 2) if window else None,
        "latency_ms_median_last": round(last.latency_ms_median, 2),
        "compute_ms_p99_worst": worst("compute_ms_p99"), "compute_ms_median_last": last.extra.get("compute_ms_median"),
        "hold_ms_p99_worst": worst("hold_ms_p99"),
        "queue_depth_max": max((s.queue_depth for s in window), default=None),
        "landmarks_best": last.extra.get("landmarks_best"), "effective_particles": last.extra.get("effective_particles"),
        "logs": str(logs),
    }
    emit(report, args.out)


if __name__ == "__main__":
    main()
