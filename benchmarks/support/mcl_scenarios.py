"""Localization scenarios shared by the MCL tests and benchmarks: runs with a per-scan trace, kidnapping.

:func:`trace_run` drives one :class:`~services.mcl.core.MonteCarloLocalizer`
over a robot's events and records, per scan, the particle count, the
significant hypotheses, whether it is localized and the error of its best
pose against the truth. :func:`kidnapped` splices two robots of one
simulation: the events of the first until ``at``, then those of the second,
as if the robot had been carried to where the second one is.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Iterable, Iterator

import numpy as np

from robots.dataset import Dataset
from robots.models import wrap_angle
from robots.worlds import World, make_world
from schemas.contract import OdomEvent, ScanEvent
from services.mcl.core import MonteCarloLocalizer


@dataclass
class Trace:
    """Per scan: stamp, particles, significant hypotheses (means and weights), localized, error of the best pose."""

    stamp: list[float] = field(default_factory=list)
    particles: list[int] = field(default_factory=list)
    hypotheses: list[int] = field(default_factory=list)
    means: list[np.ndarray] = field(default_factory=list)
    weights: list[np.ndarray] = field(default_factory=list)
    localized: list[bool] = field(default_factory=list)
    error_m: list[float] = field(default_factory=list)
    error_rad: list[float] = field(default_factory=list)
    kidnapped: list[bool] = field(default_factory=list)

    def converged(self, xy: float, theta: float) -> np.ndarray:
        """Mask of scans where the filter is localized on the truth."""
        return (np.asarray(self.localized) & (np.asarray(self.error_m) <= xy)
                & (np.asarray(self.error_rad) <= theta))

    def first_converged(self, xy: float, theta: float, after: float = -np.inf) -> float | None:
        """Stamp of the first scan at or after ``after`` where the filter is localized on the truth."""
        stamps = np.asarray(self.stamp)
        hits = np.flatnonzero(self.converged(xy, theta) & (stamps >= after))
        return float(stamps[hits[0]]) if hits.size else None


def symmetric_cross(seed: int = 0) -> World:
    """The ``cross`` world without the room that breaks its symmetry: every position has four twins."""
    world = make_world("cross", seed)
    symmetric = world.landmarks[: world.extra["symmetric_landmarks"]]
    return dataclasses.replace(world, name="cross_symmetric", landmarks=symmetric)


def random_starts(world: World, count: int, seed: int) -> World:
    """``world`` with robot i starting at a random pose (uniform over the bounds, any heading) drawn from ``seed``."""
    rng = np.random.default_rng([seed, 99])
    xmin, xmax, ymin, ymax = world.bounds
    starts = np.column_stack([rng.uniform(xmin, xmax, count), rng.uniform(ymin, ymax, count),
                              rng.uniform(-np.pi, np.pi, count)])
    return dataclasses.replace(world, start_poses=lambda i: starts[i % count])


def kidnapped(dataset: Dataset, first: str, second: str, at: float) -> tuple[Iterator, callable]:
    """(events, truth) of a robot that runs as ``first`` until ``at`` and then as ``second``.

    ``truth(stamp)`` gives the true pose of whichever robot the events come from at that stamp.
    """
    one, two = dataset.robots[first], dataset.robots[second]

    def events():
        for event in dataset.events(robots=[first, second]):
            if (event.robot_id == first) == (event.stamp < at):
                yield event

    def truth(stamp: float) -> np.ndarray:
        return (one if stamp < at else two).truth_at(np.array([stamp]))[0]

    return events(), truth


def trace_run(mcl: MonteCarloLocalizer, events: Iterable, truth) -> Trace:
    """Drive ``mcl`` over ``events``; ``truth(stamp)`` gives the true pose for the error."""
    trace = Trace()
    for event in events:
        if isinstance(event, OdomEvent):
            mcl.predict(event.control, event.dt, event.control_cov)
        elif isinstance(event, ScanEvent):
            report = mcl.update(event.observations)
            found = mcl.hypotheses()
            actual = truth(event.stamp)
            best = found[0].mean
            trace.stamp.append(event.stamp)
            trace.particles.append(report.particles_after)
            trace.hypotheses.append(report.hypotheses)
            trace.means.append(np.array([h.mean for h in found]))
            trace.weights.append(np.array([h.weight for h in found]))
            trace.localized.append(report.localized)
            trace.error_m.append(float(np.hypot(*(best[:2] - actual[:2]))))
            trace.error_rad.append(float(abs(wrap_angle(best[2] - actual[2]))))
            trace.kidnapped.append(report.kidnapped)
    return trace
