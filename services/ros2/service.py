"""``fleetslam ros2``: ROS 2 robots on rmw_zenoh join fleetslam directly, and get its estimates back in ROS 2.

ROS 2's Zenoh middleware puts every topic on a Zenoh key (:mod:`services.ros2.rmw_zenoh`), so a process on the
same router reads a ROS 2 robot with no ROS installed, no bridge process and no DDS. For each robot of the fleet
file (:mod:`services.ros2.fleet`) this process

- subscribes its odometry (``nav_msgs/Odometry`` or ``geometry_msgs/TwistStamped``) and its landmarks
  (``geometry_msgs/PoseArray``, or ``sensor_msgs/LaserScan`` through the point-landmark extractor) on their
  rmw_zenoh keys, with any type hash, and announces the subscriptions (``MS`` tokens) to the ROS graph;
- turns them into fleetslam's RobotInfo, Odometry and Scan (:class:`services.ros2.core.RobotInput`) and publishes
  them on the robot's fleetslam keys through a :class:`services.client.RobotLink`, as any fleetslam robot does
  (reliable, cached for lossless recovery, history queryable, liveliness tokens);
- publishes back, on rmw_zenoh keys with the ``MP`` tokens that make ``ros2 topic list`` show them: each robot's
  fused pose (central FastSLAM) as ``nav_msgs/Odometry`` on ``/<ns>/fleetslam/odom``, its ``map → odom`` transform
  on ``/tf``, and the central and D-SLAM maps as ``visualization_msgs/MarkerArray`` on ``/fleetslam/map``.

Every input that cannot be used is counted by reason in the stats (``{prefix}/ros2/stats``) and logged the first
times: a sample without rmw_zenoh's attachment, a type hash that is not the fleet's distribution's, a repeated
sequence number (``duplicate``), CDR that does not decode as the topic's type (``bad_cdr``), and what
:class:`~services.ros2.core.RobotInput` refuses (``wrong_type``, ``unknown_frame``, ``time_backwards``,
``non_finite``, ``bad_shape``, ...). Sequence numbers that jump count the samples lost upstream (``ros_lost``).
"""

from __future__ import annotations

import argparse
import logging
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from schemas.codec import decode
from schemas.config import Ros2Settings, add_settings_arguments, settings_from_args
from schemas.contract import SettingsError, TruthEvent
from schemas.messages import Estimate, MapEstimate
from schemas.transport import stream_caches
from services.client import RobotLink
from services.ros2.core import (TYPE_HASH_NOT_SUPPORTED, RobotInput, quaternion_yaw, reject_reason, truth_pose,
                                type_hash, typestore_for)
from services.ros2.fleet import TRUTH_TYPE, FleetFile, FleetFileError, RobotEntry, load_fleet
from services.ros2.outputs import landmark_markers, map_to_odom, odometry_message, transform_message
from services.ros2.rmw_zenoh import RosNode, RosPublisher, RosSample
from services.mapfeed import MapFeed
from services.runtime import ServiceShell

log = logging.getLogger("fleetslam.ros2")

POSE_TYPE, TF_TYPE, MAP_TYPE = "nav_msgs/msg/Odometry", "tf2_msgs/msg/TFMessage", "visualization_msgs/msg/MarkerArray"
MAP_COLORS = {"central": (0.9, 0.3, 0.1, 0.8), "dslam": (0.1, 0.4, 0.9, 0.8)}
ODOM_POSES_KEPT = 400  # a robot's own odometry poses kept to pair with the fused pose of the same stamp


@dataclass
class RosTopic:
    """One subscribed ROS 2 topic of a robot: which stream it feeds and what type and hash it must carry."""

    robot_id: str
    stream: str  # "odom", "landmarks" or "truth"
    msgtype: str
    type_hash: str


@dataclass
class RobotSide:
    """A ROS 2 robot as the bridge holds it: its converter, its fleetslam link (made at its first message), its
    pose publisher, and its recent poses in its own odometry frame (for ``map → odom``)."""

    entry: RobotEntry
    input: RobotInput
    pose_pub: RosPublisher
    link: RobotLink | None = None
    odom_stamps: deque = field(default_factory=lambda: deque(maxlen=ODOM_POSES_KEPT))
    odom_poses: deque = field(default_factory=lambda: deque(maxlen=ODOM_POSES_KEPT))
    truth_seq: int = 0
    last_truth_stamp: float = float("-inf")

    def truth(self, message) -> TruthEvent:
        """A true pose (for the evaluator only), numbered in its own stream."""
        stamp, pose = truth_pose(message)
        if not (np.isfinite(stamp) and np.all(np.isfinite(pose[:2]))):
            raise ValueError("non_finite: true position or stamp is NaN or infinite")
        if self.truth_seq and stamp < self.last_truth_stamp:
            raise ValueError(f"time_backwards: true pose at {stamp!r} before {self.last_truth_stamp!r}")
        event = TruthEvent(self.entry.robot_id, self.truth_seq, stamp, pose)
        self.truth_seq, self.last_truth_stamp = self.truth_seq + 1, stamp
        return event

    def odom_pose_at(self, stamp: float) -> np.ndarray | None:
        """The robot's own odometry pose nearest ``stamp`` (None before the first)."""
        if not self.odom_stamps:
            return None
        stamps = np.fromiter(self.odom_stamps, float)
        return self.odom_poses[int(np.argmin(np.abs(stamps - stamp)))]


