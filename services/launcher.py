"""``fleetslam demo``: a whole fleet on this machine, as separate processes.

Starts a router, the services that exist in this installation, the monitor (and with ``--viz`` the live
Rerun view, ``fleetslam viz``), the world's true map (``fleetslam world``) and ``--robots`` simulated robots in
one world (plus ``--unknown-start-robots`` that announce no start pose, for MCL to find); lets the robots run for
``--duration`` wall seconds; stops everything in order (robots, services,
monitor, router) with SIGTERM; then prints per-robot message counts, service
statistics, the memory of each process, and where the logs and results are.

The fleet is secured unless ``--open``: the router makes one password per
robot and service in ``--secrets-dir`` on the first run (reused after) and
denies by default; each process logs in as itself (a robot as its id, a
service as its name, the world map as ``world``), so a process without
credentials is refused.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from rich.console import Console
from rich.table import Table

from schemas.config import DemoSettings, add_settings_arguments, settings_from_args
from schemas.transport import Shutdown
from services.credentials import WORLD_USER

log = logging.getLogger("fleetslam.demo")


@dataclass
class ServiceSpec:
    """A service the demo starts: ``fleetslam NAME ARGS...``

    ``{out}`` in an argument becomes the demo's output folder.
    """

    name: str
    args: list[str] = field(default_factory=list)
    stats_name: str | None = None  # the service's name in {prefix}/{name}/stats, when it differs


SERVICES: list[ServiceSpec] = [
    ServiceSpec("assoc"),
    ServiceSpec("central", ["--map-out", "{out}/maps/central.json"]),
    ServiceSpec("dslam", ["--association", "auto", "--map-out", "{out}/maps/dslam.json"]),
    ServiceSpec("mcl"),
    ServiceSpec("evaluate", ["--out", "{out}/report"], stats_name="eval"),
]


# Set per process by the launcher (its own credentials), never inherited from the launcher's environment.
CREDENTIAL_VARIABLES = ("FLEETSLAM_ZENOH_USER", "FLEETSLAM_ZENOH_PASSWORD", "FLEETSLAM_ZENOH_PASSWORD_FILE",
                        "FLEETSLAM_SECRETS_DIR", "FLEETSLAM_ROUTER_CONFIG")
VIZ_WEB_PORT, VIZ_GRPC_PORT = 9090, 9876  # fleetslam viz's defaults: web viewer (HTTP) and its data (gRPC)


@dataclass
class Child:
    name: str
    process: subprocess.Popen
    log_path: Path


class Fleet:
    """Starts, watches and stops the demo's processes."""

    def __init__(self, settings: DemoSettings, out: Path):
        self.settings = settings
        self.out = out
        self.children: list[Child] = []
        self.exit_codes: dict[str, int] = {}  # exit code of every stopped process (0: a clean stop on SIGTERM)
        self.killed: list[str] = []  # processes that had to be killed after the stop timeout
        self.endpoint = f"tcp/127.0.0.1:{settings.port}"
        self.secrets = None if settings.open else Path(settings.secrets_dir).resolve()
        inherited = {k: v for k, v in os.environ.items() if k not in CREDENTIAL_VARIABLES}
        self.env = {**inherited, "FLEETSLAM_ZENOH_CONNECT": self.endpoint, "FLEETSLAM_PREFIX": settings.prefix,
                    "PYTHONUNBUFFERED": "1"}

    def credentials(self, user: str | None) -> dict[str, str]:
        """``user``'s login (its password file in the secrets folder); none for an open fleet."""
        if self.secrets is None or user is None:
            return {}
        return {"zenoh_user": user, "zenoh_password_file": str(self.secrets / f"{user}.password")}

    def router_words(self, robot_ids: list[str]) -> list[str]:
        """``fleetslam router`` on the demo's endpoint: secured with a user per robot (and the default services)."""
        words = ["router", "--listen", self.endpoint]
        if self.secrets is not None:
            words += ["--secrets-dir", str(self.secrets), "--robot-users", ",".join(robot_ids)]
        return words

    def start(self, name: str, *words: str, user: str | None = None) -> Child:
        """``fleetslam WORDS...`` logging in as ``user`` (a secured fleet)."""
        log_path = self.out / "logs" / f"{name}.log"
        log_path.parent.mkdir(parents=True, exist_ok=True)
        handle = open(log_path, "w")
        env = {**self.env, **{f"FLEETSLAM_{k.upper()}": v for k, v in self.credentials(user).items()}}
        process = subprocess.Popen([sys.executable, "-m", "services.cli", *words], env=env, stdout=handle,
                                   stderr=subprocess.STDOUT, start_new_session=True)
        child = Child(name, process, log_path)
        self.children.append(child)
        return child

    def wait_for_router(self, timeout: float = 10.0) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                with socket.create_connection(("127.0.0.1", self.settings.port), timeout=0.2):
                    return
            except OSError:
                if self.children[0].process.poll() is not None:
                    raise RuntimeError(f"router exited; see {self.children[0].log_path}") from None
                time.sleep(0.05)
        raise RuntimeError(f"router did not listen on {self.endpoint} within {timeout} s")

    def wait_for_services(self, names: list[str], shutdown: Shutdown, timeout: float = 60.0) -> float:
        """Wait until every named service publishes its stats (it has subscribed), so robots start to a ready fleet."""
        from schemas.config import FleetSettings
        from schemas.transport import session_scope

        seen: set[str] = set()
        started = time.monotonic()
        settings = FleetSettings(zenoh_connect=self.endpoint, prefix=self.settings.prefix,
                                 **self.credentials("monitor"))
        with session_scope(settings) as session:
            subscriber = session.declare_subscriber(
                f"{self.settings.prefix}/*/stats", lambda sample: seen.add(str(sample.key_expr).split("/")[-2])
            )
            try:
                while not set(names) <= seen and time.monotonic() - started < timeout:
                    dead = [c.name for c in self.children if c.process.poll() is not None]
                    if dead:
                        raise RuntimeError(f"{', '.join(dead)} exited at start; see {self.out / 'logs'}")
                    if shutdown.wait(0.1):
                        break
            finally:
                subscriber.undeclare()
        missing = sorted(set(names) - seen)
        if missing:
            log.warning("no stats from %s after %.0f s; starting the robots anyway", ", ".join(missing), timeout)
        return time.monotonic() - started

    @staticmethod
    def memory_mb(child: Child) -> float | None:
        try:
            for line in Path(f"/proc/{child.process.pid}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
        except OSError:
            return None
        return None

    def stop(self, children: list[Child], timeout: float = 10.0) -> dict[str, float]:
        """SIGTERM, then wait; SIGKILL what does not exit. Returns seconds each took to exit."""
        started = time.monotonic()
        for child in children:
            if child.process.poll() is None:
                child.process.send_signal(signal.SIGTERM)
        took = {}
        for child in children:
            try:
                child.process.wait(timeout=max(0.1, timeout - (time.monotonic() - started)))
            except subprocess.TimeoutExpired:
                log.warning("%s did not stop in %.0f s; killing it", child.name, timeout)
                os.killpg(child.process.pid, signal.SIGKILL)
                child.process.wait()
                self.killed.append(child.name)
            took[child.name] = time.monotonic() - started
            self.exit_codes[child.name] = child.process.returncode
        return took


def run_demo(settings: DemoSettings, shutdown: Shutdown, console: Console) -> dict:
    from services.evaluation.report import clear_report  # matplotlib: only when a demo runs

    out = Path(settings.out)
    out.mkdir(parents=True, exist_ok=True)
    cleared = clear_report(out / "report")
    for stale in (out / "maps").glob("*.json"):  # the maps of an earlier demo
        stale.unlink()
    if cleared:
        log.info("removed %d files of an earlier demo report from %s", cleared, out / "report")
    fleet = Fleet(settings, out)
    services = SERVICES
    summary: dict = {"settings": settings.model_dump(mode="json"), "services": [s.name for s in services],
                     "secured": fleet.secrets is not None}
    robot_ids = [f"r{i + 1}" for i in range(settings.robots + settings.unknown_start_robots)]
    guests = [rid for rid in settings.guest_robots.split(",") if rid and rid not in robot_ids]
    router = fleet.start("router", *fleet.router_words(robot_ids + guests))
    try:
        fleet.wait_for_router()
        monitor = fleet.start("monitor", "monitor", "--plain", "--json-out", str(out / "monitor.json"), user="monitor")
        viewers = [fleet.start("viz", "viz", "--serve", str(VIZ_WEB_PORT), "--grpc-port", str(VIZ_GRPC_PORT),
                               "--save", str(out / "fleet.rrd"), user="viz")] if settings.viz else []
        recorders = [fleet.start("record", "record", "--out", settings.record, user="record")] if settings.record else []
        service_children = [fleet.start(s.name, s.name, *(a.format(out=settings.out) for a in s.args), user=s.name)
                            for s in services]
        world = fleet.start(WORLD_USER, "world", "--world", settings.world, "--seed", str(settings.seed),
                            user=WORLD_USER)
        ready_s = fleet.wait_for_services(["monitor", *(c.name for c in viewers), *(c.name for c in recorders),
                                           *(s.stats_name or s.name for s in services)], shutdown)
        if viewers:
            from services.viz.recording import web_viewer_url

            console.print(f"live view: {web_viewer_url(VIZ_WEB_PORT, VIZ_GRPC_PORT)} (recording to {out / 'fleet.rrd'})")
        summary["services_ready_s"] = ready_s
        robot_duration = settings.duration * settings.speedup
        robots = [
            fleet.start(rid, "robot", "--id", rid, "--world", settings.world, "--seed", str(settings.seed),
                        "--rate", str(settings.rate), "--speedup", str(settings.speedup),
                        "--duration", f"{robot_duration:g}", "--start-delay", "1.0", "--no-publish-world",
                        "--fleet", ",".join(robot_ids),
                        *(["--unknown-start"] if i >= settings.robots else []), user=rid)
            for i, rid in enumerate(robot_ids)
        ]
        access = (f"secured (a password per process, made once in {fleet.secrets})" if fleet.secrets is not None
                  else "[bold red]OPEN[/] (--open: no passwords, no access control)")
        console.print(f"[bold]fleetslam demo[/]: router {fleet.endpoint} {access}, {settings.robots} robots "
                      f"(+{settings.unknown_start_robots} with no start pose) in world "
                      f"'{settings.world}', services: {', '.join(s.name for s in services) or 'none yet'}; "
                      f"{settings.duration:g} s (Ctrl-C stops early)")
        if guests and fleet.secrets is not None:
            console.print(f"a robot of your own joins as {guests[0]}: FLEETSLAM_ZENOH_CONNECT={fleet.endpoint} "
                          f"FLEETSLAM_ZENOH_USER={guests[0]} FLEETSLAM_ZENOH_PASSWORD_FILE="
                          f"{fleet.secrets / (guests[0] + '.password')} (services.client.RobotLink, docs/robots.md)")
        started = time.monotonic()
        deadline = started + settings.duration + 15.0
        memory: dict[str, float | None] = {}
        while any(r.process.poll() is None for r in robots) and time.monotonic() < deadline:
            if shutdown.wait(0.5):
                console.print("interrupted: stopping the fleet")
                break
            if not memory and time.monotonic() > deadline - settings.duration - 12.0:
                memory = {c.name: fleet.memory_mb(c) for c in fleet.children}
        summary["elapsed_s"] = time.monotonic() - started
        memory = {c.name: fleet.memory_mb(c) for c in fleet.children} if not memory else memory
        summary["memory_mb"] = memory
        summary["stop_s"] = fleet.stop(robots)
        evaluators = [c for c in service_children if c.name == "evaluate"]
        summary["stop_s"].update(fleet.stop([c for c in service_children if c not in evaluators], timeout=15.0))
        summary["stop_s"].update(fleet.stop(evaluators, timeout=30.0))
        summary["stop_s"].update(fleet.stop([world, monitor, *viewers, *recorders]))
    finally:
        remaining = [c for c in fleet.children if c.process.poll() is None and c is not router]
        if remaining:
            fleet.stop(remaining)
        summary.setdefault("stop_s", {}).update(fleet.stop([router]))
        summary["exit_codes"], summary["killed"] = fleet.exit_codes, fleet.killed
    monitor_path = out / "monitor.json"
    summary["monitor"] = json.loads(monitor_path.read_text()) if monitor_path.exists() else {}
    metrics_path = out / "report" / "metrics.json"
    if metrics_path.exists():
        summary["metrics"] = json.loads(metrics_path.read_text())
    summary["problems"] = problems(summary)
    (out / "demo.json").write_text(json.dumps(summary, indent=2))
    return summary


LAG_MEDIAN_MS, LAG_P99_MS = 250.0, 1000.0  # a service slower than this did not keep up with the fleet
ROBOT_STREAM_SERVICES = ("central", "dslam", "mcl")  # services that take every robot's odometry and scans


def problems(summary: dict) -> list[str]:
    """What went wrong in a demo, one line each: services that lagged (latency, a backlog, robot messages they
    never processed), robots that lost messages, robots MCL never localized. Services' figures are their last
    stats (published every second or so), so a shortfall or a backlog of up to two seconds of the fleet's messages
    is not counted: a snapshot taken in the middle of a burst shows a few messages queued in a service that keeps up."""
    monitor = summary.get("monitor", {})
    robots = monitor.get("robots", {})
    elapsed = max(float(summary.get("elapsed_s") or 0.0), 1e-9)
    sent = sum(c["odom"] + c["scan"] for c in robots.values())
    slack = max(10.0, 2.0 * sent / elapsed)  # two seconds of the fleet's messages
    found = []
    for rid, counts in sorted(robots.items()):
        if counts["missing"]:
            found.append(f"robot {rid}: {counts['missing']} messages lost on the way (seq gaps seen by the monitor)")
    for name, stats in sorted(monitor.get("services", {}).items()):
        service = name.split(":")[0]
        median, p99 = stats["latency_ms_median"], stats["latency_ms_p99"]
        if median > LAG_MEDIAN_MS or p99 > LAG_P99_MS:
            found.append(f"{service} lagged: latency median {median:.0f} ms, p99 {p99:.0f} ms")
        if stats.get("queue_depth", 0) > slack:
            found.append(f"{service} had {stats['queue_depth']} messages queued at its last stats")
        if service in ROBOT_STREAM_SERVICES and sent:
            taken = stats["messages_in"].get("odom", 0) + stats["messages_in"].get("scan", 0)
            if sent - taken > slack:
                found.append(f"{service} never processed about {sent - taken} of the {sent} robot messages")
    for rid in summary.get("metrics", {}).get("mcl_never_localized", []):
        found.append(f"MCL never localized robot {rid}: no error figure for it")
    return found


def print_summary(summary: dict, console: Console, settings: DemoSettings) -> None:
    robots = summary.get("monitor", {}).get("robots", {})
    elapsed = float(summary.get("elapsed_s") or settings.duration)
    table = Table(title=f"messages per robot (over {elapsed:.1f} s wall, speed-up {settings.speedup:g})")
    for column in ("robot", "odom", "scan", "truth", "missing", "msg/s"):
        table.add_column(column, justify="right")
    for rid, c in robots.items():
        total = c["odom"] + c["scan"] + c["truth"]
        table.add_row(rid, str(c["odom"]), str(c["scan"]), str(c["truth"]), str(c["missing"]),
                      f"{total / max(elapsed, 1e-9):.1f}")
    console.print(table)
    services = summary.get("monitor", {}).get("services", {})
    if services:
        stable = Table(title="services")
        for column in ("service", "in", "rejected", "published", "latency ms median", "p99"):
            stable.add_column(column, justify="right")
        for name, s in sorted(services.items()):
            stable.add_row(name, str(sum(s["messages_in"].values())), str(sum(s["rejected"].values())),
                           str(s["published"]), f"{s['latency_ms_median']:.2f}", f"{s['latency_ms_p99']:.2f}")
        console.print(stable)
    rejected = summary.get("monitor", {}).get("rejected", {})
    console.print(f"rejected by the monitor: {rejected or 'none'}")
    memory = summary.get("memory_mb", {})
    console.print("memory (RSS MB): " + ", ".join(f"{k} {v:.0f}" for k, v in memory.items() if v is not None))
    console.print("exit after SIGTERM (s): " + ", ".join(f"{k} {v:.2f}" for k, v in summary.get("stop_s", {}).items()))
    results = summary.get("metrics", {}).get("summary", {})
    if results:
        rtable = Table(title="results against truth (live evaluator)")
        for column in ("estimator", "ATE per robot (m)", "ATE aligned (m)", "map RMSE (m)", "landmarks matched/est."):
            rtable.add_column(column, justify="right")
        for estimator, r in sorted(results.items()):
            landmarks = r.get("landmarks") or {}
            rtable.add_row(
                estimator,
                " ".join(f"{k} {v:.3f}" for k, v in (r.get("ate_rmse_m") or {}).items() if v is not None),
                " ".join(f"{k} {v:.3f}" for k, v in (r.get("ate_aligned_rmse_m") or {}).items() if v is not None),
                "-" if r.get("map_rmse_m") is None else f"{r['map_rmse_m']:.3f}",
                f"{landmarks.get('matched', '-')}/{landmarks.get('estimated', '-')}" if landmarks else "-",
            )
        console.print(rtable)
    found = summary.get("problems", [])
    if found:
        console.print(f"[bold red]{len(found)} problem(s):[/]")
        for line in found:
            console.print(f"  - {line}")
    else:
        console.print("[green]no problems[/]: every service kept up, no message was lost, every robot was localized")
    report, maps = Path(settings.out) / "report", Path(settings.out) / "maps"
    saved = ", ".join(sorted(p.name for p in maps.glob("*.json"))) or "none"
    console.print(f"plots (map_*.png, errors.png), TUM trajectories (*.tum) and metrics.json in {report}/; "
                  f"saved maps in {maps}/ ({saved}; start a service from one with --map FILE); "
                  f"logs in {settings.out}/logs; this summary in {settings.out}/demo.json")
    if settings.record:
        done = summary.get("exit_codes", {}).get("record") == 0 and Path(settings.record).is_file()
        console.print(f"recording: {settings.record} (replay: fleetslam replay {settings.record}; offline: fleetslam run "
                      f"--dataset mcap:{settings.record})" if done else
                      f"[bold red]no recording[/]: {settings.record} was not finished; see {settings.out}/logs/record.log")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, DemoSettings)


def main(args: argparse.Namespace) -> int:
    settings = settings_from_args(DemoSettings, args)
    console = Console()
    shutdown = Shutdown()
    if settings.viz:
        from services.viz import rerun_missing

        if missing := rerun_missing():
            log.error("demo --viz: %s", missing)
            return 2
    try:
        summary = run_demo(settings, shutdown, console)
    except RuntimeError as exc:
        log.error("demo failed: %s", exc)
        return 1
    print_summary(summary, console, settings)
    robots = summary.get("monitor", {}).get("robots", {})
    return 0 if len(robots) == settings.robots + settings.unknown_start_robots else 1
