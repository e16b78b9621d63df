"""Pydantic models of the messages that cross Zenoh (DESIGN §2).

Arrays are numpy arrays validated for dtype, shape and finiteness; the codec
(:mod:`schemas.codec`) packs them as little-endian binary. Conventions (DESIGN
§3): SI units, angles in radians wrapped to [-π, π), poses (x, y, θ),
observations (range, bearing) in the sensor frame, noise as covariances.
"""

from __future__ import annotations

import math
from typing import Annotated, Any, ClassVar, Literal

import numpy as np
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, PlainSerializer, ValidationInfo, model_validator

ROBOT_ID_PATTERN = r"^[A-Za-z0-9_-]{1,64}$"
RobotId = Annotated[str, Field(pattern=ROBOT_ID_PATTERN)]
FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]


def _symmetric(array: np.ndarray) -> bool:
    """Symmetric in its last two axes, exactly (the usual case, cheap) or within rounding."""
    swapped = np.swapaxes(array, -1, -2)
    return bool(np.array_equal(array, swapped)) or bool(np.allclose(array, swapped, atol=1e-9, rtol=1e-6))


def _array_validator(shape: tuple[int | None, ...], kind: str, finite: bool, nonnegative: bool, symmetric: bool):
    dtype = {"float": np.float64, "int": np.int64, "bool": np.bool_}[kind]

    def validate(value: Any, info: ValidationInfo) -> np.ndarray:
        if isinstance(value, (list, tuple)) or np.isscalar(value):
            if info.context and info.context.get("wire"):
                raise ValueError("arrays must travel as packed binary, not as lists")
            value = np.asarray(value)
        if not isinstance(value, np.ndarray):
            raise ValueError(f"expected an array, got {type(value).__name__}")
        if value.ndim != len(shape) or any(want is not None and got != want for got, want in zip(value.shape, shape)):
            expected = "(" + ", ".join("n" if s is None else str(s) for s in shape) + ")"
            raise ValueError(f"shape {value.shape} does not match {expected}")
        if kind == "float" and value.dtype.kind not in "fiu":
            raise ValueError(f"dtype {value.dtype} is not numeric")
        if kind == "int" and value.dtype.kind not in "iu":
            raise ValueError(f"dtype {value.dtype} is not integer")
        if kind == "bool" and value.dtype.kind != "b":
            raise ValueError(f"dtype {value.dtype} is not boolean")
        array = value.astype(dtype, copy=False)
        if finite and kind == "float" and not np.all(np.isfinite(array)):
            raise ValueError("contains NaN or infinity")
        if nonnegative and np.any(array < 0):
            raise ValueError("contains negative values")
        if symmetric and array.size and not _symmetric(array):
            raise ValueError("covariance is not symmetric")
        return array

    return validate


def Array(*shape: int | None, kind: str = "float", finite: bool = True, nonnegative: bool = False, symmetric: bool = False):
    """An annotated numpy array field of a given shape (``None`` = any length)."""
    return Annotated[
        np.ndarray,
        BeforeValidator(_array_validator(shape, kind, finite, nonnegative, symmetric)),
        PlainSerializer(lambda a: a, return_type=Any, when_used="always"),
    ]


Pose = Array(3)
Covariance2 = Array(2, 2, symmetric=True)
Covariance3 = Array(3, 3, symmetric=True)


class Message(BaseModel):
    """Base of every message: strict fields, numpy arrays allowed, a schema version."""

    model_config = ConfigDict(arbitrary_types_allowed=True, extra="forbid", validate_assignment=False)
    SCHEMA_VERSION: ClassVar[int] = 1


class StreamMessage(Message):
    """A message of a per-robot stream: robot id, per-stream seq (0, 1, ...) and stamp (s)."""

    robot_id: RobotId
    seq: int = Field(ge=0)
    stamp: FiniteFloat


class SensorSpec(BaseModel):
    """A range-bearing sensor: limits, field of view, noise covariance of (r, φ)."""

    model_config = ConfigDict(arbitrary_types_allowed=True, extra="forbid")
    min_range: float = Field(0.0, ge=0.0, allow_inf_nan=False)
    max_range: float = Field(gt=0.0, allow_inf_nan=False)
    fov: float = Field(gt=0.0, le=2 * math.pi + 1e-9, description="total field of view (rad), centred ahead")
    noise_cov: Covariance2
    offset: Array(2) = Field(default_factory=lambda: np.zeros(2), description="sensor position (a, b) in the body frame")
    detection_probability: float = Field(1.0, ge=0.0, le=1.0)
    clutter_rate: float = Field(0.0, ge=0.0, description="expected false detections per scan")


