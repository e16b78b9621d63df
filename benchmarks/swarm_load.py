"""Past one machine's robots: a ``fleetslam swarm`` of N robots at 10 Hz through two meshed routers into central.

Two sites, as ``services.launcher``'s ``Fleet`` runs them: router A, and router B started with ``--connect`` to A
(the routers form a mesh). The swarm (``fleetslam swarm --robots N``, one process, each robot on its own keys with its
own token, no landmark ids) publishes on router A at real time; the central FastSLAM service (``--particles``,
``--association shared``: no ids) runs on router B. Measured, per run:

- every message processed: central's ``processed`` (its stats' extra) against the odometry and scans the swarm says
  it sent (its ``--json-out``); ``unprocessed`` is the difference once central has drained its queue (or after
  ``--drain-s``: still queued, not lost, when ``rejected`` and ``missing`` are empty);
- arrival → handled latency: central's ``latency_ms_p99`` (arrival in the service to the end of its handling, queue
  wait included), the worst over the stats published while the swarm ran at full rate (after ``--warmup`` s), and
  its median; for a message the reorder buffer held (it waits for the other robots' streams), arrival → handed to
  the filter is ``hold_ms``, and the target is judged on the worse of the two p99s; the filter time
  (``compute_ms``) beside them;
- CPU of each process (psutil: user + system seconds over the window, in cores) and of each processor, so that
  "both cores in use" is shown, and the swarm's own lag behind its schedule (a swarm that fell behind offered less);
- central's CPU per message: its cores over the window divided by the messages it processed per second meanwhile
  (``central_cpu_ms_per_message``: all its work, the filter's included, over odometry and scans alike), and how
  many it processed per second; compare runs by ratios, on a shared machine absolute times swing;
- the same with ``central --workers N`` (``--compare-workers``, 2 by default; central's default is 1) when central has
  a ``--workers`` flag.

Target (issue 54): 200 robots at 10 Hz, central 100 particles without ids: every message processed, p99 < 100 ms,
both cores in use. With ``--search`` the robot counts of ``--robots`` (a comma list, largest first) are run in turn
until one meets the latency and loss target: the largest N central keeps up with.

    .venv/bin/python benchmarks/swarm_load.py [--robots 200] [--duration 60] [--particles 100] [--search]
        [--single-router] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import psutil

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from schemas.config import DemoSettings, FleetSettings  # noqa: E402
from schemas.messages import ServiceStats  # noqa: E402
from schemas.transport import Shutdown, open_session  # noqa: E402
from services.launcher import Child, Fleet  # noqa: E402
from report import emit  # noqa: E402
from soak import StatsLog, free_port  # noqa: E402

PREFIX = "swarmload"
LATENCY_TARGET_MS = 100.0
SWARM_LINGER_S = 1.0


def central_has_workers() -> bool:
    """Whether ``fleetslam central`` takes ``--workers`` (issue 54 adds it)."""
    text = subprocess.run([sys.executable, "-m", "services.cli", "central", "--help"], capture_output=True, text=True,
                          cwd=REPO).stdout
    return "--workers" in text


class CpuLog:
    """User + system CPU seconds of each process, and per-processor busy shares, sampled every second."""

    def __init__(self, children: list[Child]):
        self.processes = {child.name: psutil.Process(child.process.pid) for child in children}
        self.samples: list[tuple[float, dict[str, float], list]] = []
        self.rss_mb: dict[str, float] = {}
        self._stop = threading.Event()
        psutil.cpu_percent(percpu=True)
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(1.0):
            seconds = {}
            for name, process in self.processes.items():
                try:
                    times = process.cpu_times()
                    seconds[name] = times.user + times.system
                    self.rss_mb[name] = max(self.rss_mb.get(name, 0.0), process.memory_info().rss / 2**20)
                except psutil.NoSuchProcess:
                    continue
            self.samples.append((time.monotonic(), seconds, psutil.cpu_times(percpu=True)))

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()

    def window(self, start: float, end: float) -> dict:
        """Cores each process used on average in [start, end], their sum, and each processor's busy share."""
        inside = [s for s in self.samples if start <= s[0] <= end]
        if len(inside) < 2:
            return {}
        (t0, first, cpus0), (t1, last, cpus1) = inside[0], inside[-1]
        cores = {name: round((last[name] - first[name]) / (t1 - t0), 2) for name in last if name in first}
        busy = []
        for before, after in zip(cpus0, cpus1):
            spent = sum(after) - sum(before)
            idle = (after.idle + after.iowait) - (before.idle + before.iowait)
            busy.append(round(1.0 - idle / spent, 2) if spent > 0 else None)
        return {"seconds": round(t1 - t0, 1), "cores_by_process": cores, "cores_total": round(sum(cores.values()), 2),
                "processor_busy": busy}


