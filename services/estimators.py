"""The estimators ``fleetslam run`` and the benchmarks can drive, by name.

Each entry is a plain import of the estimator's ``make_estimator(options, infos)``
(:class:`schemas.contract.RunOptions` in, an :class:`schemas.contract.Estimator`
out), so a reader and a tool can follow it to the code.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Callable

from central.fastslam.core import make_estimator as make_fastslam
from schemas.contract import UNKNOWN_ASSOCIATION, Estimator, RunOptions, resolve_association
from schemas.messages import RobotInfo
from services.baselines.dead_reckoning import make_estimator as make_dead_reckoning
from services.baselines.ekf_slam import make_estimator as make_ekf_slam
from services.dslam.core import make_estimator as make_dslam
from services.maps import seed_from_options
from services.mcl.fleet import make_estimator as make_mcl

Factory = Callable[[RunOptions, list[RobotInfo]], Estimator]

ESTIMATORS: dict[str, Factory] = {
    "odometry": make_dead_reckoning,
    "ekf": make_ekf_slam,
    "fastslam": make_fastslam,
    "dslam": make_dslam,
    "mcl": make_mcl,
}


def make_estimator(options: RunOptions, infos: list[RobotInfo]) -> Estimator:
    """Build the estimator ``options.estimator`` for the robots ``infos`` (ValueError naming the choices), started
    from the saved map in ``options`` if it carries one (:func:`services.maps.seed_from_options`)."""
    try:
        factory = ESTIMATORS[options.estimator]
    except KeyError:
        raise ValueError(f"unknown estimator {options.estimator!r}; choose from {', '.join(ESTIMATORS)}") from None
    options = replace(options, association=resolve_association(options.estimator, options.association))
    estimator = factory(options, infos)
    seed_from_options(estimator, options)
    return estimator


__all__ = ["ESTIMATORS", "UNKNOWN_ASSOCIATION", "make_estimator", "resolve_association"]
