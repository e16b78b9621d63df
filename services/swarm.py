"""``fleetslam swarm``: many simulated robots in one process, so that tests and benchmarks reach hundreds of robots.

Each robot is what ``fleetslam robot`` makes of a simulated robot: its own keys (``{prefix}/robots/{rid}/...``), its
own :class:`~services.client.RobotLink` (reliable BLOCK publishers with caches sized as the robot process sizes them,
the info and history queryables, the liveliness tokens), its own simulator streams (robot ``sK`` draws what
``fleetslam robot --id sK`` draws). What a swarm saves is the rest: one process and one Zenoh session for all of
them, and one loop that publishes every robot's odometry and scans (and truth with ``--publish-truth``) merged in
time order, paced at real time divided by ``--speedup``.

A swarm that cannot keep up says so: every ``--progress-period-s`` it logs the messages sent and how far behind its
schedule it runs (a warning past ``--behind-warning-s``); it never slows its clock down to hide it. SIGINT/SIGTERM
stop it cleanly (every link closed, so every token goes). At the end it logs the counts sent and, with
``--json-out``, writes them per robot and stream.

Robots do not detect each other unless ``--detect-robots``: then the simulator draws robot detections between all
pairs, in one piece, at a cost quadratic in the swarm's size; without, the swarm is simulated ``--simulate-chunk``
robots at a time, at a cost linear in its size (about 0.1 s of one core per robot-minute at 10 Hz).
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

from robots.dataset import Dataset, RobotLog
from robots.simulator import simulate
from robots.worlds import make_world
from schemas.codec import encode
from schemas.config import SwarmSettings, add_settings_arguments, settings_from_args
from schemas.keys import Keys
from schemas.messages import RobotInfo, WorldTruth
from schemas.transport import (Shutdown, StreamPublisher, answer_with, linger_time, paced, run_command, stream_caches,
                               session_scope, undeclare_all)
from services.client import RobotLink

log = logging.getLogger("fleetslam.swarm")

COUNTED = ("odom", "scan", "truth", "info")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, SwarmSettings)


def swarm_ids(settings: SwarmSettings) -> list[str]:
    """The robots' ids, ``PREFIX{first}`` to ``PREFIX{first + robots - 1}``."""
    return [f"{settings.id_prefix}{number}" for number in range(settings.first, settings.first + settings.robots)]


def unknown_starts(settings: SwarmSettings) -> list[bool]:
    """Which robots announce no start pose: the last ``unknown_start`` share of them (rounded to the nearest)."""
    unknown = round(settings.unknown_start * settings.robots)
    return [index >= settings.robots - unknown for index in range(settings.robots)]


def announced_info(robot: RobotLog) -> RobotInfo:
    """The RobotInfo the robot announces: the simulator's, with the motion limits of its controls (as
    ``fleetslam robot`` announces them), so that receivers refuse a control beyond them."""
    limits = {name: limit for name, limit in robot.motion_limits().items() if getattr(robot.info, name) is None}
    return robot.info.model_copy(update=limits)


def simulate_swarm(settings: SwarmSettings, shutdown: Shutdown) -> Dataset | None:
    """Every robot's log (None if stopped meanwhile): one simulation of the whole swarm with ``detect_robots``, else
    ``simulate_chunk`` robots at a time (each robot's data depends on its own streams only, so chunks change
    nothing)."""
    world = make_world(settings.world, settings.seed)
    ids, unknown = swarm_ids(settings), unknown_starts(settings)
    chunk = len(ids) if settings.detect_robots else settings.simulate_chunk
    logs: dict[str, RobotLog] = {}
    started = time.monotonic()
    for begin in range(0, len(ids), chunk):
        if shutdown.is_set():
            return None
        part = slice(begin, begin + chunk)
        simulated = simulate(world, seed=settings.seed, duration=settings.duration, rate=settings.rate,
                             unknown_start=unknown[part], robot_ids=ids[part], robot_detections=settings.detect_robots)
        logs.update(simulated.robots)
        log.info("simulated %d of %d robots (%.1f s)", len(logs), len(ids), time.monotonic() - started)
    for robot in logs.values():
        robot.info = announced_info(robot)
    return Dataset(name=f"sim:{world.name}", robots=logs, landmarks=world.landmarks.copy(),
                   landmark_ids=world.landmark_ids, meta={"world": world.name, "seed": settings.seed})


class Schedule:
    """How far behind its schedule the publishing loop runs: now, at most in the current progress period, at most
    over the run."""

    def __init__(self) -> None:
        self.behind_s = 0.0
        self.period_max_s = 0.0
        self.run_max_s = 0.0

    def note(self, behind_s: float) -> None:
        self.behind_s = max(behind_s, 0.0)
        self.period_max_s = max(self.period_max_s, self.behind_s)
        self.run_max_s = max(self.run_max_s, self.behind_s)

    def next_period(self) -> float:
        """The period's largest lag; a new period starts."""
        period_max, self.period_max_s = self.period_max_s, 0.0
        return period_max