def run_once(robots: int, workers: int | None, args: argparse.Namespace, logs: Path, shutdown: Shutdown) -> dict:
    """One run: routers, central, a swarm of ``robots``; what was measured."""
    out = logs / (f"n{robots}" + (f"-workers{workers}" if workers else ""))
    site_a = Fleet(DemoSettings(port=free_port(), prefix=PREFIX, out=str(out), open=True), out)
    site_b = site_a if args.single_router else Fleet(DemoSettings(port=free_port(), prefix=PREFIX, out=str(out),
                                                                  open=True), out)
    result: dict = {"robots": robots, "workers": workers, "routers": 1 if args.single_router else 2,
                    "load_average_before": [round(x, 2) for x in os.getloadavg()]}
    stats = StatsLog()
    session = cpu = None
    counts_file = out / "swarm.json"
    try:
        routers = [site_a.start("router-a", "router", "--listen", site_a.endpoint)]
        site_a.wait_for_router()
        if site_b is not site_a:
            routers.append(site_b.start("router-b", "router", "--listen", site_b.endpoint, "--connect", site_a.endpoint))
            site_b.wait_for_router()
        central = site_b.start("central", "central", "--particles", str(args.particles), "--association",
                               args.association, "--seed", str(args.seed),
                               *(["--workers", str(workers)] if workers else []))
        session = open_session(FleetSettings(zenoh_connect=site_a.endpoint, prefix=PREFIX))
        subscriber = session.declare_subscriber(f"{PREFIX}/central/stats", stats.on_sample)
        result["central_ready_s"] = round(site_b.wait_for_services(["central"], shutdown, timeout=120), 1)
        swarm = site_a.start("swarm", "swarm", "--robots", str(robots), "--rate", str(args.rate), "--duration",
                             f"{args.duration:g}", "--world", args.world, "--seed", str(args.seed), "--start-delay", "2",
                             "--linger-s", str(SWARM_LINGER_S), "--json-out", str(counts_file))
        cpu = CpuLog([*routers, central, swarm])
        while swarm.process.poll() is None and not shutdown.wait(0.5):
            if central.process.poll() is not None:
                raise RuntimeError(f"central exited; see {central.log_path}")
        swarm_done = time.monotonic()
        sent_file = json.loads(counts_file.read_text()) if counts_file.exists() else {}
        sent = sent_file.get("sent", {}).get("odom", 0) + sent_file.get("sent", {}).get("scan", 0)
        drain_deadline = time.monotonic() + args.drain_s
        while not shutdown.is_set() and time.monotonic() < drain_deadline:
            last = stats.last().get("central")
            if last is not None and last.extra.get("processed", 0) >= sent and last.extra.get("buffered", 1) == 0:
                break
            shutdown.wait(0.5)
        drained = time.monotonic()
        cpu.stop()
        subscriber.undeclare()
        records = [r for r in stats.snapshot() if r.service == "central"]
        publishing = [r.t for r in records if r.stats.extra.get("processed", 0) > 0]
        window_start = (publishing[0] if publishing else swarm_done) + args.warmup
        window_end = swarm_done - SWARM_LINGER_S
        in_window = [r.stats for r in records if window_start <= r.t <= window_end]
        last = records[-1].stats if records else ServiceStats(service="central", instance="none", stamp=0.0,
                                                               uptime_s=0.0)
        processed = int(last.extra.get("processed", 0))
        result.update(
            sent_odom_scan=sent, processed=processed, unprocessed=sent - processed, rejected=last.rejected,
            missing=int(last.extra.get("missing", 0)),
            swarm_behind_max_s=sent_file.get("behind_max_s"), swarm_wall_s=sent_file.get("wall_s"),
            drain_after_swarm_s=round(drained - swarm_done, 1),
            latency_ms=latency_figures(in_window), cpu=cpu.window(window_start, window_end),
            **central_cost(records, cpu, window_start, window_end),
            rss_max_mb={name: round(mb, 1) for name, mb in cpu.rss_mb.items()},
            load_average_after=[round(x, 2) for x in os.getloadavg()], logs=str(out))
        result["met"] = met(result, args)
    finally:
        if cpu is not None and cpu._thread.is_alive():
            cpu.stop()
        if session is not None:
            session.close()
        for site in (site_a, site_b) if site_b is not site_a else (site_a,):
            site.stop([c for c in reversed(site.children) if not c.name.startswith("router")], timeout=30)
        for site in (site_b, site_a) if site_b is not site_a else (site_a,):
            site.stop([c for c in site.children if c.name.startswith("router")])
    return result


