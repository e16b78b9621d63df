"""Motion: a robot's controls are buffered and applied in one draw per particle.

The filter only looks at a robot's pose when one of its scans arrives, so it needs p(x_end | x_start,
u_1..u_K), not every pose in between: the buffered controls are integrated into one Gaussian relative
motion (:func:`robots.models.integrate_controls`) and each particle draws from it once, at the robot's
next scan or every ``max_batch_s``. A control covers the time since the previous one; a scan later than
the last control extends that control to its stamp (by at most ``max_extrapolation_s``).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from central.fastslam import kernels, noise_gain, reacquire, resampling
from central.fastslam.config import FastSlamConfig
from central.fastslam.lifecycle import RobotState
from robots.gaussian import diagonal_variances, sqrt_psd, turn_slip, valid_cov2
from robots.models import integrate_controls, se2_compose, wrap_angle
from schemas.contract import OdomEvent

if TYPE_CHECKING:
    from central.fastslam.core import FastSlam


def take_control(slam: FastSlam, robot: RobotState, event: OdomEvent) -> bool:
    """Check and buffer one control of a placed robot; False (counted) if it is refused."""
    control = np.asarray(event.control, float)
    stamp, dt = float(event.stamp), float(event.dt)
    if (control.shape != (2,) or not (math.isfinite(control[0]) and math.isfinite(control[1]))
            or not (math.isfinite(dt) and 0.0 < dt <= 10.0) or not math.isfinite(stamp)):
        slam.rejected["bad_odometry"] += 1
        return False
    if event.control_cov is not robot.checked_cov:  # a log passes one covariance object for all its controls
        cov = np.asarray(event.control_cov, float)
        if not valid_cov2(cov):
            slam.rejected["bad_odometry"] += 1
            return False
        robot.checked_cov, robot.scaled_cov, robot.scaled_gain = event.control_cov, None, None
    if robot.scaled_gain != noise_gain.gain(robot):
        robot.scaled_gain = noise_gain.gain(robot)
        robot.scaled_cov = np.asarray(robot.checked_cov, float) * (slam.config.motion_scale * robot.scaled_gain)
    if stamp < robot.last_odom_stamp:
        slam.rejected["time_backwards"] += 1
        return False
    robot.last_odom_stamp = stamp
    scale = noise_gain.turn_scale(robot)
    if scale != 1.0:
        control = control * (1.0, scale)
    start = stamp - dt
    if robot.pose_time is None:
        robot.pose_time = start
    if start - robot.pose_time > slam.config.max_extrapolation_s:
        slam.counts["odometry_gaps"] += 1
    span = min(stamp - robot.pose_time, dt + slam.config.max_extrapolation_s)
    cov = robot.scaled_cov
    if span > 0.0:
        buffer(robot, control, span, cov)
    elif stamp < robot.pose_time:  # a scan after it was handled first: its motion was extrapolated instead
        slam.counts["controls_late"] += 1
    robot.pose_time = max(robot.pose_time, stamp)
    robot.last_control, robot.last_cov = control, cov
    if robot.pending_s >= slam.config.max_batch_s:
        flush(slam, robot)
    return True


def buffer(robot: RobotState, control: np.ndarray, span: float, cov: np.ndarray) -> None:
    """Append one control applied over ``span`` seconds."""
    robot.controls.append(control)
    robot.dts.append(span)
    robot.covs.append(cov)
    robot.pending_s += span


def pending_motion(robot: RobotState, config: FastSlamConfig) -> tuple[np.ndarray, np.ndarray] | None:
    """(Δ̄, Σ_Δ) of the buffered controls in the robot's frame at their start, or None if nothing is buffered.

    Controls are only ever appended between two :func:`clear`, so the count and the buffered time name the
    buffer: the association, the prediction and the pose report of one scan share one integration. The
    arrays returned are shared: callers must not change them in place."""
    if not robot.controls:
        return None
    key = (len(robot.controls), robot.pending_s)
    if robot.pending_memo is not None and robot.pending_memo[0] == key:
        return robot.pending_memo[1]
    integrate = kernels.integrate_controls if config.compiled else integrate_controls
    delta, cov = integrate(robot.model, np.array(robot.controls), np.array(robot.dts), np.array(robot.covs))
    cov = cov + diagonal_variances(config.pose_noise_per_s) * robot.pending_s
    if config.turn_slip and robot.info.turn_slip_var > 0.0:
        cov[2, 2] += turn_slip(robot.info.turn_slip_var, delta[2])
    robot.pending_memo = (key, (delta, cov))
    return delta, cov


def clear(robot: RobotState) -> None:
    """Forget the buffered controls (they have been applied)."""
    robot.controls, robot.dts, robot.covs, robot.pending_s, robot.pending_memo = [], [], [], 0.0, None


def take_pending(slam: FastSlam, robot: RobotState) -> tuple[np.ndarray, np.ndarray] | None:
    """The buffered motion (:func:`pending_motion`), cleared from the buffer for the caller to apply; with shared
    association it is also added to the robot's drift (:mod:`central.fastslam.reacquire`).

    With turn gains on, each particle first turns by (gain − 1)·Δθ̄ (its own hypothesis of the robot's turn gain;
    composing Δ̄ after that turn rotates Δ̄'s few centimetres with it, well inside its noise), and the gains walk
    by ``turn_gain_walk``·√(time buffered)."""
    motion = pending_motion(robot, slam.config)
    span = robot.pending_s
    clear(robot)
    config = slam.config
    if motion is not None:
        noise_gain.moved(slam, robot, motion[0], motion[1])
    if motion is not None and config.reacquire and config.association == "shared":
        heading = resampling.weighted_heading(slam.pose[:, robot.index, 2], slam.weights())
        slip = 0.0 if config.turn_slip else robot.info.turn_slip_var  # turn_slip: already in the motion's covariance
        accumulate = kernels.drift_accumulate if config.compiled else reacquire.accumulate
        robot.drift = accumulate(robot.drift, heading, motion[0], motion[1], slip)
        if robot.blind is not None:
            robot.blind.moved(motion[0])
    if motion is not None and (config.turn_gain_std > 0.0 or config.turn_gain_walk > 0.0):
        col = robot.index
        slam.pose[:, col, 2] = wrap_angle(slam.pose[:, col, 2] + (slam.turn_gain[:, col] - 1.0) * motion[0][2])
        if config.turn_gain_walk > 0.0:
            step = config.turn_gain_walk * math.sqrt(span) * slam.rng.standard_normal(slam.pose.shape[0])
            slam.turn_gain[:, col] = np.clip(slam.turn_gain[:, col] + step, 0.5, 1.5)
    return motion


def flush(slam: FastSlam, robot: RobotState) -> None:
    """Apply the buffered controls: one draw per particle from N(Δ̄, Σ_Δ), composed onto its pose."""
    motion = take_pending(slam, robot)
    if motion is None:
        return
    delta, cov = motion
    noise = slam.rng.standard_normal((slam.pose.shape[0], 3)) @ sqrt_psd(cov).T
    slam.pose[:, robot.index] = se2_compose(slam.pose[:, robot.index], delta + noise)


def advance_to(robot: RobotState, stamp: float, config: FastSlamConfig) -> None:
    """Extend the last control up to a scan's ``stamp`` (by at most ``max_extrapolation_s``)."""
    if robot.pose_time is None:
        robot.pose_time = stamp
        return
    if stamp > robot.pose_time and robot.last_control is not None:
        span = min(stamp - robot.pose_time, config.max_extrapolation_s)
        buffer(robot, robot.last_control, span, robot.last_cov)
    robot.pose_time = max(robot.pose_time, stamp)
