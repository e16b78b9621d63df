"""``fleetslam replay FILE.mcap``: the robots of a recording, published again as live robots.

Each recorded robot (one with a RobotInfo in the file) comes back as a robot
process would: its liveliness token ``{prefix}/robots/{rid}/alive``, its
RobotInfo (published at the start, answered to late joiners, and again
wherever the recording has it), then its odometry, scans and truth, and the
world's true map once, all under this process's prefix, with the recorded
payload bytes unchanged, at the recorded pace (reception times) divided by
``--speedup``, through reliable BLOCK publishers. A robot's token goes when its
last message is out. Services' outputs in the file are not replayed: the
running services recompute them. SIGINT/SIGTERM stop it cleanly.
"""

from __future__ import annotations

import argparse
import logging
import time
from collections import Counter
from dataclasses import dataclass, field


from schemas.codec import DecodeError, decode
from schemas.config import ReplaySettings, add_settings_arguments, settings_from_args
from schemas.keys import Keys
from schemas.mcap_file import Recording, read_recording
from schemas.messages import RobotInfo
from schemas.recording import RecordingError, robot_of, topic_kind
from schemas.transport import (ConnectError, Shutdown, StreamPublisher, answer_history, answer_with, cache_samples,
                               declare_robot_tokens,
                               linger_time, session_scope, undeclare_all)

log = logging.getLogger("fleetslam.replay")

REPLAYED_STREAMS = ("info", "odom", "scan", "truth")


@dataclass(frozen=True, slots=True)
class ReplayItem:
    """One message to publish ``offset_s`` recorded seconds after the first one."""

    offset_s: float
    robot_id: str
    stream: str
    data: bytes


@dataclass
class ReplayPlan:
    """What a replay publishes: each robot's RobotInfo, the world truth, and the robot messages in order."""

    infos: dict[str, bytes]
    world: bytes | None
    items: list[ReplayItem]
    last_index: dict[str, int] = field(default_factory=dict)  # each robot's last item
    left_out: dict[str, str] = field(default_factory=dict)  # robots recorded but not replayed, and why

    @property
    def span_s(self) -> float:
        return self.items[-1].offset_s if self.items else 0.0


def plan_replay(recording: Recording, robots: list[str] | None = None, start_s: float = 0.0) -> ReplayPlan:
    """The replay of ``robots`` (default: all) from ``start_s`` recorded seconds on; :class:`RecordingError`
    when a named robot is not in the recording or no robot is left to replay. Pure."""
    infos: dict[str, bytes] = {}
    recorded: set[str] = set()
    world = None
    for message in recording.messages:
        robot = robot_of(recording.prefix, message.topic)
        if robot is None:
            if world is None and topic_kind(recording.prefix, message.topic) == "world":
                world = message.data
            continue
        recorded.add(robot[0])
        if robot[1] == "info" and robot[0] not in infos:
            try:
                if decode(message.data, RobotInfo).robot_id == robot[0]:
                    infos[robot[0]] = message.data
            except DecodeError:
                pass
    if not recorded:
        raise RecordingError(f"{recording.path}: no robots were recorded (keys {recording.prefix}/robots/*/...)")
    unknown = sorted(set(robots or ()) - recorded)
    if unknown:
        raise RecordingError(f"{recording.path}: robot{'s' if len(unknown) > 1 else ''} {', '.join(unknown)} not "
                             f"recorded (it has {', '.join(sorted(recorded))})")
    chosen = set(robots or recorded)
    left_out = {rid: "no RobotInfo recorded" for rid in sorted(chosen - set(infos))}
    chosen &= set(infos)
    start_ns = recording.messages[0].log_time_ns + int(round(start_s * 1e9))
    items: list[ReplayItem] = []
    first_ns = None
    for message in recording.messages:
        robot = robot_of(recording.prefix, message.topic)
        if robot is None or robot[0] not in chosen or message.log_time_ns < start_ns:
            continue
        first_ns = message.log_time_ns if first_ns is None else first_ns
        items.append(ReplayItem((message.log_time_ns - first_ns) / 1e9, robot[0], robot[1], message.data))
    last_index = {item.robot_id: k for k, item in enumerate(items)}
    for rid in sorted(chosen - set(last_index)):
        left_out[rid] = f"nothing recorded after {start_s:g} s"
    if not last_index:
        reasons = "; ".join(f"{rid}: {why}" for rid, why in left_out.items())
        raise RecordingError(f"{recording.path}: no robot to replay ({reasons})")
    return ReplayPlan(infos={rid: infos[rid] for rid in sorted(last_index)}, world=world, items=items,
                      last_index=last_index, left_out=left_out)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", metavar="FILE.mcap", help="a recording written by fleetslam record")
    add_settings_arguments(parser, ReplaySettings)