class RobotInfo(Message):
    """What a robot is: motion model and parameters, sensor, start pose if known."""

    robot_id: RobotId
    stamp: FiniteFloat
    motion_model: Literal["unicycle", "ackermann"]
    wheelbase: float = Field(0.0, ge=0.0, allow_inf_nan=False, description="ackermann L (m)")
    encoder_offset: float = Field(0.0, allow_inf_nan=False, description="ackermann H: rear-axle centre to encoder wheel (m)")
    sensor: SensorSpec
    start_pose: Pose | None = None
    start_pose_cov: Covariance3 | None = None
    source: str = Field("sim", description="sim:WORLD or replay:DATASET")
    odom_rate_hz: float = Field(gt=0.0, allow_inf_nan=False)
    scan_rate_hz: float = Field(gt=0.0, allow_inf_nan=False)
    max_speed: float | None = Field(None, gt=0.0, allow_inf_nan=False,
                                    description="largest |speed| its odometry reports (m/s): unicycle v, ackermann encoder speed")
    max_turn_rate: float | None = Field(None, gt=0.0, allow_inf_nan=False, description="unicycle: largest |ω| (rad/s)")
    max_steering: float | None = Field(None, gt=0.0, le=math.pi / 2, allow_inf_nan=False,
                                       description="ackermann: largest |steering angle| (rad)")
    turn_slip_var: float = Field(
        0.0, ge=0.0, allow_inf_nan=False,
        description="heading variance (rad²) per radian turned that the odometry covariance leaves out: wheels "
        "slip in turns (robots.gaussian.turn_slip; D-SLAM widens its association gate by it, FastSLAM its motion when "
        "asked)")

    @model_validator(mode="after")
    def _ackermann_has_wheelbase(self) -> "RobotInfo":
        if self.motion_model == "ackermann" and not self.wheelbase > 0:
            raise ValueError("an ackermann robot must announce its wheelbase (> 0 m)")
        return self


class Odometry(StreamMessage):
    """Control applied over ``dt``: (v, ω) for unicycle, (encoder speed, steering) for ackermann."""

    dt: float = Field(gt=0.0, le=10.0, allow_inf_nan=False)
    control: Array(2)
    control_cov: Covariance2


class Scan(StreamMessage):
    """Range-bearing detections at one instant, in the sensor frame."""

    ranges: Array(None, nonnegative=True)
    bearings: Array(None)
    landmark_ids: Array(None, kind="int") | None = Field(None, description="true landmark id per detection, -1 unknown")
    noise_cov: Covariance2
    robot_ids: list[RobotId] = Field(default_factory=list, description="other robots detected")
    robot_ranges: Array(None, nonnegative=True) = Field(default_factory=lambda: np.zeros(0))
    robot_bearings: Array(None) = Field(default_factory=lambda: np.zeros(0))

    @model_validator(mode="after")
    def _lengths_agree(self) -> "Scan":
        n = self.ranges.shape[0]
        if self.bearings.shape[0] != n:
            raise ValueError(f"{n} ranges but {self.bearings.shape[0]} bearings")
        if self.landmark_ids is not None and self.landmark_ids.shape[0] != n:
            raise ValueError(f"{n} ranges but {self.landmark_ids.shape[0]} landmark ids")
        m = len(self.robot_ids)
        if self.robot_ranges.shape[0] != m or self.robot_bearings.shape[0] != m:
            raise ValueError("robot detections: ids, ranges and bearings differ in length")
        if np.any(np.abs(self.bearings) > math.pi + 1e-9) or np.any(np.abs(self.robot_bearings) > math.pi + 1e-9):
            raise ValueError("bearing outside [-π, π]")
        return self

    def __len__(self) -> int:
        return int(self.ranges.shape[0])


class GroundTruth(StreamMessage):
    """The true pose of a robot (simulator, or a data set's truth).

    GPS-like truth has no heading: then ``heading_known`` is false and θ is 0 on the wire.
    """

    pose: Pose
    heading_known: bool = True


class WorldTruth(Message):
    """The true landmark map (published once on ``fleet/world/truth`` and to late joiners)."""

    world: str
    stamp: FiniteFloat
    landmarks: Array(None, 2)
    landmark_ids: Array(None, kind="int")

    @model_validator(mode="after")
    def _lengths_agree(self) -> "WorldTruth":
        if self.landmark_ids.shape[0] != self.landmarks.shape[0]:
            raise ValueError("landmarks and landmark_ids differ in length")
        return self


class RobotEstimate(BaseModel):
    """One robot's pose estimate inside an :class:`Estimate`."""

    model_config = ConfigDict(arbitrary_types_allowed=True, extra="forbid")
    robot_id: RobotId
    stamp: FiniteFloat
    pose: Pose
    cov: Covariance3


