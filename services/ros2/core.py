"""ROS 2 messages ⇄ fleetslam events: pure conversions, shared by the live bridge and ROS 2 bags.

No Zenoh, no I/O. Messages are rosbags' message classes (a typestore per ROS distribution, :func:`typestore_for`);
CDR bytes are the caller's business (``typestore.serialize_cdr`` / ``deserialize_cdr``).

Import (:class:`RobotInput`, one per robot, stateful): odometry messages become :class:`OdomEvent`, landmark
messages :class:`ScanEvent`. An odometry message's twist is the control that acted over the interval that ends
at its stamp, so the robot's first message only starts the clock. The control is (twist.linear.x,
twist.angular.z) for a unicycle, and (encoder speed, steering) for an Ackermann vehicle, inverted exactly from
the rear-axle twist (:class:`robots.models.AckermannModel`: ω = v·tan α / L, v_encoder = v − ω·H). The twist
covariance, of (v, ω), becomes the control's covariance (through the model's Jacobian for an Ackermann vehicle);
when it is zero, the entry's ``odometry_std`` is used. PoseArray positions are the detections in the sensor
frame (origin at ``sensor.offset``, turned by ``sensor.yaw``): range = |p|, bearing = atan2 turned into the body
frame, which is fleetslam's sensor convention (:class:`robots.models.RangeBearingSensor`). LaserScan messages go
through the point-landmark extractor (:mod:`robots.features`). A message that cannot be used raises
``ValueError("reason: detail")``; the reasons (:data:`REJECT_REASONS`) are what the bridge counts.

Export (:func:`robot_log_messages`): a :class:`RobotLog` as nav_msgs/Odometry (one per control, plus one at the
first interval's start that starts the clock) and geometry_msgs/PoseArray (one per scan), which import turns back
into the same controls, intervals, ranges and bearings (to float rounding). PoseArray has no room for landmark
ids or detections of other robots: they are not carried. An Ackermann vehicle standing still has no steering
angle in its twist: it comes back as 0 (it moves the vehicle no more than any other angle at zero speed).
"""

from __future__ import annotations

import heapq
import math
from functools import lru_cache
from typing import Any, Iterator

import numpy as np
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.base import Nodetype

from robots.dataset import RobotLog
from robots.models import dead_reckon, motion_model, wrap_angle
from schemas.contract import OdomEvent, ScanEvent
from schemas.messages import RobotInfo
from services.ros2.fleet import LANDMARKS_TRUTH_TYPE, TRUTH_TYPE, RobotEntry

DISTRO_STORES = {"humble": Stores.ROS2_HUMBLE, "jazzy": Stores.ROS2_JAZZY, "kilted": Stores.ROS2_KILTED,
                 "rolling": Stores.LATEST}
TYPE_HASH_NOT_SUPPORTED = "TypeHashNotSupported"
REJECT_REASONS = ("wrong_type", "unknown_frame", "time_backwards", "time_gap", "non_finite", "bad_shape",
                  "bad_covariance")
MIN_ACKERMANN_SPEED = 1e-9  # m/s: below it the steering angle is not in the twist (0 is used)
CONTIGUOUS_S = 1e-6  # s: an interval starting farther than this from the previous one's end follows a gap
NUMERIC_DTYPES = {"bool": np.bool_, "byte": np.uint8, "char": np.uint8, "octet": np.uint8, "float32": np.float32,
                  "float64": np.float64, "int8": np.int8, "uint8": np.uint8, "int16": np.int16, "uint16": np.uint16,
                  "int32": np.int32, "uint32": np.uint32, "int64": np.int64, "uint64": np.uint64}

Message = Any  # a rosbags message instance (a dataclass of the typestore)


# ---------------------------------------------------------------- typestore, hashes, messages, stamps
@lru_cache(maxsize=None)
def typestore_for(distro: str):
    """rosbags' typestore of a ROS distribution (humble, jazzy, kilted; rolling: the newest rosbags knows)."""
    if distro not in DISTRO_STORES:
        raise ValueError(f"unknown ROS distribution {distro!r} (known: {', '.join(DISTRO_STORES)})")
    return get_typestore(DISTRO_STORES[distro])


def type_hash(typestore, msgtype: str, distro: str) -> str:
    """The type hash rmw_zenoh puts in a topic's key: ``RIHS01_…``, or ``TypeHashNotSupported`` on Humble."""
    return TYPE_HASH_NOT_SUPPORTED if distro == "humble" else typestore.hash_rihs01(msgtype)


