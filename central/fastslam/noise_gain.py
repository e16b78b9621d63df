"""Each robot's odometry noise, measured from its own detections (:mod:`robots.odometry_noise`): the gain on the
covariance its odometry announces that the particles draw from.

A robot announces the covariance of its odometry. How much of it the particles should draw was a constant fitted to
one data set (a quarter, chosen on Victoria Park, whose announced noise is the ACFR example's, several times its real
scatter); on data that announces its real noise (MR.CLAM, fitted against Vicon) a quarter left the particles too
narrow: a robot's heading error outgrew them, its scans paired with the wrong landmarks and it mapped a turned copy
of the world. Now each robot starts at the announced covariance and its gain follows pairs of its detections of one
landmark placed by its own dead reckoning, which no filter corrects (``motion_noise_adapt``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from robots.odometry_noise import OdometryNoiseGain

if TYPE_CHECKING:
    from central.fastslam.core import FastSlam
    from central.fastslam.lifecycle import RobotState


def start(slam: FastSlam, model_name: str) -> OdometryNoiseGain | None:
    """A placed robot's estimator (None when the gain does not adapt). Its turn scale adapts too (``turn_scale_adapt``)
    for a robot whose odometry is (v, ω): an Ackermann robot's turn comes from its steering through its wheelbase,
    which one scale on the turn does not stand for."""
    config = slam.config
    if not config.adapts_motion_noise:
        return None
    bounds = config.turn_scale_bounds if config.turn_scale_adapt and model_name == "unicycle" else None
    return OdometryNoiseGain(1.0, config.motion_noise_min_gain, config.motion_noise_max_gain, config.motion_noise_step,
                             turn_scale_bounds=bounds)


def turn_scale(robot: RobotState) -> float:
    """What the robot's odometry turn is multiplied by before the particles move (1 when it does not adapt)."""
    return 1.0 if robot.odometry_noise is None else robot.odometry_noise.turn_scale


def gain(robot: RobotState) -> float:
    """The robot's present gain on its announced odometry covariance (1 when it does not adapt)."""
    return 1.0 if robot.odometry_noise is None else robot.odometry_noise.gain


def moved(slam: FastSlam, robot: RobotState, delta: np.ndarray, cov: np.ndarray) -> None:
    """A motion was applied (its covariance as drawn: announced × scale × gain); the dead reckoning follows it."""
    if robot.odometry_noise is not None:
        scale = slam.config.motion_scale * (robot.scaled_gain or 1.0)
        robot.odometry_noise.move(delta, cov / scale)


def observe(slam: FastSlam, robot: RobotState, z: np.ndarray, r: np.ndarray, ids: np.ndarray | None) -> None:
    """The scan's detections of confirmed landmarks (their ids by the association) step the robot's gain."""
    from central.fastslam.shared import confirmed  # here: shared imports motion, which imports this module

    if robot.odometry_noise is None or ids is None or not len(ids):
        return
    keep = ids >= 0  # after the update every such id is in the map
    keep[keep] = confirmed(slam, ids[keep])
    if not keep.any():
        return
    before = robot.odometry_noise.pairs
    robot.odometry_noise.scan(robot.sensor.offset, ids[keep].tolist(), z[keep], r)
    slam.counts["noise_gain_pairs"] += robot.odometry_noise.pairs - before