class TiledMapMessage(Message):
    """A map output sent by tiles (:mod:`schemas.maptiles`): ``full`` lists every tile of the map, otherwise only
    the tiles that changed since the message numbered ``seq`` − 1; ``tiles`` (k, 2) are tile indices (⌊x / tile_size⌋,
    ⌊y / tile_size⌋), ``tile_counts`` how many of ``landmarks``, in order, each listed tile holds now (0 empties it).
    A full message may leave ``tiles`` empty: its landmarks are then the whole map. Receivers assemble the map with
    :class:`schemas.maptiles.TiledMap` (services: :class:`services.mapfeed.MapFeed`)."""

    SCHEMA_VERSION: ClassVar[int] = 2
    seq: int = Field(ge=0)
    stamp: FiniteFloat
    landmarks: Array(None, 2)
    full: bool = True
    tile_size: float = Field(0.0, ge=0.0, allow_inf_nan=False, description="tile side (m); 0: untiled")
    tiles: Array(None, 2, kind="int") = Field(default_factory=lambda: np.zeros((0, 2), np.int64))
    tile_counts: Array(None, kind="int", nonnegative=True) = Field(default_factory=lambda: np.zeros(0, np.int64))

    @model_validator(mode="after")
    def _tiles_agree(self) -> "TiledMapMessage":
        if self.tiles.shape[0] != self.tile_counts.shape[0]:
            raise ValueError("tiles and tile_counts differ in length")
        untiled = self.full and self.tiles.shape[0] == 0
        if not untiled and int(self.tile_counts.sum()) != self.landmarks.shape[0]:
            raise ValueError("tile_counts do not add up to the landmarks")
        if not self.full and not self.tile_size > 0:
            raise ValueError("a delta (full = false) needs tile_size > 0")
        if np.unique(self.tiles, axis=0).shape[0] != self.tiles.shape[0]:
            raise ValueError("a tile is listed twice")
        return self


class Estimate(TiledMapMessage):
    """The central FastSLAM estimate: every robot's pose and the shared landmark map (by tiles)."""

    robots: list[RobotEstimate]
    landmark_covs: Array(None, 2, 2)
    landmark_ids: Array(None, kind="int") | None = None
    particles: int = Field(ge=0)
    effective_particles: float = Field(ge=0.0)
    method: str = ""

    @model_validator(mode="after")
    def _lengths_agree(self) -> "Estimate":
        if self.landmark_covs.shape[0] != self.landmarks.shape[0]:
            raise ValueError("landmarks and landmark_covs differ in length")
        if self.landmark_ids is not None and self.landmark_ids.shape[0] != self.landmarks.shape[0]:
            raise ValueError("landmarks and landmark_ids differ in length")
        return self


class MapEstimate(TiledMapMessage):
    """The D-SLAM map (by tiles): landmark means and ids, marginal covariances of a requested set (the landmarks near
    the robots, sent whole in every message), sparsity figures."""

    landmark_ids: Array(None, kind="int")
    covariance_ids: Array(None, kind="int") = Field(default_factory=lambda: np.zeros(0, np.int64))
    covariances: Array(None, 2, 2) = Field(default_factory=lambda: np.zeros((0, 2, 2)))
    info_nnz: int = Field(0, ge=0)
    recovery_iterations: int = Field(0, ge=0)

    @model_validator(mode="after")
    def _lengths_agree(self) -> "MapEstimate":
        if self.landmark_ids.shape[0] != self.landmarks.shape[0]:
            raise ValueError("landmarks and landmark_ids differ in length")
        if self.covariance_ids.shape[0] != self.covariances.shape[0]:
            raise ValueError("covariance_ids and covariances differ in length")
        return self

    def landmark_covariances(self) -> np.ndarray:
        """One covariance per landmark, in ``landmarks``' order: the marginal sent, zero where none was sent."""
        covs = np.zeros((self.landmarks.shape[0], 2, 2))
        row = {int(i): k for k, i in enumerate(self.landmark_ids.tolist())}
        for landmark_id, cov in zip(self.covariance_ids.tolist(), self.covariances):
            if int(landmark_id) in row:
                covs[row[int(landmark_id)]] = cov
        return covs


class PoseEstimate(StreamMessage):
    """One robot's pose estimate from a localization service."""

    pose: Pose
    cov: Covariance3
    source: str = ""


class ServiceStats(Message):
    """Health of a service: messages in, rejections by reason, latency, queue depth."""

    service: str
    instance: str
    stamp: FiniteFloat
    uptime_s: float = Field(ge=0.0)
    messages_in: dict[str, int] = Field(default_factory=dict)
    rejected: dict[str, int] = Field(default_factory=dict)
    published: int = Field(0, ge=0)
    latency_ms_median: float = 0.0
    latency_ms_p99: float = 0.0
    queue_depth: int = Field(0, ge=0)
    extra: dict[str, float] = Field(default_factory=dict)


class PoseHypothesis(BaseModel):
    """One cluster of an MCL particle set: its mean, covariance, weight and size."""

    model_config = ConfigDict(arbitrary_types_allowed=True, extra="forbid")
    mean: Pose
    cov: Covariance3
    weight: float = Field(ge=0.0, le=1.0 + 1e-9)
    particles: int = Field(ge=0)


class MclPose(StreamMessage):
    """MCL's belief about one robot: every significant hypothesis and the best pose.

    ``localized`` is true once one hypothesis dominates (the central service
    takes a robot with an unknown start pose in on the first such message, and
    places it again when later ones stay far from its own pose: ``replace_after``).
    """

    best_pose: Pose
    best_cov: Covariance3
    localized: bool = False
    hypotheses: list[PoseHypothesis] = Field(default_factory=list)
    particles: int = Field(0, ge=0)
    variant: str = ""
