"""What every estimator offers, so that one offline runner (``fleetslam run``),
the benchmarks and the service shells can drive any of them the same way.

An estimator is a pure numeric object (no Zenoh, no I/O). It is told about a
robot once (:meth:`Estimator.add_robot`), then fed odometry and scans in time
order, and asked for its current poses and map. Estimators are built from
:class:`RunOptions` by name through :data:`ESTIMATORS`: each entry names a
``module:function`` with the signature ``make(options, infos) -> Estimator``.
"""

from __future__ import annotations

import importlib
import importlib.util
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from robots.dataset import OdomEvent, ScanEvent
from schemas.messages import RobotInfo

ESTIMATORS: dict[str, str] = {
    "odometry": "services.evaluation.odometry:make_estimator",
    "ekf": "services.association.ekf_slam:make_estimator",
    "fastslam": "central.fastslam:make_estimator",
    "dslam": "services.dslam.estimator:make_estimator",
    "mcl": "services.mcl.estimator:make_estimator",
}


@dataclass
class RunOptions:
    """Settings of one estimator run (offline or in a service)."""

    estimator: str = "odometry"
    association: str = "known"
    particles: int = 100
    seed: int = 0
    variant: str | None = None
    extra: dict = field(default_factory=dict)


@dataclass
class MapView:
    """An estimator's landmark map: means ``(n,2)``, covariances ``(n,2,2)``, true ids if known."""

    means: np.ndarray
    covs: np.ndarray
    ids: np.ndarray | None = None


class Estimator(Protocol):
    def add_robot(self, info: RobotInfo) -> None:
        """Take a robot in (its start pose, if known, is in ``info``)."""

    def on_odometry(self, event: OdomEvent) -> None:
        """Predict with one control."""

    def on_scan(self, event: ScanEvent) -> None:
        """Update with one scan."""

    def poses(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Every robot's current (pose ``(3,)``, covariance ``(3,3)``)."""

    def landmark_map(self) -> MapView:
        """The current map (empty arrays for a localisation-only estimator)."""


def refuse_unknown_settings(estimator: str, given: dict, known) -> None:
    """ValueError naming the settings in ``given`` that estimator ``estimator`` does not have."""
    unknown = sorted(set(given) - set(known))
    if unknown:
        choices = ", ".join(sorted(known)) or "none"
        raise ValueError(f"unknown {estimator} settings: {', '.join(unknown)} (it has: {choices})")


def make_estimator(options: RunOptions, infos: list[RobotInfo]) -> Estimator:
    """Build the estimator ``options.estimator`` for the robots ``infos``."""
    try:
        target = ESTIMATORS[options.estimator]
    except KeyError:
        raise ValueError(f"unknown estimator {options.estimator!r}; choose from {', '.join(ESTIMATORS)}") from None
    module_name, func_name = target.split(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        raise ValueError(f"estimator {options.estimator!r} is not available in this installation ({exc})") from None
    return getattr(module, func_name)(options, infos)


def available_estimators() -> list[str]:
    """Names of the estimators whose modules are installed."""
    found = []
    for name, target in ESTIMATORS.items():
        try:
            if importlib.util.find_spec(target.split(":")[0]) is not None:
                found.append(name)
        except ModuleNotFoundError:
            continue
    return found
