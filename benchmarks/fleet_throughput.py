"""Throughput of the transport: N robot processes at a high speed-up through one router.

Starts a router and ``--robots`` simulated robots (separate processes), counts
every message a subscriber receives, checks seq continuity, and prints JSON:
messages per second through the router, messages lost, wall time.

    python benchmarks/fleet_throughput.py --robots 5 --speedup 50 --duration 60
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
from collections import defaultdict
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from robots.simulator import simulate  # noqa: E402
from schemas.codec import decode  # noqa: E402
from schemas.config import FleetSettings  # noqa: E402
from schemas.messages import GroundTruth, Odometry, Scan  # noqa: E402
from schemas.transport import open_session  # noqa: E402
from report import emit

MODELS = {"odom": Odometry, "scan": Scan, "truth": GroundTruth}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robots", type=int, default=5)
    parser.add_argument("--speedup", type=float, default=50.0)
    parser.add_argument("--duration", type=float, default=60.0, help="robot seconds each robot publishes")
    parser.add_argument("--rate", type=float, default=10.0)
    parser.add_argument("--world", default="arena")
    parser.add_argument("--out", help="also write the JSON here")
    args = parser.parse_args()

    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    env = {**os.environ, "FLEETSLAM_ZENOH_CONNECT": endpoint, "FLEETSLAM_PREFIX": "bench"}
    cli = [sys.executable, "-m", "services.cli"]
    router = subprocess.Popen([*cli, "router", "--listen", endpoint], env=env, cwd=REPO, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 10
    while True:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
            break
        except OSError:
            if time.monotonic() > deadline:
                raise SystemExit("router did not start")
            time.sleep(0.05)
    session = open_session(FleetSettings(zenoh_connect=endpoint))
    lock = threading.Lock()
    seqs: dict[tuple[str, str], list[int]] = defaultdict(list)
    first_last = [None, None]

    def on_sample(sample) -> None:
        _, _, rid, stream = str(sample.key_expr).split("/")
        if stream not in MODELS:
            return
        message = decode(sample.payload.to_bytes(), MODELS[stream])
        now = time.monotonic()
        with lock:
            seqs[(rid, stream)].append(message.seq)
            first_last[0] = first_last[0] or now
            first_last[1] = now

    subscriber = session.declare_subscriber("bench/robots/*/*", on_sample)
    ids = [f"r{i + 1}" for i in range(args.robots)]
    expected = {}
    for rid in ids:
        log = simulate(args.world, seed=0, duration=args.duration, rate=args.rate, robot_ids=[rid]).robots[rid]
        expected.update({(rid, "odom"): len(log.odom_stamp), (rid, "scan"): len(log.scan_stamp),
                         (rid, "truth"): len(log.truth_stamp)})
    robots = [subprocess.Popen([*cli, "robot", "--id", rid, "--world", args.world, "--duration", str(args.duration),
                                "--rate", str(args.rate), "--speedup", str(args.speedup), "--start-delay", "0.5"],
                               env=env, cwd=REPO, stderr=subprocess.DEVNULL) for rid in ids]
    for robot in robots:
        robot.wait(timeout=args.duration / args.speedup + 60)
    total_expected = sum(expected.values())
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        with lock:
            if sum(len(v) for v in seqs.values()) >= total_expected:
                break
        time.sleep(0.05)
    subscriber.undeclare()
    session.close()
    router.send_signal(signal.SIGTERM)
    router.wait(timeout=10)
    received = sum(len(v) for v in seqs.values())
    in_order = all(v == list(range(len(v))) for v in seqs.values())
    span = (first_last[1] - first_last[0]) if first_last[0] else float("nan")
    result = {
        "robots": args.robots, "speedup": args.speedup, "robot_seconds": args.duration, "rate_hz": args.rate,
        "expected": total_expected, "received": received, "lost": total_expected - received, "in_order": in_order,
        "messages_per_s": received / span if span > 0 else None, "span_s": span,
    }
    emit(result, args.out)


if __name__ == "__main__":
    main()
