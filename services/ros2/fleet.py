"""The fleet file: which ROS 2 robots join fleetslam, on which topics, with which models (YAML, pydantic).

One file serves the live bridge (``fleetslam ros2``) and ROS 2 bags (``rosbag2:`` data sets, ``fleetslam
export rosbag2`` writes one beside the bag). Each robot entry says where its odometry and landmarks are
published (topic names relative to the robot's namespace, message types), its motion model, its sensor
(limits, noise, mounting) and what fleetslam cannot read from the messages (noise when a message carries no
covariance, start pose, rates). :func:`load_fleet` reads and checks a file; every error names the file and the
field (``robots.0.sensor.max_range``).
"""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from schemas.messages import ROBOT_ID_PATTERN, SensorSpec

ROS_NAME = r"[A-Za-z_][A-Za-z0-9_]*"
NAMESPACE_PATTERN = rf"^/({ROS_NAME}(/{ROS_NAME})*)?$"
TOPIC_PATTERN = rf"^/?{ROS_NAME}(/{ROS_NAME})*$"
FRAME_PATTERN = r"^[A-Za-z0-9_][A-Za-z0-9_/.-]*$"

RosDistro = Literal["humble", "jazzy", "kilted", "rolling"]
OdometryType = Literal["nav_msgs/msg/Odometry", "geometry_msgs/msg/TwistStamped"]
LandmarksType = Literal["geometry_msgs/msg/PoseArray", "sensor_msgs/msg/LaserScan"]
TRUTH_TYPE = "geometry_msgs/msg/PoseStamped"
LANDMARKS_TRUTH_TYPE = "visualization_msgs/msg/MarkerArray"


class FleetFileError(ValueError):
    """A fleet file that cannot be read or does not validate; the message names the file and the field."""


def default_namespace(robot_id: str) -> str:
    """``/`` + the robot id made a ROS name (``-`` becomes ``_``; a leading digit gets ``robot_`` before it)."""
    name = robot_id.replace("-", "_")
    return "/" + ("robot_" + name if name[0].isdigit() else name)


