"""Centralised multi-robot FastSLAM (Howard, "Multi-robot simultaneous localization and mapping using particle
filters"): the numeric core, vectorised over particles (:mod:`central.fastslam.core`).

``make_estimator(options, infos)`` builds it for ``fleetslam run --estimator fastslam`` and the benchmarks;
the ``fleetslam central`` service (:mod:`central.service`) wraps it.
"""

from __future__ import annotations

from central.fastslam.config import FastSlamConfig
from central.fastslam.core import FastSlam
from schemas.contract import RunOptions, build_config
from schemas.messages import RobotInfo

__all__ = ["FastSlam", "FastSlamConfig", "make_estimator"]


def make_estimator(options: RunOptions, infos: list[RobotInfo]) -> FastSlam:
    """FastSLAM with ``options.association`` (known | nn | mht), ``options.particles`` (None: the default) and
    ``options.seed``; ``options.settings`` (``--set``) overrides any :class:`FastSlamConfig` field, e.g.
    ``proposal=fastslam2``. A bad name or value raises :class:`schemas.contract.SettingsError` (one line)."""
    base = {"association": options.association, "seed": options.seed}
    if options.particles is not None:
        base["particles"] = options.particles
    config = build_config(FastSlamConfig, base, owner="fastslam")
    return FastSlam(config.with_overrides(options.settings, owner="fastslam"), infos)