class Ros2Bridge(ServiceShell):
    """The ``fleetslam ros2`` process (see the module docstring)."""

    name = "ros2"

    def __init__(self, settings: Ros2Settings, fleet: FleetFile):
        super().__init__(settings)
        self.settings: Ros2Settings = settings
        self.fleet = fleet
        self.typestore = typestore_for(fleet.ros_distro)
        self.topics: dict[str, RosTopic] = {}
        self.robots: dict[str, RobotSide] = {}
        self.last_sequence: dict[bytes, int] = {}  # per ROS publisher (its GID)
        self._map_due = {"central": 0.0, "dslam": 0.0}
        self.central_feed = MapFeed(self, Estimate, self.keys.central_state, "central_state")
        self.dslam_feed = MapFeed(self, MapEstimate, self.keys.dslam_state, "dslam_state")
        self.node: RosNode | None = None

    def _hash(self, msgtype: str) -> str:
        return type_hash(self.typestore, msgtype, self.fleet.ros_distro)

    def setup(self, session) -> None:
        fleet, settings = self.fleet, self.settings
        self.node = node = RosNode(session, settings.node_name, "/", fleet.domain_id)
        for entry in fleet.robots:
            side = RobotSide(entry, RobotInput(entry),
                             node.publisher(entry.topic(settings.pose_topic), POSE_TYPE, self._hash(POSE_TYPE)))
            self.robots[entry.robot_id] = side
            streams = [("odom", entry.odometry_topic, entry.odometry_type),
                       ("landmarks", entry.landmarks_topic, entry.landmarks_type)]
            if entry.truth_topic:
                streams.append(("truth", entry.truth_topic, TRUTH_TYPE))
            for stream, topic, msgtype in streams:
                tag = f"ros:{entry.robot_id}:{stream}"
                self.topics[tag] = RosTopic(entry.robot_id, stream, msgtype, self._hash(msgtype))
                node.subscription(entry.topic(topic), msgtype, self._hash(msgtype), self._enqueuer_of(tag))
            log.info("ROS 2 robot %s: %s (%s), %s (%s)", entry.robot_id, entry.topic(entry.odometry_topic),
                     entry.odometry_type, entry.topic(entry.landmarks_topic), entry.landmarks_type)
        self.tf_pub = node.publisher(settings.tf_topic, TF_TYPE, self._hash(TF_TYPE))
        self.map_pub = node.publisher(settings.map_topic, MAP_TYPE, self._hash(MAP_TYPE))
        self.subscribe(self.keys.central_estimate, "central", recover=False)
        self.subscribe(self.keys.dslam_map, "dslam_map", recover=False)

    def _enqueuer_of(self, tag: str):
        def on_sample(sample: RosSample) -> None:
            self.enqueue(tag, sample.key, sample, nbytes=len(sample.payload))
        return on_sample

    async def handle(self, tag: str, key: str, payload) -> None:
        if tag in ("central", self.central_feed.reply_tag):
            reply = tag == self.central_feed.reply_tag
            estimate = decode(payload, Estimate)
            if not reply:  # a reply brings the map: its poses are not the stream's
                self._central_poses(estimate)
            whole = self.central_feed.take(estimate, reply=reply)
            if whole is not None:
                self._map("central", whole.stamp, whole.landmarks, whole.landmark_covs)
        elif tag in ("dslam_map", self.dslam_feed.reply_tag):
            estimate = self.dslam_feed.take(decode(payload, MapEstimate), reply=tag == self.dslam_feed.reply_tag)
            if estimate is not None:
                self._dslam(estimate)
        elif tag in self.topics:
            self._ros_sample(self.topics[tag], payload)

    # ------------------------------------------------------------------ ROS 2 in
    def _ros_sample(self, topic: RosTopic, sample: RosSample) -> None:
        if sample.attachment is None:
            self.reject(reject_reason(ValueError(sample.attachment_error)), f"{sample.key}: {sample.attachment_error}")
            return
        key_hash = sample.key.rsplit("/", 1)[-1]
        if key_hash not in (topic.type_hash, TYPE_HASH_NOT_SUPPORTED):
            self.reject("type_hash_mismatch", f"{sample.key}: {topic.msgtype} of {self.fleet.ros_distro} is "
                        f"{topic.type_hash}")
            return
        gid, sequence = sample.attachment.gid, sample.attachment.sequence
        last = self.last_sequence.get(gid)
        if last is not None and sequence <= last:
            self.reject("duplicate", f"{sample.key}: sequence number {sequence} after {last}")
            return
        if last is not None and sequence > last + 1:
            self.extra["ros_lost"] = self.extra.get("ros_lost", 0.0) + (sequence - last - 1)
        self.last_sequence[gid] = sequence
        try:
            message = self.typestore.deserialize_cdr(sample.payload, topic.msgtype)
        except Exception as error:  # noqa: BLE001 - rosbags raises several kinds on bytes that are not the type
            self.reject("bad_cdr", f"{sample.key}: {type(error).__name__}: {error}")
            return
        side = self.robots[topic.robot_id]
        try:
            if topic.stream == "odom":
                event = side.input.odometry(message)
                if topic.msgtype == POSE_TYPE:
                    pose = message.pose.pose
                    side.odom_stamps.append(message.header.stamp.sec + message.header.stamp.nanosec * 1e-9)
                    side.odom_poses.append(np.array([pose.position.x, pose.position.y,
                                                     quaternion_yaw(pose.orientation)]))
            elif topic.stream == "landmarks":
                event = side.input.landmarks(message)
            else:
                event = side.truth(message)
        except ValueError as error:
            self.reject(reject_reason(error), f"{sample.key}: {error}")
            return
        if event is None:  # the first odometry message only starts the robot's clock
            return
        self._link(side, event.stamp).put_event(event)
        self.count_extra(f"forwarded_{topic.stream}")

    def _link(self, side: RobotSide, stamp: float) -> RobotLink:
        """The robot's fleetslam link, made at its first usable message (so it is announced only once it speaks)."""
        if side.link is None:
            info = side.input.info(stamp)
            rates = {"info": 1.0, "odom": info.odom_rate_hz, "scan": info.scan_rate_hz, "truth": 1.0}
            caches = stream_caches(self.settings, rates)
            side.link = RobotLink(self.session, info, self.settings.prefix, caches=caches,
                                  info_max_period_s=self.settings.info_max_period_s,
                                  heartbeat_s=self.settings.heartbeat_period_s)
            log.info("ROS 2 robot %s joined fleetslam (%s)", info.robot_id, info.source)
        return side.link

    # ------------------------------------------------------------------ ROS 2 out
    def _central_poses(self, estimate: Estimate) -> None:
        ts, map_frame = self.typestore, self.fleet.map_frame
        for robot in estimate.robots:
            side = self.robots.get(robot.robot_id)
            if side is None:
                continue
            entry = side.entry
            side.pose_pub.put(ts.serialize_cdr(odometry_message(ts, robot.pose, robot.cov, robot.stamp, map_frame,
                                                                entry.base_frame), POSE_TYPE))
            odom = side.odom_pose_at(robot.stamp)
            if odom is not None:
                transform = map_to_odom(robot.pose, odom)
                self.tf_pub.put(ts.serialize_cdr(transform_message(ts, transform, robot.stamp, map_frame,
                                                                   entry.odom_frame), TF_TYPE))
            self.published += 1

    def _dslam(self, estimate: MapEstimate) -> None:
        self._map("dslam", estimate.stamp, estimate.landmarks, estimate.landmark_covariances())

    def _map(self, source: str, stamp: float, means: np.ndarray, covs: np.ndarray) -> None:
        now = time.monotonic()
        if now < self._map_due[source]:
            return
        self._map_due[source] = now + self.settings.map_period_s
        markers = landmark_markers(self.typestore, means, covs, stamp, self.fleet.map_frame, source,
                                   MAP_COLORS[source])
        self.map_pub.put(self.typestore.serialize_cdr(markers, MAP_TYPE))
        self.published += 1

    def on_stop(self) -> None:
        for side in self.robots.values():
            if side.link is not None:
                side.link.close()
        if self.node is not None:
            self.node.undeclare()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, Ros2Settings)


def main(args: argparse.Namespace) -> int:
    settings = settings_from_args(Ros2Settings, args)
    try:
        fleet = load_fleet(settings.fleet_file)
    except FleetFileError as error:
        raise SettingsError(str(error)) from None
    return Ros2Bridge(settings, fleet).serve()
