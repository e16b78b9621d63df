"""Soak: a whole fleet for a long stretch of robot time; does memory grow, does latency drift, is anything lost?

Starts, as ``fleetslam demo`` does (services.launcher's ``Fleet`` and ``SERVICES``), a router, every service
(association, central FastSLAM, D-SLAM, MCL, the evaluator) with its default settings, and ``--robots``
simulated robots (the last ``--unknown-start-robots`` of them announce no start pose, so MCL has work) for
``--robot-minutes`` of robot time at ``--speedup``. Meanwhile it samples each service's resident memory
(/proc/PID/status VmRSS) every ``--rss-period-s`` and reads every ``{prefix}/*/stats``. When the robots are done
it waits for the services to empty their queues, stops everything and prints JSON: per service the RSS at 10 %
of the run and at the end and the growth in %, the latency p99 (and median) in the first and the last fifth of
the run, messages lost (the services' ``missing`` seq gaps; the central service's processed count against what
the robots say they sent), rejections by reason, the wall time. A progress line goes to stderr every ~30 s.
Variables FLEETSLAM_* of the caller are not passed on: every process runs with its defaults.

    .venv/bin/python benchmarks/soak.py --robots 10 --robot-minutes 30 --speedup 5 --out reports/soak.json
"""

from __future__ import annotations

import argparse
import ast
import re
import socket
import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from schemas.codec import DecodeError, decode  # noqa: E402
from schemas.config import DemoSettings, FleetSettings  # noqa: E402
from schemas.messages import ServiceStats  # noqa: E402
from schemas.transport import Shutdown, open_session  # noqa: E402
from services.credentials import WORLD_USER  # noqa: E402
from services.launcher import SERVICES, Child, Fleet  # noqa: E402
from report import emit  # noqa: E402

PREFIX = "soak"
PROGRESS_PERIOD_S = 30.0
ROBOT_DONE = re.compile(r"robot (\S+) done: odom (\d+), scan (\d+), truth (\d+)")
CENTRAL_PROCESSED = re.compile(r"central: processed (\{[^}]*\})")
STATS_NAMES = {spec.stats_name or spec.name: spec.name for spec in SERVICES}  # name in the stats key -> process