def _default_value(typestore, node: tuple) -> Any:
    kind, detail = node
    if kind == Nodetype.BASE:
        name = detail[0]
        return "" if name in ("string", "wstring") else False if name == "bool" else \
            0.0 if name.startswith("float") else 0
    if kind == Nodetype.NAME:
        return new_message(typestore, detail)
    element, length = detail
    if element[0] == Nodetype.BASE and element[1][0] in NUMERIC_DTYPES:
        return np.zeros(length if kind == Nodetype.ARRAY else 0, NUMERIC_DTYPES[element[1][0]])
    return [_default_value(typestore, element) for _ in range(length if kind == Nodetype.ARRAY else 0)]


def new_message(typestore, msgtype: str, **fields) -> Message:
    """A message of ``msgtype`` with ``fields`` given and every other field zero / empty (as ROS 2 does)."""
    _, definitions = typestore.fielddefs[msgtype]
    if len(fields) < len(definitions):
        fields = {name: fields[name] if name in fields else _default_value(typestore, node)
                  for name, node in definitions} | fields
    try:
        return typestore.types[msgtype](**fields)
    except TypeError as error:
        raise TypeError(f"{msgtype}: {error}") from None


def stamp_to_ns(stamp: float) -> int:
    """Seconds (float) to integer nanoseconds; whole seconds split off first, so Unix-time stamps keep every bit."""
    whole = math.floor(stamp)
    return int(whole) * 1_000_000_000 + round((stamp - whole) * 1e9)


def ns_to_stamp(stamp_ns: int) -> float:
    """Integer nanoseconds to seconds (float), exact back to the stamp :func:`stamp_to_ns` was given."""
    whole, rest = divmod(int(stamp_ns), 1_000_000_000)
    return whole + rest / 1e9


def header_stamp(msg: Message) -> float:
    """A message header's time stamp in seconds."""
    return ns_to_stamp(msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec)


def make_header(typestore, stamp_ns: int, frame_id: str) -> Message:
    """A std_msgs/Header at ``stamp_ns``."""
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return new_message(typestore, "std_msgs/msg/Header",
                       stamp=new_message(typestore, "builtin_interfaces/msg/Time", sec=sec, nanosec=nanosec),
                       frame_id=frame_id)


def _reject(reason: str, detail: str) -> ValueError:
    return ValueError(f"{reason}: {detail}")


def reject_reason(error: ValueError) -> str:
    """The machine-friendly reason of a rejection raised here (the text before the first colon)."""
    return str(error).partition(":")[0]


def yaw_quaternion(typestore, theta: float) -> Message:
    """A geometry_msgs/Quaternion turning by ``theta`` about z (NaN gives a NaN quaternion: heading unknown)."""
    return new_message(typestore, "geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=math.sin(theta / 2),
                       w=math.cos(theta / 2))


def quaternion_yaw(q: Message) -> float:
    """The heading (rotation about z) of a geometry_msgs/Quaternion."""
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


# ---------------------------------------------------------------- controls: twist ⇄ fleetslam control
def ackermann_control(entry: RobotEntry, speed: float, turn_rate: float) -> np.ndarray:
    """(encoder speed, steering) of an Ackermann vehicle whose rear-axle centre moves at (v, ω): the exact
    inverse of :meth:`AckermannModel.to_unicycle` (tan α = ω·L / v, v_encoder = v − ω·H)."""
    if abs(speed) < MIN_ACKERMANN_SPEED:
        return np.array([speed - turn_rate * entry.encoder_offset, 0.0])
    steering = math.atan(turn_rate * entry.wheelbase / speed)
    return np.array([speed - turn_rate * entry.encoder_offset, steering])


