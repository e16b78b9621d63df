"""A ROS 2 bag (rosbag2: MCAP or sqlite3 storage) as a :class:`~robots.dataset.Dataset`, through a fleet file.

The fleet file (:mod:`services.ros2.fleet`) says which topics are whose odometry and landmarks; each robot's
messages go through the same conversions as the live bridge (:class:`services.ros2.core.RobotInput`), so an
offline run of a bag sees what ``fleetslam ros2`` would have published. Messages the conversion refuses are left
out and counted by reason in ``meta["rejected"]`` (``{robot: {reason: count}}``); topics of the fleet file that
the bag does not hold are listed in ``meta["topics_missing"]``. Optional truth topics (a robot's
``truth_topic``, the fleet's ``landmarks_truth_topic``) give the truth to score against. A bag folder written by
``fleetslam export rosbag2`` holds its ``fleet.yaml``: it is used when no fleet file is given. Landmark ids and
detections of other robots are not in the messages: the data set has neither.
"""

from __future__ import annotations

import logging
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np

from robots.dataset import Dataset, robot_log_from_streams
from schemas.contract import OdomEvent, ScanEvent

log = logging.getLogger(__name__)

FLEET_FILE_NAME = "fleet.yaml"


def bag_fleet(path: Path, fleet=None):
    """The fleet file of a bag: ``fleet`` (a FleetFile or a path), else the ``fleet.yaml`` beside the bag."""
    from services.ros2.fleet import FleetFile, load_fleet

    if isinstance(fleet, FleetFile):
        return fleet
    if fleet is not None:
        return load_fleet(fleet)
    folder = path if path.is_dir() else path.parent
    if (folder / FLEET_FILE_NAME).is_file():
        return load_fleet(folder / FLEET_FILE_NAME)
    raise ValueError(f"rosbag2 {path}: no fleet file given (--fleet FILE.yaml) and no {FLEET_FILE_NAME} in {folder}")


def load_rosbag2(path: str | Path, fleet=None) -> Dataset:
    """Load a rosbag2 folder (or its single storage file) with a fleet file (a FleetFile or a path; default: the
    bag's ``fleet.yaml``)."""
    from rosbags.rosbag2 import Reader

    from services.ros2.core import RobotInput, landmarks_truth, reject_reason, truth_pose, typestore_for

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"rosbag2 {path} does not exist")
    fleet = bag_fleet(path, fleet)
    typestore = typestore_for(fleet.ros_distro)
    inputs = {entry.robot_id: RobotInput(entry, source=f"replay:rosbag2:{path.name}") for entry in fleet.robots}
    routes: dict[str, tuple[str, str]] = {}
    for entry in fleet.robots:
        routes[entry.topic(entry.odometry_topic)] = (entry.robot_id, "odometry")
        routes[entry.topic(entry.landmarks_topic)] = (entry.robot_id, "landmarks")
        if entry.truth_topic:
            routes[entry.topic(entry.truth_topic)] = (entry.robot_id, "truth")
    if fleet.landmarks_truth_topic:
        routes[fleet.landmarks_truth_topic] = ("", "landmarks_truth")
    odom: dict[str, list[OdomEvent]] = defaultdict(list)
    scans: dict[str, list[ScanEvent]] = defaultdict(list)
    truth: dict[str, list] = defaultdict(list)
    first_stamp: dict[str, float] = {}
    rejected: dict[str, Counter] = defaultdict(Counter)
    landmarks = landmark_ids = None
    with Reader(path) as reader:
        connections = [c for c in reader.connections if c.topic in routes]
        present = {c.topic for c in connections}
        unknown_types = sorted({c.msgtype for c in connections if c.msgtype not in typestore.types})
        if unknown_types:
            raise ValueError(f"rosbag2 {path}: message types unknown to ROS {fleet.ros_distro}: "
                             f"{', '.join(unknown_types)}")
        for connection, _, raw in reader.messages(connections=connections):
            robot, kind = routes[connection.topic]
            msg = typestore.deserialize_cdr(raw, connection.msgtype)
            if kind == "landmarks_truth":
                landmarks, landmark_ids = landmarks_truth(msg)
                continue
            if kind == "truth":
                truth[robot].append(truth_pose(msg))
                continue
            try:
                if kind == "odometry":
                    event = inputs[robot].odometry(msg)
                    if event is not None:
                        odom[robot].append(event)
                else:
                    scans[robot].append(inputs[robot].landmarks(msg))
            except ValueError as error:
                rejected[robot][reject_reason(error)] += 1
                continue
            first_stamp.setdefault(robot, float(inputs[robot].last_odom_stamp if kind == "odometry"
                                                else inputs[robot].last_scan_stamp))
    logs = {rid: robot_log_from_streams(inputs[rid].info(first_stamp[rid]), odom[rid], scans[rid],
                                        [t for t, _ in truth[rid]], [pose for _, pose in truth[rid]])
            for rid in inputs if odom[rid] or scans[rid]}
    if not logs:
        raise ValueError(f"rosbag2 {path}: no odometry or landmarks of any robot of the fleet file")
    offsets = {entry.truth_offset for entry in fleet.robots if entry.robot_id in logs}
    meta = {"path": str(path), "ros_distro": fleet.ros_distro,
            "rejected": {rid: dict(counts) for rid, counts in rejected.items()},
            "messages": {rid: {"odometry": len(odom[rid]), "landmarks": len(scans[rid]), "truth": len(truth[rid])}
                         for rid in logs},
            "topics_missing": sorted(set(routes) - present),
            "robots_left_out": sorted(set(inputs) - set(logs))}
    if len(offsets) == 1 and offsets != {(0.0, 0.0)}:
        meta["truth_offset"] = tuple(offsets.pop())
    for rid, counts in meta["rejected"].items():
        log.warning("rosbag2 %s: robot %s: messages rejected %s", path.name, rid, counts)
    return Dataset(name=f"rosbag2:{path.name}", robots=logs, landmarks=landmarks, landmark_ids=landmark_ids, meta=meta)