class FleetModel(BaseModel):
    """Base of the fleet file's sections: unknown fields are errors (a typo must not pass silently)."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class SensorEntry(FleetModel):
    """The landmark sensor: limits, noise, where it sits on the robot."""

    min_range: float = Field(0.0, ge=0.0, allow_inf_nan=False, description="nearest detection (m)")
    max_range: float = Field(30.0, gt=0.0, allow_inf_nan=False, description="farthest detection (m)")
    fov: float = Field(2 * math.pi, gt=0.0, le=2 * math.pi, allow_inf_nan=False,
                       description="total field of view (rad), centred on the sensor's x axis")
    range_std: float = Field(0.1, gt=0.0, allow_inf_nan=False, description="σ of a detection's range (m)")
    bearing_std: float = Field(0.02, gt=0.0, allow_inf_nan=False, description="σ of a detection's bearing (rad)")
    offset: tuple[float, float] = Field((0.0, 0.0), description="sensor position (x, y) in the base frame (m)")
    yaw: float = Field(0.0, ge=-math.pi, le=math.pi, allow_inf_nan=False,
                       description="sensor heading in the base frame (rad); bearings are turned into the base frame by it")
    detection_probability: float = Field(1.0, ge=0.0, le=1.0, description="share of landmarks in view it detects")
    clutter_rate: float = Field(0.0, ge=0.0, description="expected false detections per scan")

    def spec(self) -> SensorSpec:
        """The sensor as fleetslam announces it in RobotInfo."""
        return SensorSpec(min_range=self.min_range, max_range=self.max_range, fov=self.fov,
                          noise_cov=np.diag([self.range_std**2, self.bearing_std**2]), offset=np.array(self.offset),
                          detection_probability=self.detection_probability, clutter_rate=self.clutter_rate)


class RobotEntry(FleetModel):
    """One ROS 2 robot: its fleetslam id, its topics and frames, its motion and sensor models."""

    robot_id: str = Field(pattern=ROBOT_ID_PATTERN, description="fleetslam robot id (letters, digits, _ and -)")
    namespace: str = Field("", description="ROS namespace of the robot's topics (default: / + robot_id)")
    odometry_topic: str = Field("odom", pattern=TOPIC_PATTERN, description="odometry topic, relative to the namespace")
    odometry_type: OdometryType = Field("nav_msgs/msg/Odometry", description="odometry message type")
    landmarks_topic: str = Field("landmarks", pattern=TOPIC_PATTERN,
                                 description="landmark detections (or laser scans) topic, relative to the namespace")
    landmarks_type: LandmarksType = Field(
        "geometry_msgs/msg/PoseArray",
        description="PoseArray: detections' positions in the sensor frame; LaserScan: point landmarks extracted here")
    truth_topic: str | None = Field(
        None, pattern=TOPIC_PATTERN, description="optional true poses (geometry_msgs/msg/PoseStamped in the map "
        "frame; a NaN orientation means heading unknown), for scoring only")
    motion_model: Literal["unicycle", "ackermann"] = Field("unicycle", description="how controls move the robot")
    wheelbase: float = Field(0.0, ge=0.0, allow_inf_nan=False, description="ackermann: wheelbase L (m)")
    encoder_offset: float = Field(0.0, allow_inf_nan=False,
                                  description="ackermann: lateral offset H of the encoder wheel from the rear-axle centre (m)")
    odometry_std: tuple[float, float] = Field(
        (0.05, 0.1), description="σ of the control when a message has no covariance: unicycle (m/s, rad/s), "
        "ackermann (m/s, rad of steering)")
    turn_slip_var: float = Field(0.0, ge=0.0, allow_inf_nan=False,
                                 description="heading variance (rad²) per radian turned that the odometry noise leaves out")
    max_speed: float | None = Field(None, gt=0.0, description="largest |speed| the odometry may report (m/s)")
    max_turn_rate: float | None = Field(None, gt=0.0, description="unicycle: largest |ω| (rad/s)")
    max_steering: float | None = Field(None, gt=0.0, le=math.pi / 2, description="ackermann: largest |steering| (rad)")
    max_odom_gap_s: float = Field(10.0, gt=0.0, le=10.0,
                                  description="an odometry message after a longer silence restarts the clock (s)")
    sensor: SensorEntry = Field(default_factory=SensorEntry, description="the landmark sensor")
    base_frame: str = Field("", description="robot body frame (odometry child frame); default NAMESPACE/base_link")
    odom_frame: str = Field("", description="odometry frame (odometry header frame); default NAMESPACE/odom")
    sensor_frame: str = Field("", description="frame of the landmarks / scans header; default NAMESPACE/sensor")
    start_pose: tuple[float, float, float] | None = Field(None, description="start pose (x, y, θ) in the map frame, if known")
    start_pose_std: tuple[float, float, float] = Field((1e-3, 1e-3, 1e-3), description="σ of the start pose (m, m, rad)")
    truth_offset: tuple[float, float] = Field((0.0, 0.0),
                                              description="body-frame point (x, y) the true positions refer to (m)")
    odom_rate_hz: float = Field(10.0, gt=0.0, description="odometry rate announced in RobotInfo (Hz)")
    scan_rate_hz: float = Field(10.0, gt=0.0, description="landmark message rate announced in RobotInfo (Hz)")
    extractor: dict[str, Any] | None = Field(
        None, description="LaserScan only: robots.features.ExtractorConfig fields (point-landmark extraction)")

    @model_validator(mode="before")
    @classmethod
    def _default_namespace(cls, data: Any) -> Any:
        """The namespace defaults to / + robot id, and the frames to the namespace's (``robot1/odom``): the robots
        of a fleet share one ``/tf``, where two ``odom`` frames would be one."""
        if isinstance(data, dict) and not data.get("namespace") and isinstance(data.get("robot_id"), str) \
                and re.match(ROBOT_ID_PATTERN, data["robot_id"]):
            data = {**data, "namespace": default_namespace(data["robot_id"])}
        if isinstance(data, dict) and isinstance(data.get("namespace"), str):
            prefix = data["namespace"].strip("/")
            for name, frame in (("base_frame", "base_link"), ("odom_frame", "odom"), ("sensor_frame", "sensor")):
                if not data.get(name):
                    data = {**data, name: f"{prefix}/{frame}" if prefix else frame}
        return data

    @model_validator(mode="after")
    def _consistent(self) -> "RobotEntry":
        if not re.match(NAMESPACE_PATTERN, self.namespace):
            raise ValueError(f"namespace {self.namespace!r} is not a ROS namespace (/name/name...)")
        for name in ("base_frame", "odom_frame", "sensor_frame"):
            if not re.match(FRAME_PATTERN, getattr(self, name)):
                raise ValueError(f"{name} {getattr(self, name)!r} is not a frame id (letters, digits, _ / . -)")
        if self.motion_model == "ackermann" and not self.wheelbase > 0:
            raise ValueError("an ackermann robot needs its wheelbase (> 0 m)")
        if not all(math.isfinite(s) and s > 0 for s in self.odometry_std):
            raise ValueError(f"odometry_std must be two finite σ > 0, got {self.odometry_std}")
        if self.start_pose is not None and not all(map(math.isfinite, self.start_pose)):
            raise ValueError(f"start_pose must be finite, got {self.start_pose}")
        if not all(math.isfinite(s) and s > 0 for s in self.start_pose_std):
            raise ValueError(f"start_pose_std must be three finite σ > 0, got {self.start_pose_std}")
        if self.extractor is not None:
            if self.landmarks_type != "sensor_msgs/msg/LaserScan":
                raise ValueError("extractor is only for landmarks_type sensor_msgs/msg/LaserScan")
            self.extractor_config()
        return self

    def topic(self, name: str) -> str:
        """The full topic name: ``name`` under the namespace (``odom`` -> ``/robot1/odom``); absolute names stay."""
        return name if name.startswith("/") else f"{self.namespace.rstrip('/')}/{name}"

    def extractor_config(self):
        """The LaserScan point-landmark extractor's configuration (robots.features, imported here only)."""
        from robots.features import ExtractorConfig

        known = {f.name for f in dataclasses.fields(ExtractorConfig)}
        unknown = sorted(set(self.extractor or {}) - known)
        if unknown:
            raise ValueError(f"extractor: unknown field(s) {', '.join(unknown)} (known: {', '.join(sorted(known))})")
        return ExtractorConfig(**(self.extractor or {}))