def central_cost(records: list, cpu: CpuLog, start: float, end: float) -> dict:
    """Central's processed messages per second over [start, end] (its stats) and its CPU per message (ms): its cores
    then over that rate."""
    inside = [(r.t, r.stats.extra.get("processed", 0.0)) for r in records if start <= r.t <= end]
    if len(inside) < 2 or inside[-1][1] <= inside[0][1]:
        return {}
    rate = (inside[-1][1] - inside[0][1]) / (inside[-1][0] - inside[0][0])
    cores = cpu.window(inside[0][0], inside[-1][0]).get("cores_by_process", {}).get("central")
    return {"central_processed_per_s": round(rate, 1),
            "central_cpu_ms_per_message": None if cores is None else round(1e3 * cores / rate, 3)}


def latency_figures(window: list[ServiceStats]) -> dict:
    """Worst p99 and median of the medians of central's stats in the window (each over its last messages)."""
    if not window:
        return {}

    def worst(name: str) -> float | None:
        values = [s.extra[name] for s in window if name in s.extra]
        return round(max(values), 1) if values else None

    return {"p99_worst": round(max(s.latency_ms_p99 for s in window), 1),
            "p99_median": round(float(np.median([s.latency_ms_p99 for s in window])), 1),
            "median": round(float(np.median([s.latency_ms_median for s in window])), 1),
            "hold_p99_worst": worst("hold_ms_p99"), "compute_p99_worst": worst("compute_ms_p99"),
            "compute_median_last": window[-1].extra.get("compute_ms_median"),
            "queue_depth_max": max(s.queue_depth for s in window), "stats": len(window)}


def met(result: dict, args: argparse.Namespace) -> dict:
    """The target's parts, each met or missed: every message processed, p99 < 100 ms (the worse of arrival → end
    of handling and, for the messages the reorder buffer held, arrival → handed to the filter), both cores in use
    (the processes together used more than one core), the swarm on schedule (it offered the full rate)."""
    latency = result["latency_ms"]
    p99 = max((latency[name] for name in ("p99_worst", "hold_p99_worst") if latency.get(name) is not None),
              default=None)
    cores = result["cpu"].get("cores_total")
    return {"every_message_processed": result["unprocessed"] == 0 and result["sent_odom_scan"] > 0,
            "p99_below_100_ms": p99 is not None and p99 < LATENCY_TARGET_MS,
            "both_cores_in_use": cores is not None and cores > 1.0,
            "swarm_on_schedule": (result["swarm_behind_max_s"] or 0.0) < args.behind_limit_s}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robots", default="200", help="robot counts to run, comma-separated (largest first)")
    parser.add_argument("--search", action="store_true",
                        help="stop at the first robot count that meets the latency and loss target")
    parser.add_argument("--rate", type=float, default=10.0, help="scan (and odometry) rate of every robot (Hz)")
    parser.add_argument("--duration", type=float, default=60.0, help="seconds of robot time, published at real time")
    parser.add_argument("--particles", type=int, default=100)
    parser.add_argument("--association", default="shared")
    parser.add_argument("--world", default="arena")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--warmup", type=float, default=10.0, help="seconds of publishing left out of the figures")
    parser.add_argument("--drain-s", type=float, default=120.0, help="longest wait for central to drain its queue")
    parser.add_argument("--behind-limit-s", type=float, default=0.5,
                        help="the swarm is on schedule while it runs less than this far behind (s)")
    parser.add_argument("--single-router", action="store_true", help="one router for both (no mesh)")
    parser.add_argument("--no-workers-run", action="store_true", help="skip the central --workers N run")
    parser.add_argument("--compare-workers", type=int, default=2,
                        help="the first robot count again with central --workers N (central's default is 1)")
    parser.add_argument("--logs", default="reports/swarm_load", help="folder of the processes' logs")
    parser.add_argument("--out", help="also write the JSON here")
    args = parser.parse_args()
    sizes = [int(n) for n in args.robots.split(",")]
    shutdown = Shutdown()
    workers_flag = central_has_workers()
    runs = []
    for index, robots in enumerate(sizes):
        variants = [None] + ([args.compare_workers] if workers_flag and index == 0 and not args.no_workers_run else [])
        for workers in variants:
            if shutdown.is_set():
                break
            run = run_once(robots, workers, args, Path(args.logs), shutdown)
            print(json.dumps({k: run.get(k) for k in ("robots", "workers", "unprocessed", "latency_ms",
                                                      "central_processed_per_s", "central_cpu_ms_per_message", "met")}),
                  file=sys.stderr, flush=True)
            runs.append(run)
        kept_up = [r for r in runs if r["robots"] == robots and r.get("met", {}).get("every_message_processed")
                   and r.get("met", {}).get("p99_below_100_ms")]
        if args.search and kept_up:
            break
    kept_up = [r["robots"] for r in runs if r.get("met") and r["met"]["every_message_processed"]
               and r["met"]["p99_below_100_ms"] and r["met"]["swarm_on_schedule"]]
    emit({"settings": vars(args), "cpus": os.cpu_count(), "central_has_workers": workers_flag, "runs": runs,
          "largest_robots_kept_up": max(kept_up, default=None)}, args.out)


if __name__ == "__main__":
    main()