def publish(plan: ReplayPlan, settings: ReplaySettings, shutdown: Shutdown) -> Counter:
    """Publish the plan as live robots; the count of messages published per stream."""
    keys = Keys(settings.prefix)
    counts: Counter = Counter()
    with session_scope(settings) as session:
        tokens = {rid: declare_robot_tokens(session, keys, rid) for rid in plan.infos}
        sent = Counter((item.robot_id, item.stream) for item in plan.items)
        wall_span_s = max(plan.span_s, 1.0) / settings.speedup
        caches = {(rid, stream): cache_samples(settings, sent[(rid, stream)] / wall_span_s)
                  for rid in plan.infos for stream in REPLAYED_STREAMS}
        pubs = {key: StreamPublisher(session, keys.robot(*key), cache=size,
                                     keep=size if key[1] in ("odom", "scan") else 0) for key, size in caches.items()}
        declared: list = list(pubs.values())
        declared += [answer_history(session, keys.history(rid), [pubs[(rid, "odom")], pubs[(rid, "scan")]])
                     for rid in plan.infos if (rid, "odom") in pubs and (rid, "scan") in pubs]
        declared += [answer_with(session, keys.info(rid), payload) for rid, payload in plan.infos.items()]
        world_pub = None
        if plan.world is not None:
            world_pub = StreamPublisher(session, keys.world_truth)
            declared.append(world_pub)
            declared.append(answer_with(session, keys.world_truth, plan.world))
        try:
            shutdown.wait(settings.start_delay)
            for rid, payload in plan.infos.items():
                pubs[(rid, "info")].put(payload)
            if world_pub is not None:
                world_pub.put(plan.world)
            log.info("replaying %s: %d messages over %.1f recorded s at speed-up %g", ", ".join(plan.infos),
                     len(plan.items), plan.span_s, settings.speedup)
            wall0 = time.monotonic()
            next_progress = wall0 + settings.progress_period_s
            for k, item in enumerate(plan.items):
                due = wall0 + item.offset_s / settings.speedup
                now = time.monotonic()
                if (due > now and shutdown.wait(due - now)) or shutdown.is_set():
                    break
                pubs[(item.robot_id, item.stream)].put(item.data)
                counts[item.stream] += 1
                if plan.last_index[item.robot_id] == k:
                    undeclare_all(tokens.pop(item.robot_id))
                    log.info("robot %s done", item.robot_id)
                if time.monotonic() >= next_progress:
                    log.info("replay: %.1f of %.1f recorded s; %s", item.offset_s, plan.span_s,
                             ", ".join(f"{s} {n}" for s, n in sorted(counts.items())))
                    next_progress = time.monotonic() + settings.progress_period_s
            linger_s = linger_time(settings.linger_s, shutdown.is_set())
            if linger_s > 0:
                log.info("replay: keeping the caches %g s more for receivers that missed the last messages", linger_s)
                time.sleep(linger_s)
        finally:
            undeclare_all([*declared, *(token for pair in tokens.values() for token in pair)])
    return counts


def main(args: argparse.Namespace) -> int:
    settings = settings_from_args(ReplaySettings, args)
    shutdown = Shutdown()
    robots = [r.strip() for r in settings.robot_ids.split(",") if r.strip()] if settings.robot_ids else None
    try:
        recording = read_recording(args.file)
        plan = plan_replay(recording, robots, settings.start_s)
    except RecordingError as exc:
        log.error("cannot replay: %s", exc)
        return 2
    for rid, why in plan.left_out.items():
        log.warning("robot %s is not replayed: %s", rid, why)
    try:
        counts = publish(plan, settings, shutdown)
    except ConnectError as exc:
        log.error("%s", exc)
        return 2
    stopped = f" (stopped by {shutdown.signal_name})" if shutdown.signal_name else ""
    log.info("replay done%s: %s", stopped, ", ".join(f"{s} {n}" for s, n in sorted(counts.items())) or "nothing sent")
    return 0