class FleetFile(FleetModel):
    """The fleet: ROS distribution, domain, map frame and the robots."""

    ros_distro: RosDistro = Field("jazzy", description="selects the message definitions and type hashes (humble: no hash)")
    domain_id: int = Field(0, ge=0, le=232, description="ROS domain id (the first chunk of rmw_zenoh keys)")
    map_frame: str = Field("map", pattern=FRAME_PATTERN, description="frame of fleetslam's map and estimates")
    landmarks_truth_topic: str | None = Field(
        None, pattern=TOPIC_PATTERN, description="optional true landmark map (visualization_msgs/msg/MarkerArray, "
        "marker id = landmark id), for scoring only")
    robots: list[RobotEntry] = Field(min_length=1, description="the robots")

    @model_validator(mode="after")
    def _distinct(self) -> "FleetFile":
        ids = [r.robot_id for r in self.robots]
        if len(set(ids)) != len(ids):
            raise ValueError(f"robot ids repeat: {', '.join(sorted({i for i in ids if ids.count(i) > 1}))}")
        topics = [robot.topic(name) for robot in self.robots
                  for name in (robot.odometry_topic, robot.landmarks_topic, robot.truth_topic) if name]
        repeated = sorted({t for t in topics if topics.count(t) > 1})
        if repeated:
            raise ValueError(f"topics used twice: {', '.join(repeated)}")
        return self

    def robot(self, robot_id: str) -> RobotEntry:
        """The entry of ``robot_id`` (KeyError naming the known ids)."""
        for entry in self.robots:
            if entry.robot_id == robot_id:
                return entry
        raise KeyError(f"robot {robot_id!r} is not in the fleet (it has {', '.join(r.robot_id for r in self.robots)})")


def _describe(error: ValidationError) -> str:
    """Every problem of a validation error, one ``field.path: message`` each, joined by ``; ``."""
    lines = []
    for item in error.errors():
        where = ".".join(str(part) for part in item["loc"])
        message = item["msg"].removeprefix("Value error, ")
        given = item.get("input")
        if where and isinstance(given, (str, int, float, bool)) and item["type"] != "value_error":
            message += f" (got {given!r})"
        lines.append(f"{where}: {message}" if where else message)
    return "; ".join(lines)


def parse_fleet(data: Any, source: str = "fleet file") -> FleetFile:
    """A FleetFile from parsed YAML (a mapping); :class:`FleetFileError` naming ``source`` and each bad field."""
    if not isinstance(data, dict):
        raise FleetFileError(f"{source}: expected a mapping with a 'robots' list, got {type(data).__name__}")
    try:
        return FleetFile(**data)
    except ValidationError as error:
        raise FleetFileError(f"{source}: {_describe(error)}") from None


def load_fleet(path: str | Path) -> FleetFile:
    """Read and check a fleet file (YAML)."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as error:
        raise FleetFileError(f"fleet file {path}: cannot read it ({error.strerror or error})") from None
    except yaml.YAMLError as error:
        raise FleetFileError(f"fleet file {path}: not valid YAML ({str(error).splitlines()[0]})") from None
    return parse_fleet(data, f"fleet file {path}")


def fleet_yaml(fleet: FleetFile) -> str:
    """The fleet file as YAML text (what :func:`load_fleet` reads back to an equal FleetFile)."""
    data = fleet.model_dump(mode="json")
    data["robots"] = [{k: v for k, v in robot.items() if v is not None} for robot in data["robots"]]
    return yaml.safe_dump({k: v for k, v in data.items() if v is not None}, sort_keys=False, default_flow_style=None)


def save_fleet(fleet: FleetFile, path: str | Path) -> None:
    """Write the fleet file as YAML."""
    Path(path).write_text(fleet_yaml(fleet))
