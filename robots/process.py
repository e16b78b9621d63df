"""``fleetslam robot``: one robot process, simulated or replaying a data set.

It declares its queryables, then the liveliness token ``{prefix}/robots/{rid}/alive`` (so a process that sees
the token can query it at once), publishes
its RobotInfo (again after ``info_period_s``, then less and less often up to every ``info_max_period_s``, and to
late joiners through a queryable),
the world's true map once on ``{prefix}/world/truth`` (and to late joiners;
not with ``--no-publish-world``, where ``fleetslam world`` publishes it under
its own identity), then its odometry, scans and truth in time order, paced at real time divided
by ``--speedup``. Publishers are reliable with congestion control BLOCK, so
nothing is dropped silently, and advanced: each caches ``outage_budget_s`` of
its stream and sends heartbeats, so a receiver that was cut off, restarted or
late recovers what it missed (and keeps its odometry and scans for the
history queryable ``{prefix}/robots/{rid}/history`` that a restarted service
asks); after its last message the robot keeps them
``linger_s`` (at most 1 s when stopped by a signal) for a receiver that missed
the tail. SIGINT/SIGTERM stop it cleanly.
"""

from __future__ import annotations

import argparse
import logging
import time
from dataclasses import dataclass
from typing import Iterable, Iterator


from robots.dataset import Dataset, RobotLog
from robots.simulator import simulate
from schemas.codec import encode
from schemas.config import RobotSettings, add_settings_arguments, settings_from_args
from schemas.keys import Keys
from schemas.messages import WorldTruth
from schemas.transport import (Shutdown, StreamPublisher, answer_with, linger_time, paced, run_command, session_scope,
                               stream_caches, undeclare_all)
from services.client import RobotLink

log = logging.getLogger("fleetslam.robot")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, RobotSettings)


def fleet_ids(rid: str, fleet: str) -> list[str]:
    """The simulated robots' ids in the fleet's order, this robot's added if missing: it is simulated among them and
    detects them. Each robot's motion and detections come from streams of its own (seeded by its number in
    ``rN``, else by its place in this list, the same in every robot's process), so they do not change with the
    fleet."""
    return list(dict.fromkeys([*(other for other in fleet.split(",") if other), rid]))


def load_robot(settings: RobotSettings) -> tuple[RobotLog, Dataset]:
    """The log this robot publishes: a simulation, or one robot of a data set."""
    if settings.replay:
        from robots.loaders import load_dataset

        if settings.fleet:
            raise ValueError("--fleet is for simulated robots: a replayed robot detects whom its data set says")

        dataset = load_dataset(settings.replay)
        if len(dataset.robots) != 1:
            raise ValueError(f"--replay {settings.replay!r} holds {len(dataset.robots)} robots; name one (mrclam:PATH:N)")
        robot = next(iter(dataset.robots.values()))
    else:
        rid = settings.robot_id or "r1"
        dataset = simulate(
            settings.world, seed=settings.seed, duration=settings.duration, rate=settings.rate,
            odom_factor=settings.odom_factor, trajectory=settings.trajectory,
            detection_probability=settings.detection_probability, clutter_rate=settings.clutter_rate,
            unknown_start=settings.unknown_start, robot_ids=fleet_ids(rid, settings.fleet),
        )
        robot = dataset.robots[rid]
    updates = {}
    if settings.robot_id and settings.robot_id != robot.robot_id:
        updates["robot_id"] = settings.robot_id
    if settings.unknown_start:
        updates.update(start_pose=None, start_pose_cov=None)
    updates.update({name: limit for name, limit in robot.motion_limits().items() if getattr(robot.info, name) is None})
    if updates:
        robot.info = robot.info.model_copy(update=updates)
    return robot, dataset


@dataclass
class Instant:
    """Events of one stamp (a scan and the odometry that ends with it), published together."""

    stamp: float
    events: list


def instants(events: Iterable) -> Iterator[Instant]:
    """Consecutive events of equal stamps grouped (the events come in time order)."""
    current: Instant | None = None
    for event in events:
        if current is not None and event.stamp == current.stamp:
            current.events.append(event)
            continue
        if current is not None:
            yield current
        current = Instant(event.stamp, [event])
    if current is not None:
        yield current


def single(events: Iterable) -> Iterator[Instant]:
    """Each event alone (published as it comes)."""
    for event in events:
        yield Instant(event.stamp, [event])


def run(settings: RobotSettings, shutdown: Shutdown) -> dict[str, int]:
    """Publish the robot's log over Zenoh; return the count of messages per stream."""
    robot, dataset = load_robot(settings)
    rid = robot.robot_id
    keys = Keys(settings.prefix)
    until = None if settings.replay is None else robot.start_stamp + settings.duration
    world_payload = None
    if dataset.landmarks is not None and settings.publish_truth and settings.publish_world:
        world_payload = encode(WorldTruth(world=dataset.name, stamp=robot.start_stamp, landmarks=dataset.landmarks,
                                          landmark_ids=dataset.landmark_ids))
    with session_scope(settings) as session:
        rates = {**robot.stream_rates(), "info": 1.0 / settings.info_period_s}
        caches = stream_caches(settings, rates, settings.speedup)
        answer_world = world_pub = None
        if world_payload is not None:  # before the link's tokens: alive means every queryable answers
            answer_world = answer_with(session, keys.world_truth, world_payload)
            world_pub = StreamPublisher(session, keys.world_truth)
        link = RobotLink(session, robot.info, settings.prefix, caches=caches, info_period_s=settings.info_period_s,
                         info_max_period_s=settings.info_max_period_s, heartbeat_s=settings.heartbeat_period_s)
        try:
            shutdown.wait(settings.start_delay)
            link.publish_info()
            if world_pub is not None:
                world_pub.put(world_payload)
            log.info("robot %s publishing %s (%s) at speed-up %g", rid, robot.info.source, robot.info.motion_model,
                     settings.speedup)
            data0 = min(robot.start_stamp, dataset.meta.get("fleet_start", robot.start_stamp))  # one clock for a fleet
            events = robot.events(until=until, with_truth=settings.publish_truth)
            for instant, _ in paced(instants(events) if settings.publish_together else single(events), data0,
                                    settings.speedup, shutdown):
                link.put_events(instant.events, with_ids=settings.publish_ids)
            counts = {name: link.counts[name] for name in ("odom", "scan", "truth")}
            log.info("robot %s done: %s", rid, ", ".join(f"{k} {v}" for k, v in counts.items()))
            linger_s = linger_time(settings.linger_s, shutdown.is_set(), settings.heartbeat_period_s)
            if linger_s > 0:
                log.info("robot %s keeps its caches %g s more for receivers that missed its last messages", rid,
                         linger_s)
                time.sleep(linger_s)
        finally:
            link.close()
            undeclare_all([answer_world, world_pub])
    return counts


def main(args: argparse.Namespace) -> int:
    return run_command(run, settings_from_args(RobotSettings, args), log, "cannot start robot", (ValueError, FileNotFoundError))