def twist_of_control(entry: RobotEntry, controls: np.ndarray, covs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rear-axle twists (v, ω) ``(..., 2)`` of fleetslam controls ``(..., 2)`` and their covariances
    ``(..., 2, 2)`` (through the model's Jacobian)."""
    model = motion_model(entry.motion_model, entry.wheelbase, entry.encoder_offset)
    twist, jacobian = model.to_unicycle(np.asarray(controls, float))
    return twist, jacobian @ covs @ np.swapaxes(jacobian, -1, -2)


def _control_cov_of_twist(entry: RobotEntry, model, control: np.ndarray, twist_cov: np.ndarray) -> np.ndarray:
    """The control's covariance from the twist's (v, ω) covariance; ``odometry_std``² when the twist has none."""
    fallback = np.diag(np.square(entry.odometry_std))
    if not np.any(twist_cov):
        return fallback
    if entry.motion_model == "unicycle":
        return twist_cov
    if abs(control[0]) < MIN_ACKERMANN_SPEED:
        return fallback  # standing still: the Jacobian is singular
    _, jacobian = model.to_unicycle(control)
    (a, b), (c, d) = jacobian.tolist()
    determinant = a * d - b * c
    if determinant == 0.0:
        return fallback
    inverse = np.array([[d, -b], [-c, a]]) / determinant
    cov = inverse @ twist_cov @ inverse.T
    return 0.5 * (cov + cov.T)


# ---------------------------------------------------------------- import: one robot's messages → events
class RobotInput:
    """One ROS 2 robot's messages as fleetslam events: keeps the previous stamps and the per-stream seq."""

    def __init__(self, entry: RobotEntry, source: str | None = None):
        self.entry = entry
        self.source = source or f"ros2:{entry.namespace}"
        self.last_odom_stamp: float | None = None
        self.last_scan_stamp: float | None = None
        self.odom_seq = 0
        self.scan_seq = 0
        self.noise_cov = entry.sensor.spec().noise_cov
        self.model = motion_model(entry.motion_model, entry.wheelbase, entry.encoder_offset)
        self._extractor = None

    def info(self, stamp: float) -> RobotInfo:
        """The robot as fleetslam announces it (from the fleet entry)."""
        entry = self.entry
        start_cov = None if entry.start_pose is None else np.diag(np.square(entry.start_pose_std))
        limits = {"max_speed": entry.max_speed}
        limits.update({"max_turn_rate": entry.max_turn_rate} if entry.motion_model == "unicycle"
                      else {"max_steering": entry.max_steering})
        return RobotInfo(
            robot_id=entry.robot_id, stamp=stamp, motion_model=entry.motion_model, wheelbase=entry.wheelbase,
            encoder_offset=entry.encoder_offset, sensor=entry.sensor.spec(),
            start_pose=None if entry.start_pose is None else np.array(entry.start_pose), start_pose_cov=start_cov,
            source=self.source, odom_rate_hz=entry.odom_rate_hz, scan_rate_hz=entry.scan_rate_hz,
            turn_slip_var=entry.turn_slip_var, **limits)

    def _check(self, msg: Message, msgtype: str, frames: dict[str, str]) -> float:
        """The message's stamp, after its type and frames are checked (an empty frame is accepted)."""
        got = getattr(msg, "__msgtype__", type(msg).__name__)
        if got != msgtype:
            raise _reject("wrong_type", f"expected {msgtype}, got {got}")
        for field_name, expected in frames.items():
            value = msg.header.frame_id if field_name == "header" else getattr(msg, field_name)
            if value and value != expected:
                raise _reject("unknown_frame", f"{field_name} frame {value!r}, expected {expected!r}")
        return header_stamp(msg)

    def odometry(self, msg: Message) -> OdomEvent | None:
        """The control that acted up to this message's stamp; None for the first message (it starts the clock)."""
        entry = self.entry
        if entry.odometry_type == "nav_msgs/msg/Odometry":
            stamp = self._check(msg, entry.odometry_type, {"header": entry.odom_frame, "child_frame_id": entry.base_frame})
            twist, twist_cov_6 = msg.twist.twist, np.asarray(msg.twist.covariance, float)
            if twist_cov_6.shape != (36,):
                raise _reject("bad_shape", f"twist covariance has {twist_cov_6.size} values, expected 36")
        else:
            stamp = self._check(msg, entry.odometry_type, {"header": entry.base_frame})
            twist, twist_cov_6 = msg.twist, np.zeros(36)
        speed, turn_rate = float(twist.linear.x), float(twist.angular.z)
        vv, vw, wv, ww = twist_cov_6[[0, 5, 30, 35]].tolist()  # the (v, ω) block of the 6 × 6 twist covariance
        if not all(map(math.isfinite, (speed, turn_rate, vv, vw, wv, ww))):
            raise _reject("non_finite", "twist or its covariance is NaN or infinite")
        if vv < 0 or ww < 0 or abs(vw - wv) > 1e-6 * max(abs(vw), abs(wv)) + 1e-12:
            raise _reject("bad_covariance", "the (v, ω) block of the twist covariance is not a covariance")
        twist_cov = np.array([[vv, vw], [wv, ww]])
        previous = self.last_odom_stamp
        if previous is None:
            self.last_odom_stamp = stamp
            return None
        if stamp <= previous:
            raise _reject("time_backwards", f"odometry stamp {stamp!r} not after {previous!r}")
        self.last_odom_stamp = stamp
        dt = stamp - previous
        if dt > entry.max_odom_gap_s:
            raise _reject("time_gap", f"{dt:.3f} s since the previous odometry (max {entry.max_odom_gap_s:g} s): "
                          "the clock starts again here")
        if entry.motion_model == "unicycle":
            control = np.array([speed, turn_rate])
        else:
            control = ackermann_control(entry, speed, turn_rate)
        cov = _control_cov_of_twist(entry, self.model, control, twist_cov)
        event = OdomEvent(entry.robot_id, self.odom_seq, stamp, dt, control, cov)
        self.odom_seq += 1
        return event

    def landmarks(self, msg: Message) -> ScanEvent:
        """The detections of one landmark message: ranges from the sensor, bearings in the body frame."""
        entry = self.entry
        stamp = self._check(msg, entry.landmarks_type, {"header": entry.sensor_frame})
        if self.last_scan_stamp is not None and stamp < self.last_scan_stamp:
            raise _reject("time_backwards", f"landmarks stamp {stamp!r} before {self.last_scan_stamp!r}")
        if entry.landmarks_type == "geometry_msgs/msg/PoseArray":
            ranges, bearings = self._pose_array(msg)
        else:
            ranges, bearings = self._laser_scan(msg)
        self.last_scan_stamp = stamp
        event = ScanEvent(entry.robot_id, self.scan_seq, stamp, ranges, bearings, None, self.noise_cov)
        self.scan_seq += 1
        return event

    def _pose_array(self, msg: Message) -> tuple[np.ndarray, np.ndarray]:
        points = np.array([(p.position.x, p.position.y) for p in msg.poses], float).reshape(-1, 2)
        if not np.all(np.isfinite(points)):
            raise _reject("non_finite", "a detection's position is NaN or infinite")
        ranges = np.hypot(points[:, 0], points[:, 1])
        bearings = wrap_angle(np.arctan2(points[:, 1], points[:, 0]) + self.entry.sensor.yaw)
        return ranges, np.asarray(bearings, float).reshape(-1)

    def _laser_scan(self, msg: Message) -> tuple[np.ndarray, np.ndarray]:
        from robots.features import extract_point_landmarks

        if self._extractor is None:
            self._extractor = self.entry.extractor_config()
        angle_min, increment = float(msg.angle_min), float(msg.angle_increment)
        if not (math.isfinite(angle_min) and math.isfinite(increment)):
            raise _reject("non_finite", "angle_min or angle_increment is not finite")
        ranges = np.asarray(msg.ranges, float)
        intensities = np.asarray(msg.intensities, float) if len(msg.intensities) else None
        if ranges.ndim != 1 or increment <= 0 or (intensities is not None and intensities.shape != ranges.shape):
            raise _reject("bad_shape", f"{ranges.size} ranges, {0 if intensities is None else intensities.size} "
                          f"intensities, angle increment {increment!r}")
        found = extract_point_landmarks(ranges, angle_min, increment, intensities, self._extractor)
        bearings = wrap_angle(np.asarray(found.bearing, float) + self.entry.sensor.yaw)
        return np.asarray(found.range, float), np.asarray(bearings, float).reshape(-1)


# ---------------------------------------------------------------- export: a RobotLog → ROS 2 messages
def fleet_entry_for(log: RobotLog) -> RobotEntry:
    """A fleet entry describing a loaded robot: its models and noise, ``odom`` / ``landmarks`` (PoseArray) topics,
    ``ground_truth`` when the log has truth."""
    info = log.info
    odom_cov = log.odom_cov if log.odom_cov.ndim == 2 else (log.odom_cov[0] if len(log.odom_cov) else np.eye(2))
    sensor = info.sensor
    start_std = None if info.start_pose_cov is None else tuple(float(s) for s in np.sqrt(np.diag(info.start_pose_cov)))
    return RobotEntry(
        robot_id=log.robot_id, motion_model=info.motion_model, wheelbase=info.wheelbase,
        encoder_offset=info.encoder_offset,
        odometry_std=tuple(float(s) for s in np.sqrt(np.maximum(np.diag(odom_cov), 1e-18))),
        turn_slip_var=info.turn_slip_var, max_speed=info.max_speed, max_turn_rate=info.max_turn_rate,
        max_steering=info.max_steering,
        truth_topic="ground_truth" if log.truth_stamp.size else None,
        sensor=dict(min_range=sensor.min_range, max_range=sensor.max_range, fov=sensor.fov,
                    range_std=math.sqrt(log.scan_cov[0, 0]), bearing_std=math.sqrt(log.scan_cov[1, 1]),
                    offset=tuple(float(v) for v in sensor.offset), detection_probability=sensor.detection_probability,
                    clutter_rate=sensor.clutter_rate),
        start_pose=None if info.start_pose is None else tuple(float(v) for v in info.start_pose),
        **({"start_pose_std": start_std} if start_std else {}),
        odom_rate_hz=info.odom_rate_hz, scan_rate_hz=info.scan_rate_hz,
    )


def _odometry_message(typestore, entry: RobotEntry, stamp_ns: int, pose: np.ndarray, twist: np.ndarray,
                      twist_cov: np.ndarray) -> Message:
    covariance = np.zeros((6, 6))
    covariance[0, 0], covariance[0, 5], covariance[5, 0], covariance[5, 5] = twist_cov.ravel().tolist()
    vector = "geometry_msgs/msg/Vector3"
    return new_message(
        typestore, "nav_msgs/msg/Odometry", header=make_header(typestore, stamp_ns, entry.odom_frame),
        child_frame_id=entry.base_frame,
        pose=new_message(typestore, "geometry_msgs/msg/PoseWithCovariance", pose=new_message(
            typestore, "geometry_msgs/msg/Pose",
            position=new_message(typestore, "geometry_msgs/msg/Point", x=float(pose[0]), y=float(pose[1])),
            orientation=yaw_quaternion(typestore, float(pose[2])))),
        twist=new_message(typestore, "geometry_msgs/msg/TwistWithCovariance", twist=new_message(
            typestore, "geometry_msgs/msg/Twist", linear=new_message(typestore, vector, x=float(twist[0])),
            angular=new_message(typestore, vector, z=float(twist[1]))), covariance=covariance.reshape(36)))


def _pose_array_message(typestore, entry: RobotEntry, stamp_ns: int, ranges: np.ndarray,
                        bearings: np.ndarray) -> Message:
    angles = bearings - entry.sensor.yaw
    xs, ys = ranges * np.cos(angles), ranges * np.sin(angles)
    identity = yaw_quaternion(typestore, 0.0)
    poses = [new_message(typestore, "geometry_msgs/msg/Pose",
                         position=new_message(typestore, "geometry_msgs/msg/Point", x=float(x), y=float(y)),
                         orientation=identity) for x, y in zip(xs.tolist(), ys.tolist())]
    return new_message(typestore, "geometry_msgs/msg/PoseArray",
                       header=make_header(typestore, stamp_ns, entry.sensor_frame), poses=poses)


def _truth_message(typestore, map_frame: str, stamp_ns: int, pose: np.ndarray) -> Message:
    return new_message(typestore, TRUTH_TYPE, header=make_header(typestore, stamp_ns, map_frame),
                       pose=new_message(typestore, "geometry_msgs/msg/Pose", position=new_message(
                           typestore, "geometry_msgs/msg/Point", x=float(pose[0]), y=float(pose[1])),
                           orientation=yaw_quaternion(typestore, float(pose[2]))))


def _odometry_messages(log: RobotLog, entry: RobotEntry, typestore) -> Iterator[tuple]:
    """(stamp_ns, rank, topic, msgtype, message) of the odometry: a clock-start message at the first interval's
    start (and after every gap), then one per control at the end of its interval."""
    if not log.odom_stamp.size:
        return
    topic, msgtype = entry.topic(entry.odometry_topic), "nav_msgs/msg/Odometry"
    model = motion_model(entry.motion_model, entry.wheelbase, entry.encoder_offset)
    covs = np.broadcast_to(log.odom_cov, (log.odom_stamp.size, 2, 2))
    twists, twist_covs = twist_of_control(entry, log.odom_control, covs)
    start = np.zeros(3) if log.info.start_pose is None else np.asarray(log.info.start_pose, float)
    relative = dead_reckon(model, log.odom_control, log.odom_dt)
    c, s = math.cos(start[2]), math.sin(start[2])
    poses = np.column_stack([start[0] + c * relative[:, 0] - s * relative[:, 1],
                             start[1] + s * relative[:, 0] + c * relative[:, 1],
                             wrap_angle(start[2] + relative[:, 2])])
    still = np.zeros(2)
    previous_end = None
    for k, (stamp, dt) in enumerate(zip(log.odom_stamp.tolist(), log.odom_dt.tolist())):
        begin = stamp - dt
        if previous_end is None or abs(begin - previous_end) > CONTIGUOUS_S:
            begin_ns = stamp_to_ns(begin)
            yield begin_ns, 0, topic, msgtype, _odometry_message(typestore, entry, begin_ns, poses[k], still,
                                                                 np.zeros((2, 2)))
        stamp_ns = stamp_to_ns(stamp)
        yield stamp_ns, 0, topic, msgtype, _odometry_message(typestore, entry, stamp_ns, poses[k + 1], twists[k],
                                                             twist_covs[k])
        previous_end = stamp


def _scan_messages(log: RobotLog, entry: RobotEntry, typestore) -> Iterator[tuple]:
    topic, msgtype = entry.topic(entry.landmarks_topic), "geometry_msgs/msg/PoseArray"
    for k, stamp in enumerate(log.scan_stamp.tolist()):
        lo, hi = log.scan_offsets[k], log.scan_offsets[k + 1]
        stamp_ns = stamp_to_ns(stamp)
        yield stamp_ns, 1, topic, msgtype, _pose_array_message(typestore, entry, stamp_ns, log.det_range[lo:hi],
                                                               log.det_bearing[lo:hi])


def _truth_messages(log: RobotLog, entry: RobotEntry, typestore, map_frame: str) -> Iterator[tuple]:
    if entry.truth_topic is None:
        return
    topic = entry.topic(entry.truth_topic)
    for k, stamp in enumerate(log.truth_stamp.tolist()):
        stamp_ns = stamp_to_ns(stamp)
        yield stamp_ns, 2, topic, TRUTH_TYPE, _truth_message(typestore, map_frame, stamp_ns, log.truth_pose[k])


def robot_log_messages(log: RobotLog, entry: RobotEntry, typestore, map_frame: str = "map") -> Iterator[tuple]:
    """(topic, msgtype, stamp_ns, message) of one robot's log in time order (at equal stamps odometry, then
    landmarks, then truth): Odometry per control, PoseArray per scan, PoseStamped per true pose when the entry has
    a ``truth_topic``."""
    merged = heapq.merge(_odometry_messages(log, entry, typestore), _scan_messages(log, entry, typestore),
                         _truth_messages(log, entry, typestore, map_frame), key=lambda item: item[:2])
    for stamp_ns, _, topic, msgtype, message in merged:
        yield topic, msgtype, stamp_ns, message


def landmarks_truth_message(typestore, map_frame: str, stamp_ns: int, landmarks: np.ndarray,
                            landmark_ids: np.ndarray | None) -> Message:
    """The true landmark map as a visualization_msgs/MarkerArray: one cylinder per landmark, id = landmark id."""
    ids = np.arange(len(landmarks)) if landmark_ids is None else np.asarray(landmark_ids)
    header = make_header(typestore, stamp_ns, map_frame)
    markers = [new_message(
        typestore, "visualization_msgs/msg/Marker", header=header, ns="landmarks", id=int(i), type=3,
        pose=new_message(typestore, "geometry_msgs/msg/Pose", position=new_message(
            typestore, "geometry_msgs/msg/Point", x=float(x), y=float(y)), orientation=yaw_quaternion(typestore, 0.0)),
        scale=new_message(typestore, "geometry_msgs/msg/Vector3", x=0.2, y=0.2, z=1.0),
        color=new_message(typestore, "std_msgs/msg/ColorRGBA", r=0.2, g=0.6, b=0.2, a=1.0))
        for (x, y), i in zip(np.asarray(landmarks, float).tolist(), ids.tolist())]
    return new_message(typestore, LANDMARKS_TRUTH_TYPE, markers=markers)


def landmarks_truth(msg: Message) -> tuple[np.ndarray, np.ndarray]:
    """(landmarks (L, 2), ids (L,)) of a true-map MarkerArray."""
    points = np.array([(m.pose.position.x, m.pose.position.y) for m in msg.markers], float).reshape(-1, 2)
    return points, np.array([m.id for m in msg.markers], np.int64)


def truth_pose(msg: Message) -> tuple[float, np.ndarray]:
    """(stamp, pose (x, y, θ)) of a true-pose PoseStamped (θ NaN when its orientation is NaN)."""
    p, q = msg.pose.position, msg.pose.orientation
    theta = quaternion_yaw(q) if all(map(math.isfinite, (q.z, q.w))) else math.nan
    return header_stamp(msg), np.array([p.x, p.y, theta])
