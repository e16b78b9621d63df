"""Centralised multi-robot FastSLAM (paper 001): the numeric core, vectorised over particles.

``make_estimator(options, infos)`` builds it for ``fleetslam run --estimator fastslam``
and the benchmarks; the ``fleetslam central`` service (:mod:`central.service`) wraps it.
"""

from __future__ import annotations

from central.fastslam.config import FastSlamConfig
from central.fastslam.filter import FastSlam
from schemas.messages import RobotInfo
from services.estimator import RunOptions

__all__ = ["FastSlam", "FastSlamConfig", "make_estimator"]


def make_estimator(options: RunOptions, infos: list[RobotInfo]) -> FastSlam:
    """FastSLAM with ``options.association`` (known | nn | mht), ``options.particles``, ``options.seed``;
    ``options.variant`` picks the proposal (fastslam1 | fastslam2); ``options.extra`` overrides any
    :class:`FastSlamConfig` field."""
    config = FastSlamConfig(particles=options.particles, association=options.association, seed=options.seed)
    overrides = dict(options.extra)
    if options.variant:
        overrides["proposal"] = options.variant
    return FastSlam(config.with_overrides(overrides), infos)
