"""The contract between the numeric cores and whatever drives them (DESIGN §1).

One neutral module that every core, runner and shell imports:

- the input events a core eats (:class:`OdomEvent`, :class:`ScanEvent`, and
  :class:`TruthEvent` for evaluators), built from messages or from a log;
- what a core returns: :class:`MapView` (landmark means, covariances, ids) and
  every robot's ``(pose, covariance)``;
- :class:`Estimator`, the protocol every estimator offers (``fleetslam run``,
  benchmarks and service shells drive them the same way), and
  :class:`RunOptions`, how one is asked for;
- :class:`CoreConfig`, the base of every core configuration: a plain frozen
  pydantic model that never reads the environment, and :func:`build_config`,
  which turns ``--set NAME=VALUE`` pairs into one with a one-line error.

It imports numpy, pydantic and :mod:`schemas.messages` only: no Zenoh, no
pydantic-settings, no service.
"""

from __future__ import annotations

import dataclasses

from dataclasses import dataclass, field
from typing import Any, Protocol, TypeVar

import numpy as np
from pydantic import BaseModel, ConfigDict, ValidationError

from schemas.messages import GroundTruth, Odometry, RobotInfo, Scan

C = TypeVar("C", bound="CoreConfig")


# ---------------------------------------------------------------- input events
@dataclass(slots=True)
class OdomEvent:
    """One control ``(2,)`` applied over ``dt`` seconds, ending at ``stamp``."""

    robot_id: str
    seq: int
    stamp: float
    dt: float
    control: np.ndarray
    control_cov: np.ndarray

    def to_message(self) -> Odometry:
        return Odometry(robot_id=self.robot_id, seq=self.seq, stamp=self.stamp, dt=self.dt,
                        control=self.control, control_cov=self.control_cov)

    @classmethod
    def from_message(cls, message: Odometry) -> "OdomEvent":
        return cls(message.robot_id, message.seq, message.stamp, message.dt, message.control, message.control_cov)


@dataclass(slots=True)
class ScanEvent:
    """Range-bearing detections at one instant (sensor frame), optional true ids, other robots detected."""

    robot_id: str
    seq: int
    stamp: float
    ranges: np.ndarray
    bearings: np.ndarray
    landmark_ids: np.ndarray | None
    noise_cov: np.ndarray
    robot_ids: list[str] = field(default_factory=list)
    robot_ranges: np.ndarray = field(default_factory=lambda: np.zeros(0))
    robot_bearings: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def observations(self) -> np.ndarray:
        """(n, 2) array of (range, bearing)."""
        return np.stack([self.ranges, self.bearings], -1)

    def to_message(self, with_ids: bool = True) -> Scan:
        return Scan(robot_id=self.robot_id, seq=self.seq, stamp=self.stamp, ranges=self.ranges, bearings=self.bearings,
                    landmark_ids=self.landmark_ids if with_ids else None, noise_cov=self.noise_cov,
                    robot_ids=self.robot_ids, robot_ranges=self.robot_ranges, robot_bearings=self.robot_bearings)

    @classmethod
    def from_message(cls, scan: Scan) -> "ScanEvent":
        return cls(scan.robot_id, scan.seq, scan.stamp, scan.ranges, scan.bearings, scan.landmark_ids, scan.noise_cov,
                   list(scan.robot_ids), scan.robot_ranges, scan.robot_bearings)


@dataclass(slots=True)
class TruthEvent:
    """A true pose (θ NaN when only the position is known, as with GPS)."""

    robot_id: str
    seq: int
    stamp: float
    pose: np.ndarray

    def to_message(self) -> GroundTruth:
        known = bool(np.isfinite(self.pose[2]))
        pose = self.pose if known else np.array([self.pose[0], self.pose[1], 0.0])
        return GroundTruth(robot_id=self.robot_id, seq=self.seq, stamp=self.stamp, pose=pose, heading_known=known)


Event = OdomEvent | ScanEvent | TruthEvent


def stream_event(message: Odometry | Scan) -> OdomEvent | ScanEvent:
    """The core's event for a decoded stream message."""
    return OdomEvent.from_message(message) if isinstance(message, Odometry) else ScanEvent.from_message(message)


def event_nbytes(event: OdomEvent | ScanEvent) -> int:
    """Roughly the memory an event holds: its arrays plus a fixed overhead (what waiting buffers are sized by)."""
    values = (getattr(event, f.name) for f in dataclasses.fields(event))
    return 256 + sum(value.nbytes for value in values if isinstance(value, np.ndarray))


