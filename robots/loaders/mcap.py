"""A fleet recording (``fleetslam record``, an MCAP file) as a :class:`~robots.dataset.Dataset`.

Every recorded robot becomes a :class:`~robots.dataset.RobotLog` from its
RobotInfo (the first one), odometry, scans and truth; the true map comes from
``{prefix}/world/truth`` when it was recorded. Services' outputs in the file
are ignored (an offline run recomputes them). Messages the live services
would refuse (a payload that does not decode, a duplicate, one out of order
or going back in time) are left out and counted in ``meta["refused"]``, as
the services count them; a robot with no RobotInfo or no odometry and scans
is left out too (``meta["robots_left_out"]``). The robot's seq numbers are not
kept: its k-th accepted message is index k, as in any other loaded data set; a
recording started after a robot did is flagged (``meta["odometry_not_recorded"]``).
"""

from __future__ import annotations

import logging
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np

from robots.dataset import Dataset, robot_log_from_streams
from schemas.codec import DecodeError, decode
from schemas.mcap_file import Recording, read_recording
from schemas.messages import GroundTruth, Odometry, RobotInfo, Scan, WorldTruth
from schemas.recording import KIND_MODELS, RecordingError, robot_of, topic_kind
from schemas.streams import StreamTracker, Verdict

log = logging.getLogger(__name__)


def dataset_from_recording(recording: Recording, name: str | None = None) -> Dataset:
    """The recorded fleet as a Dataset; :class:`RecordingError` when it holds no usable robot."""
    tracker = StreamTracker()
    refused: Counter = Counter()
    infos: dict[str, RobotInfo] = {}
    streams: dict[str, dict[str, list]] = defaultdict(lambda: {"odom": [], "scan": [], "truth": []})
    world: WorldTruth | None = None
    for message in recording.messages:
        robot = robot_of(recording.prefix, message.topic)
        kind = robot[1] if robot else topic_kind(recording.prefix, message.topic)
        if kind not in ("info", "odom", "scan", "truth", "world") or (kind == "world" and world is not None):
            continue
        try:
            decoded = decode(message.data, KIND_MODELS[kind])
        except DecodeError as error:
            refused[error.reason] += 1
            continue
        if kind == "world":
            world = decoded
            continue
        rid = robot[0]
        if decoded.robot_id != rid:
            refused["wrong_robot"] += 1
        elif kind == "info":
            infos.setdefault(rid, decoded)
        elif tracker.check(rid, kind, decoded.seq, decoded.stamp) is Verdict.ACCEPT:
            streams[rid][kind].append(decoded)
    refused.update(tracker.rejected)
    robots, left_out, late = {}, {}, {}
    for rid in sorted(set(infos) | set(streams)):
        got = streams[rid]
        if rid not in infos:
            left_out[rid] = "no RobotInfo recorded"
        elif not got["odom"] and not got["scan"]:
            left_out[rid] = "no odometry or scans recorded"
        else:
            robots[rid] = robot_log_from_streams(
                infos[rid], got["odom"], got["scan"], [t.stamp for t in got["truth"]],
                [t.pose if t.heading_known else [t.pose[0], t.pose[1], np.nan] for t in got["truth"]])
            if got["odom"] and got["odom"][0].seq > 0:
                late[rid] = got["odom"][0].seq
                log.warning("recording %s: robot %s's first %d odometry messages were not recorded: its announced "
                            "start pose does not hold for its first recorded one", recording.path.name, rid,
                            late[rid])
    for rid, why in left_out.items():
        log.warning("recording %s: robot %s left out (%s)", recording.path.name, rid, why)
    if refused:
        log.warning("recording %s: %d robot messages left out (%s)", recording.path.name, sum(refused.values()),
                    ", ".join(f"{k} {v}" for k, v in sorted(refused.items())))
    if not robots:
        reason = "; ".join(f"{rid}: {why}" for rid, why in left_out.items()) or "no robot messages"
        raise RecordingError(f"{recording.path}: no robots to load ({reason})")
    info = recording.metadata.get("fleetslam", {})
    meta = {
        "file": str(recording.path), "prefix": recording.prefix, "recorded_at": info.get("started", ""),
        "messages": len(recording.messages), "missing": tracker.missing(), "refused": dict(refused),
        "robots_left_out": left_out, "odometry_not_recorded": late, "world": world.world if world is not None else None,
        "streams": {rid: {k: len(v) for k, v in streams[rid].items()} for rid in robots},
    }
    return Dataset(name=name or f"mcap:{recording.path.name}", robots=robots,
                   landmarks=None if world is None else world.landmarks.copy(),
                   landmark_ids=None if world is None else world.landmark_ids.copy(), meta=meta)


def load_mcap(path: str | Path) -> Dataset:
    """Load a recording (``fleetslam run --dataset mcap:FILE``)."""
    return dataset_from_recording(read_recording(path))