def counts_of(links: list[RobotLink]) -> dict[str, dict[str, int]]:
    """Messages sent per robot and stream."""
    return {link.robot_id: {name: link.counts[name] for name in COUNTED} for link in links}


def total(counts: dict[str, dict[str, int]]) -> dict[str, int]:
    return {name: sum(robot[name] for robot in counts.values()) for name in COUNTED}


def publish(settings: SwarmSettings, dataset: Dataset, links: dict[str, RobotLink], shutdown: Shutdown) -> Schedule:
    """Publish every robot's events in time order, paced at real time / speedup; log progress every period."""
    schedule = Schedule()
    next_progress = time.monotonic() + settings.progress_period_s
    sent = sent_at_progress = 0
    for event, late in paced(dataset.events(with_truth=settings.publish_truth), dataset.start_stamp, settings.speedup,
                             shutdown):
        now = time.monotonic()
        schedule.note(late)
        links[event.robot_id].put_event(event, with_ids=settings.publish_ids)
        sent += 1
        if now >= next_progress:
            behind_max = schedule.next_period()
            rate = (sent - sent_at_progress) / (settings.progress_period_s + now - next_progress)
            level = logging.WARNING if behind_max > settings.behind_warning_s else logging.INFO
            log.log(level, "swarm at %.1f of %g s robot time: %d messages sent (%.0f/s); behind schedule %.3f s now, "
                    "at most %.3f s in the last %g s%s", event.stamp - dataset.start_stamp, settings.duration, sent, rate,
                    schedule.behind_s, behind_max, settings.progress_period_s,
                    ": it cannot keep up" if level == logging.WARNING else "")
            sent_at_progress = sent
            next_progress = now + settings.progress_period_s
    return schedule


def run(settings: SwarmSettings, shutdown: Shutdown) -> dict:
    """Simulate the swarm and publish it over one Zenoh session; return what was sent (see the module docstring)."""
    dataset = simulate_swarm(settings, shutdown)
    if dataset is None:
        return {"robots": settings.robots, "stopped_by": shutdown.signal_name, "sent": {}, "per_robot": {}}
    keys = Keys(settings.prefix)
    world_payload = None
    if settings.publish_truth:
        world_payload = encode(WorldTruth(world=dataset.name, stamp=dataset.start_stamp, landmarks=dataset.landmarks,
                                          landmark_ids=dataset.landmark_ids))
    with session_scope(settings) as session:
        links: dict[str, RobotLink] = {}
        world_entities = []
        try:
            if world_payload is not None:  # before the tokens: alive means every queryable answers
                world_entities = [answer_with(session, keys.world_truth, world_payload),
                                  StreamPublisher(session, keys.world_truth)]
            for rid, robot in dataset.robots.items():
                rates = {**robot.stream_rates(), "info": 1.0 / settings.info_period_s}
                caches = stream_caches(settings, rates, settings.speedup)
                if not settings.publish_truth:
                    caches["truth"] = 0
                links[rid] = RobotLink(session, robot.info, settings.prefix, caches=caches,
                                       info_period_s=settings.info_period_s,
                                       info_max_period_s=settings.info_max_period_s,
                                       heartbeat_s=settings.heartbeat_period_s)
            log.info("swarm of %d robots (%s..%s) declared on one session", len(links), next(iter(links)),
                     next(reversed(links)))
            shutdown.wait(settings.start_delay)
            for link in links.values():
                link.publish_info()
            if world_entities:
                world_entities[1].put(world_payload)
            log.info("swarm publishing %d robots at %g Hz, speed-up %g, ids %s, truth %s", len(links), settings.rate,
                     settings.speedup, "on" if settings.publish_ids else "off",
                     "on" if settings.publish_truth else "off")
            started = time.monotonic()
            schedule = publish(settings, dataset, links, shutdown)
            wall_s = time.monotonic() - started
            counts = counts_of(list(links.values()))
            sent = total(counts)
            log.info("swarm done: %d robots, odom %d, scan %d, truth %d (info %d) in %.1f s; at most %.3f s behind "
                     "schedule", len(links), sent["odom"], sent["scan"], sent["truth"], sent["info"], wall_s,
                     schedule.run_max_s)
            linger_s = linger_time(settings.linger_s, shutdown.is_set())
            if linger_s > 0:
                log.info("swarm keeps its caches %g s more for receivers that missed its last messages", linger_s)
                shutdown.wait(linger_s)
        finally:
            for link in links.values():
                link.close()
            undeclare_all(world_entities)
    result = {"robots": len(links), "sent": sent, "behind_max_s": round(schedule.run_max_s, 4),
              "wall_s": round(wall_s, 3), "stopped_by": shutdown.signal_name, "per_robot": counts}
    if settings.json_out:
        Path(settings.json_out).parent.mkdir(parents=True, exist_ok=True)
        Path(settings.json_out).write_text(json.dumps(result, indent=1) + "\n")
    return result


def main(args: argparse.Namespace) -> int:
    return run_command(run, settings_from_args(SwarmSettings, args), log, "cannot start swarm", (ValueError,))