@dataclass
class StatsRecord:
    """One ServiceStats as received, at ``t`` (time.monotonic() on arrival)."""

    t: float
    service: str  # the process name (``evaluate``, not ``eval``)
    stats: ServiceStats


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class StatsLog:
    """Every ServiceStats under ``{prefix}/*/stats``, time-stamped on arrival (a Zenoh callback thread)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.records: list[StatsRecord] = []
        self.undecodable = 0

    def on_sample(self, sample) -> None:
        try:
            stats = decode(sample.payload.to_bytes(), ServiceStats)
        except DecodeError:
            with self.lock:
                self.undecodable += 1
            return
        with self.lock:
            self.records.append(StatsRecord(time.monotonic(), STATS_NAMES.get(stats.service, stats.service), stats))

    def snapshot(self) -> list[StatsRecord]:
        with self.lock:
            return list(self.records)

    def last(self) -> dict[str, ServiceStats]:
        """The latest stats of each service."""
        return {r.service: r.stats for r in self.snapshot()}


def window_median(values: list[tuple[float, float]], start: float, end: float) -> float | None:
    """Median of the values whose time is in [start, end] (None when none is)."""
    inside = [v for t, v in values if start <= t <= end]
    return round(float(np.median(inside)), 3) if inside else None


def change_pct(before: float | None, after: float | None) -> float | None:
    if before is None or after is None or before <= 0:
        return None
    return round(100.0 * (after - before) / before, 1)


def nearest(samples: list[tuple[float, float]], t: float) -> float | None:
    """The sample value taken nearest to time ``t``."""
    return min(samples, key=lambda s: abs(s[0] - t))[1] if samples else None


def rss_summary(rss: dict[str, list[tuple[float, float]]], run_s: float) -> dict:
    """Per process: RSS (MB) at 10 % of the run, at the end (the last sample), its growth, and the peak."""
    out = {}
    for name, samples in rss.items():
        at_10 = nearest([s for s in samples if s[0] >= 0.0], 0.1 * run_s)
        end = samples[-1][1] if samples else None
        out[name] = {"at_10pct_mb": at_10, "end_mb": end, "growth_pct": change_pct(at_10, end),
                     "max_mb": max((v for _, v in samples), default=None), "samples": len(samples)}
    return out


def latency_summary(records: list[StatsRecord], t0: float, run_s: float) -> dict:
    """Per service: the median over its stats of latency p99 (and of the median) in the first and in the last
    fifth of the run (from ``t0`` for ``run_s`` seconds), and the drift between them in %; the deepest queue it
    reported from ``t0`` on."""
    out = {}
    for name in sorted({r.service for r in records}):
        mine = [r for r in records if r.service == name and r.t >= t0]
        if not mine:
            continue
        figures = {}
        for field in ("latency_ms_p99", "latency_ms_median"):
            series = [(r.t - t0, getattr(r.stats, field)) for r in mine]
            first = window_median(series, 0.0, run_s / 5.0)
            last = window_median(series, run_s * 4.0 / 5.0, run_s)
            short = field.removeprefix("latency_ms_")
            figures.update({f"{short}_first_fifth_ms": first, f"{short}_last_fifth_ms": last,
                            f"{short}_drift_pct": change_pct(first, last)})
        figures["queue_depth_max"] = max(r.stats.queue_depth for r in mine)
        figures["stats_received"] = len(mine)
        out[name] = figures
    return out


def robots_sent(robots: list[Child]) -> dict[str, dict[str, int]]:
    """What each robot says it sent, from its ``done: odom N, scan N, truth N`` log line."""
    sent = {}
    for child in robots:
        found = ROBOT_DONE.search(child.log_path.read_text())
        if found:
            sent[found.group(1)] = dict(zip(("odom", "scan", "truth"), map(int, found.groups()[1:])))
    return sent


def central_processed(child: Child | None, last: ServiceStats | None) -> tuple[dict[str, int] | None, str]:
    """Odometry and scans the central service processed per robot, from its exit log line (after its final
    flush); else the total of its last stats (``extra['processed']``) under the key ``*``."""
    if child is not None:
        found = CENTRAL_PROCESSED.search(child.log_path.read_text())
        if found:
            return {str(k): int(v) for k, v in ast.literal_eval(found.group(1)).items()}, "exit log"
    if last is not None and "processed" in last.extra:
        return {"*": int(last.extra["processed"])}, "last stats"
    return None, "none"


def losses(last: dict[str, ServiceStats], sent: dict[str, dict[str, int]], central: Child | None) -> dict:
    missing = {name: int(stats.extra["missing"]) for name, stats in last.items() if "missing" in stats.extra}
    processed, source = central_processed(central, last.get("central"))
    sent_total = sum(c["odom"] + c["scan"] for c in sent.values())
    out = {"missing_by_service": missing, "missing_total": sum(missing.values()),
           "central": {"sent_odom_scan": sent_total, "processed_from": source}}
    if processed is not None:
        out["central"].update(processed=sum(processed.values()), unprocessed=sent_total - sum(processed.values()))
        if "*" not in processed:
            out["central"]["per_robot"] = {rid: {"sent": c["odom"] + c["scan"], "processed": processed.get(rid, 0)}
                                           for rid, c in sorted(sent.items())}
    return out


def rejections(last: dict[str, ServiceStats]) -> dict:
    by_reason: Counter = Counter()
    for stats in last.values():
        by_reason.update(stats.rejected)
    return {"by_service": {name: dict(stats.rejected) for name, stats in sorted(last.items()) if stats.rejected},
            "by_reason": dict(by_reason)}


def progress_line(elapsed: float, expected: float, running: int, rss: dict, last: dict[str, ServiceStats]) -> str:
    memory = " ".join(f"{name} {samples[-1][1]:.0f}" for name, samples in rss.items() if samples)
    p99 = " ".join(f"{name} {stats.latency_ms_p99:.0f}" for name, stats in sorted(last.items()))
    queued = sum(stats.queue_depth for stats in last.values())
    missing = sum(int(stats.extra.get("missing", 0)) for stats in last.values())
    return (f"soak {elapsed:.0f}/{expected:.0f} s: {running} robots running; RSS MB {memory}; p99 ms {p99}; "
            f"queued {queued}; missing {missing}")


def drained(log: StatsLog, names: list[str], since: float) -> bool:
    """Every service has sent stats after ``since`` (time.monotonic()) with nothing left in its queue."""
    latest = {r.service: r for r in log.snapshot() if r.t >= since}
    return all(name in latest and latest[name].stats.queue_depth == 0 for name in names)


def run_soak(args: argparse.Namespace, shutdown: Shutdown) -> dict:
    out = Path(args.logs)
    out.mkdir(parents=True, exist_ok=True)
    from services.evaluation.report import clear_report  # matplotlib: only when a soak runs

    clear_report(out / "report")
    settings = DemoSettings(port=free_port(), prefix=PREFIX, out=str(out), secrets_dir=str(out / "secrets"))
    fleet = Fleet(settings, out)
    fleet.env = {k: v for k, v in fleet.env.items()
                 if not k.startswith("FLEETSLAM_") or k in ("FLEETSLAM_ZENOH_CONNECT", "FLEETSLAM_PREFIX")}
    robot_s = args.robot_minutes * 60.0
    expected_s = robot_s / args.speedup
    result: dict = {"settings": {**{k: v for k, v in vars(args).items() if k not in ("out",)},
                                 "prefix": PREFIX, "endpoint": fleet.endpoint}, "logs": str(out)}
    started = time.monotonic()
    stats_log = StatsLog()
    rss: dict[str, list[tuple[float, float]]] = {}
    session = subscriber = None
    robots: list[Child] = []
    services: list[Child] = []
    robot_ids = [f"r{i + 1}" for i in range(args.robots)]
    router = fleet.start("router", *fleet.router_words(robot_ids))  # secured, as the demo's and compose's
    try:
        fleet.wait_for_router()
        services = [fleet.start(s.name, s.name, *(a.format(out=out) for a in s.args), user=s.name) for s in SERVICES]
        fleet.start(WORLD_USER, "world", "--world", args.world, "--seed", str(args.seed), user=WORLD_USER)  # true map
        rss = {child.name: [] for child in [*services, router]}
        session = open_session(FleetSettings(zenoh_connect=fleet.endpoint, prefix=PREFIX,
                                             **fleet.credentials("monitor")))
        subscriber = session.declare_subscriber(f"{PREFIX}/*/stats", stats_log.on_sample)
        result["services_ready_s"] = round(fleet.wait_for_services(list(STATS_NAMES), shutdown), 2)
        known = args.robots - args.unknown_start_robots
        robots = [fleet.start(rid, "robot", "--id", rid, "--world", args.world, "--seed", str(args.seed),
                              "--rate", str(args.rate), "--speedup", str(args.speedup), "--duration", f"{robot_s:g}",
                              "--start-delay", "1.0", "--no-publish-world", *(["--unknown-start"] if i >= known else []),
                              user=rid)
                  for i, rid in enumerate(robot_ids) if not shutdown.is_set()]
        t0 = time.monotonic()
        deadline = t0 + expected_s + args.grace_s
        next_sample = next_progress = t0

        def sample_rss() -> None:
            now = time.monotonic()
            for child in [*services, router]:
                mb = fleet.memory_mb(child)
                if mb is not None:
                    rss[child.name].append((round(now - t0, 2), round(mb, 1)))

        while any(r.process.poll() is None for r in robots) and time.monotonic() < deadline:
            now = time.monotonic()
            if now >= next_sample:
                sample_rss()
                next_sample += args.rss_period_s
            if now >= next_progress:
                running = sum(r.process.poll() is None for r in robots)
                print(progress_line(now - t0, expected_s, running, rss, stats_log.last()), file=sys.stderr, flush=True)
                next_progress += PROGRESS_PERIOD_S
            dead = [c.name for c in services if c.process.poll() is not None]
            if dead:
                result["died"] = dead
                break
            if shutdown.wait(min(next_sample, next_progress) - time.monotonic()):
                break
        if shutdown.is_set():
            result["interrupted"] = shutdown.signal_name or "stopped"
        run_s = time.monotonic() - t0
        running = sum(r.process.poll() is None for r in robots)
        print(progress_line(run_s, expected_s, running, rss, stats_log.last()), file=sys.stderr, flush=True)
        result["run_wall_s"], result["expected_run_wall_s"] = round(run_s, 1), round(expected_s, 1)
        result["robots_unfinished"] = [r.name for r in robots if r.process.poll() is None]
        result["stop_s"] = fleet.stop(robots)
        drain_started = time.monotonic()
        while not shutdown.is_set() and time.monotonic() - drain_started < args.drain_s:
            if drained(stats_log, [c.name for c in services], drain_started):
                result["drain_s"] = round(time.monotonic() - drain_started, 1)
                break
            shutdown.wait(0.2)
        else:
            result["drain_s"] = None  # a queue was still not empty (or the soak was interrupted)
        sample_rss()
        evaluators = [c for c in services if c.name == "evaluate"]
        result["stop_s"].update(fleet.stop([c for c in services if c not in evaluators], timeout=30.0))
        result["stop_s"].update(fleet.stop(evaluators, timeout=60.0))
    finally:
        if subscriber is not None:
            subscriber.undeclare()
        if session is not None:
            session.close()
        remaining = [c for c in fleet.children if c.process.poll() is None and c is not router]
        if remaining:
            fleet.stop(remaining)
        fleet.stop([router])
    records = stats_log.snapshot()
    last = {r.service: r.stats for r in records}
    sent = robots_sent(robots)
    central = next((c for c in services if c.name == "central"), None)
    run_s = result.get("run_wall_s", 0.0)
    result.update(
        rss=rss_summary(rss, run_s), latency=latency_summary(records, t0, run_s),
        losses=losses(last, sent, central), rejected=rejections(last),
        robots_sent=sent, robots_without_done_line=sorted({r.name for r in robots} - set(sent)),
        stats_undecodable=stats_log.undecodable, exit_codes=fleet.exit_codes, killed=fleet.killed,
        stop_s={name: round(took, 2) for name, took in result.get("stop_s", {}).items()},
        wall_s=round(time.monotonic() - started, 1),
    )
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robots", type=int, default=10, help="simulated robots")
    parser.add_argument("--unknown-start-robots", type=int, default=1,
                        help="how many of the robots announce no start pose (MCL has to find them)")
    parser.add_argument("--robot-minutes", type=float, default=30.0, help="minutes of robot time each robot runs")
    parser.add_argument("--speedup", type=float, default=5.0, help="robot speed-up over real time")
    parser.add_argument("--seed", type=int, default=0, help="seed of the world and of every robot")
    parser.add_argument("--world", default="arena",
                        help="simulated world (arena: 15 landmarks, start poses for any number of robots; its map is "
                        "complete within minutes, so memory that grows after that is not the map)")
    parser.add_argument("--rate", type=float, default=10.0, help="scan rate of every robot (Hz)")
    parser.add_argument("--rss-period-s", type=float, default=5.0, help="wall seconds between RSS samples")
    parser.add_argument("--drain-s", type=float, default=120.0,
                        help="wall seconds to wait, after the robots are done, for the services to empty their queues")
    parser.add_argument("--grace-s", type=float, default=120.0,
                        help="wall seconds the robots may overrun their expected time before they are stopped")
    parser.add_argument("--logs", default="reports/soak", help="folder for the processes' logs, maps and report")
    parser.add_argument("--out", help="also write the JSON here")
    args = parser.parse_args()
    if not 0 <= args.unknown_start_robots <= args.robots:
        parser.error("--unknown-start-robots must be between 0 and --robots")
    shutdown = Shutdown()
    try:
        result = run_soak(args, shutdown)
    except RuntimeError as error:  # a process that did not start
        raise SystemExit(f"soak failed: {error}") from None
    emit(result, args.out)


if __name__ == "__main__":
    main()
