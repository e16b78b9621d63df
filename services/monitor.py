"""``fleetslam monitor``: a live console of everything under ``{prefix}/**``.

Shows the robots alive (liveliness), each robot's message counts and rates per
stream, seq gaps, rejected messages by reason (malformed payloads, wrong
schema, duplicates, time going backwards...), every service's latest stats
and the other keys seen. A malformed payload is counted, never fatal.

A robot whose liveliness token went away and whose streams start again at
seq 0 is a new run of it, recognised as the services recognise it
(:meth:`~schemas.streams.StreamTracker.leave` and
:meth:`~schemas.streams.StreamTracker.new_run`), not a burst of out-of-order
messages. Its ``restarts`` go up by one; its message counts and seq gaps
(``missing``) go on adding up over its runs, so that they compare with the
services' own counts of messages taken in (``fleetslam demo`` does). A robot
whose streams go back to seq 0 while its token stays is not a new run: those
messages are refused as out of order.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from collections import Counter, defaultdict, deque
from pathlib import Path

import zenoh
from rich.console import Console, Group
from rich.live import Live
from rich.table import Table

from schemas.codec import decode
from schemas.config import MonitorSettings, add_settings_arguments, settings_from_args
from schemas.messages import RobotInfo, ServiceStats
from schemas.recording import KIND_MODELS, ROBOT_KINDS
from schemas.streams import StreamTracker, Verdict
from services.runtime import ServiceShell

log = logging.getLogger("fleetslam.monitor")

ROBOT_MESSAGES = {kind: KIND_MODELS[kind] for kind in ROBOT_KINDS}  # the model each robot stream carries


class Monitor(ServiceShell):
    """Counts and checks every message of the fleet; renders a table."""

    name = "monitor"

    def __init__(self, settings: MonitorSettings, console: Console | None = None):
        super().__init__(settings)
        self.tick_period_s = 1.0 / settings.refresh_hz
        self.console = console or Console(stderr=False)
        self.tracker = StreamTracker(missing_before_join=False)  # it joins a running fleet: count only later losses
        self.alive: dict[str, bool] = {}
        self.infos: dict[str, RobotInfo] = {}
        self.counts: dict[str, Counter] = defaultdict(Counter)
        self.missing_in_earlier_runs: Counter = Counter()  # seq gaps of runs the tracker forgot (robot id -> count)
        self.arrivals: dict[tuple[str, str], deque] = defaultdict(lambda: deque(maxlen=5000))
        self.services: dict[str, ServiceStats] = {}
        self.topics: Counter = Counter()
        self.live: Live | None = None
        self._last_plain = 0.0

    def setup(self, session: zenoh.Session) -> None:
        self.subscribe(self.keys.everything, "sample")
        self._declared.append(
            session.liveliness().declare_subscriber(self.keys.alive_any, self._on_liveliness, history=True)
        )
        if not self.settings.plain:
            self.live = Live(self.render(), console=self.console, refresh_per_second=self.settings.refresh_hz)
            self.live.start()

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        parsed = self.keys.parse_robot_key(str(sample.key_expr))
        if parsed:
            kind = b"1" if sample.kind == zenoh.SampleKind.PUT else b"0"
            self.enqueue("alive", parsed[0], kind)

    async def handle(self, tag: str, key: str, payload: bytes) -> None:
        if tag == "alive":
            self.alive[key] = payload == b"1"
            if payload == b"0":
                self.tracker.leave(key)
                log.info("robot %s left (liveliness lost)", key)
            return
        parsed = self.keys.parse_robot_key(key)
        if parsed is None:
            if key.endswith("/stats"):
                stats = decode(payload, ServiceStats)
                self.services[f"{stats.service}:{stats.instance}"] = stats
            else:
                self.topics[key] += 1
            return
        robot_id, stream = parsed
        model = ROBOT_MESSAGES.get(stream)
        if model is None:
            self.reject("unknown_stream", key)
            return
        message = decode(payload, model)
        if message.robot_id != robot_id:
            self.reject("robot_id_mismatch", f"{key} carries {message.robot_id}")
            return
        if isinstance(message, RobotInfo):
            self.infos[robot_id] = message
            self.counts[robot_id]["info"] += 1
            return
        if message.seq == 0:  # perhaps a new run: keep its robot's seq gaps before the tracker forgets them
            missing = self.tracker.missing(robot_id)
            if self.tracker.new_run(robot_id, stream, message.seq):
                self.new_run(robot_id, missing)
        verdict = self.tracker.check(robot_id, stream, message.seq, message.stamp)
        if verdict is not Verdict.ACCEPT:
            self.reject(verdict.value, f"{key} seq {message.seq}")
            return
        self.counts[robot_id][stream] += 1
        self.arrivals[(robot_id, stream)].append(time.monotonic())

    def new_run(self, robot_id: str, missing: int) -> None:
        """A robot that left started again at seq 0 (the tracker forgot its streams): count the restart and keep
        the ``missing`` messages of the run that ended."""
        self.counts[robot_id]["restarts"] += 1
        self.missing_in_earlier_runs[robot_id] += missing
        log.info("robot %s started a new run", robot_id)

    def missing(self, robot_id: str) -> int:
        """Messages of the robot lost on the way (seq gaps), over all its runs."""
        return self.tracker.missing(robot_id) + self.missing_in_earlier_runs[robot_id]

    def rate(self, robot_id: str, stream: str) -> float:
        times = self.arrivals.get((robot_id, stream))
        if not times:
            return 0.0
        now = time.monotonic()
        window = self.settings.rate_window_s
        return sum(1 for t in times if now - t <= window) / window

    def render(self) -> Group:
        robots = Table(title="robots", expand=False)
        for column in ("robot", "alive", "source", "odom", "scan", "truth", "odom Hz", "scan Hz", "missing",
                       "restarts"):
            robots.add_column(column, justify="right" if column not in ("robot", "source") else "left")
        for rid in sorted(set(self.counts) | set(self.alive) | set(self.infos)):
            c = self.counts[rid]
            info = self.infos.get(rid)
            robots.add_row(
                rid, "yes" if self.alive.get(rid) else "no", info.source if info else "?",
                str(c["odom"]), str(c["scan"]), str(c["truth"]),
                f"{self.rate(rid, 'odom'):.1f}", f"{self.rate(rid, 'scan'):.1f}", str(self.missing(rid)),
                str(c["restarts"]),
            )
        rejected = Table(title="rejected")
        rejected.add_column("reason")
        rejected.add_column("count", justify="right")
        for reason, n in sorted(self.rejected.items()):
            rejected.add_row(reason, str(n))
        services = Table(title="services")
        for column in ("service", "in", "rejected", "published", "latency ms (median/p99)", "queue"):
            services.add_column(column)
        for name, s in sorted(self.services.items()):
            services.add_row(name, str(sum(s.messages_in.values())), str(sum(s.rejected.values())), str(s.published),
                             f"{s.latency_ms_median:.2f}/{s.latency_ms_p99:.2f}", str(s.queue_depth))
        return Group(robots, rejected, services)

    async def tick(self) -> None:
        if self.live is not None:
            self.live.update(self.render())
        elif time.monotonic() - self._last_plain >= 2.0:
            self._last_plain = time.monotonic()
            for rid in sorted(self.counts):
                c = self.counts[rid]
                print(f"monitor {rid} alive={self.alive.get(rid, False)} odom={c['odom']} scan={c['scan']} "
                      f"truth={c['truth']} missing={self.missing(rid)} restarts={c['restarts']}", flush=True)
            if self.rejected:
                print(f"monitor rejected {dict(self.rejected)}", flush=True)

    def summary(self) -> dict:
        return {
            "robots": {
                rid: {**{s: self.counts[rid][s] for s in ("info", "odom", "scan", "truth", "restarts")},
                      "missing": self.missing(rid), "alive": self.alive.get(rid, False)}
                for rid in sorted(self.counts)
            },
            "robot_restarts": sum(counts["restarts"] for counts in self.counts.values()),
            "rejected": dict(self.rejected),
            "services": {name: s.model_dump(mode="json") for name, s in self.services.items()},
            "topics": dict(self.topics),
        }

    def on_stop(self) -> None:
        if self.live is not None:
            self.live.update(self.render())
            self.live.stop()
        if self.settings.json_out:
            path = Path(self.settings.json_out)
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps(self.summary(), indent=2))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, MonitorSettings)


def main(args: argparse.Namespace) -> int:
    return Monitor(settings_from_args(MonitorSettings, args)).serve()