# ---------------------------------------------------------------- what cores return
@dataclass
class MapView:
    """An estimator's landmark map: means ``(n,2)``, covariances ``(n,2,2)``, true ids if known."""

    means: np.ndarray
    covs: np.ndarray
    ids: np.ndarray | None = None

    @classmethod
    def empty(cls, with_ids: bool = False) -> "MapView":
        return cls(np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros(0, np.int64) if with_ids else None)


class Estimator(Protocol):
    """What every estimator offers: told about robots, fed events in time order, asked for poses and a map."""

    def add_robot(self, info: RobotInfo) -> None:
        """Take a robot in (its start pose, if known, is in ``info``)."""

    def on_odometry(self, event: OdomEvent) -> None:
        """Predict with one control."""

    def on_scan(self, event: ScanEvent) -> None:
        """Update with one scan."""

    def poses(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Every robot's current (pose ``(3,)``, covariance ``(3,3)``)."""

    def landmark_map(self) -> MapView:
        """The current map (empty arrays for a localization-only estimator)."""

    def extra_metrics(self) -> dict:
        """The estimator's own figures for the run's JSON (counters, timings)."""


@dataclass
class RunOptions:
    """How one estimator is asked for: by name, with the settings every estimator shares, its own settings
    (``settings``, validated by the estimator's core configuration), and what it may be given beyond the
    events: a prior landmark map ``(L, 2)`` (a localizer's map; with covariances, the saved map a mapping estimator
    starts from: :mod:`services.maps`) and the true trajectories ``{rid: (stamps, poses)}``."""

    estimator: str = "odometry"
    association: str = "known"
    particles: int | None = None  # None: the estimator's own default
    seed: int = 0
    settings: dict[str, Any] = field(default_factory=dict)
    landmarks: np.ndarray | None = None
    landmark_ids: np.ndarray | None = None  # ids of ``landmarks`` (L,), when the map has them
    landmark_covs: np.ndarray | None = None  # covariances (L, 2, 2): a saved map a mapping estimator starts from
    landmark_hits: np.ndarray | None = None  # times each landmark was associated (L,), when known
    truth: dict[str, tuple[np.ndarray, np.ndarray]] | None = None


# ---------------------------------------------------------------- configuration
UNKNOWN_ASSOCIATION: dict[str, str] = {
    "odometry": "unknown",
    "ekf": "jcbb",
    "fastslam": "shared",
    "dslam": "auto",
    "mcl": "unknown",
}
"""What ``--association unknown`` means for each estimator: its recommended method when scans carry no ids."""


def resolve_association(estimator: str, association: str) -> str:
    """The association an estimator runs: ``unknown`` becomes the estimator's recommended method without ids."""
    return UNKNOWN_ASSOCIATION.get(estimator, association) if association == "unknown" else association


class SettingsError(ValueError):
    """A setting that does not exist or has a bad value; the message is one line naming it."""


class CoreConfig(BaseModel):
    """Base of every core configuration: frozen, unknown names refused, never read from the environment."""

    model_config = ConfigDict(frozen=True, extra="forbid", validate_default=True)

    def with_overrides(self: C, overrides: dict[str, Any], owner: str | None = None) -> C:
        """A validated copy with ``overrides`` (:class:`SettingsError` on an unknown name or a bad value)."""
        return build_config(type(self), {**self.model_dump(), **overrides}, owner, given=set(overrides))


def describe_validation_error(error: ValidationError) -> tuple[str, str]:
    """(setting name, one line) for the first problem of a pydantic validation error: ``NAME=VALUE: what was
    expected``; the name is empty for a check across several settings (the line is then its message)."""
    first = error.errors()[0]
    name = ".".join(str(part) for part in first["loc"])
    return name, f"{name}={first.get('input')!r}: {first['msg']}" if name else first["msg"]


def build_config(cls: type[C], values: dict[str, Any], owner: str | None = None, given: set[str] | None = None) -> C:
    """``cls(**values)`` with a one-line :class:`SettingsError` naming the setting, the value and what is allowed.

    ``given`` names the values the user chose (the others are defaults): an unknown one is reported first.
    """
    owner = owner or cls.__name__
    known = sorted(cls.model_fields)
    unknown = sorted(set(given if given is not None else values) - set(known))
    if unknown:
        raise SettingsError(f"unknown {owner} setting{'s' if len(unknown) > 1 else ''} {', '.join(unknown)} "
                            f"(known: {', '.join(known)})")
    try:
        return cls(**values)
    except ValidationError as error:
        name, problem = describe_validation_error(error)
        raise SettingsError(f"{owner} setting {problem}" if name else f"{owner} settings: {problem}") from None
