"""Robot-to-robot detections (``robot_detections``, on by default): they weight the particles by how well the two
robots' poses in each particle explain the detection; they never update the map.

In one filter over the whole fleet (the centralised multi-robot FastSLAM of Nieto, Guivant, Nebot and Thrun,
"Real time data association for FastSLAM") each particle holds every robot's pose, so a detection of one robot
by another is one more likelihood of the particle. Their noise is the scan's covariance times
``robot_detection_noise_scale``: a robot is a wide target whose marker is not at its reference point, and on
MR.CLAM these detections are heavy-tailed. Without landmark ids the likelihood also allows
``robot_detection_position_sd`` of relative position between the two robots: the other robots' scans resample
the shared particles until a robot's position spread is a centimetre, re-acquisition puts robots back a few
decimetres off, and such a position error seen from nearby is then explained by turning the robot (a 0.5 m
error seen at 1.7 m is 17° of bearing). With ids it made MR.CLAM worse. With the shared association they also
tell re-acquisition when a robot is sure of a wrong pose, and vote in its search (``reacquire_by_robots``,
:mod:`central.fastslam.reacquire`)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from central.fastslam import motion, reacquire, resampling
from central.fastslam.lifecycle import RobotState
from robots.gaussian import LOG_2PI, inv2, quad2, sandwich, sandwich2
from robots.models import compose_jacobian, se2_compose
from schemas.contract import ScanEvent

if TYPE_CHECKING:
    from central.fastslam.core import FastSlam


def window_point(sensor, pose: np.ndarray, target: np.ndarray, w: np.ndarray, z: np.ndarray) -> np.ndarray:
    """A held robot's detection ``z`` (range, bearing) of another robot as a point of its re-acquisition window:
    ``[seen x, seen y, robot x, robot y]``, the detection placed from the observer's weighted mean pose (circular
    mean heading) beside the detected robot's weighted mean position. ``pose`` ``(P, 3)``, ``target`` ``(P, 2)``."""
    seen = sensor.inverse(resampling.weighted_pose(pose, w)[0], z[None, :])[0]
    return np.r_[seen, w @ target]


def weigh(slam: FastSlam, robot: RobotState, event: ScanEvent, r: np.ndarray) -> None:
    """Weight particles by each detected robot: N(z; h(x_i, x_j), kR + H_j (Σ_j + σ²I) H_jᵀ), Σ_j the spread of
    the other robot's buffered motion, k ``robot_detection_noise_scale``, σ ``robot_detection_position_sd``. A
    robot not placed, or whose pose is more than ``robot_detection_max_dt`` away from the scan's stamp, is skipped
    (counted)."""
    pose = slam.pose[:, robot.index]
    for other_id, rng_, brg in zip(event.robot_ids, np.asarray(event.robot_ranges, float),
                                   np.asarray(event.robot_bearings, float)):
        other = slam.robots.get(other_id)
        if other is None or other is robot or other.pose_time is None:
            slam.counts["robot_detections_unused"] += 1
            continue
        if abs(other.pose_time - float(event.stamp)) > slam.config.robot_detection_max_dt:
            slam.counts["robot_detections_unused"] += 1
            continue
        target = slam.pose[:, other.index]
        spread = np.zeros((slam.pose.shape[0], 3, 3))
        pending = motion.pending_motion(other, slam.config)
        if pending is not None:
            spread = sandwich(compose_jacobian(target[:, 2]), pending[1])
            target = se2_compose(target, pending[0])
        zhat = robot.sensor.observe(pose, target[:, :2])
        _, h_lm = robot.sensor.jacobians(pose, target[:, :2])
        relative = spread[:, :2, :2] + slam.config.robot_detection_relative_sd ** 2 * np.eye(2)
        s = sandwich2(h_lm, relative) + r * slam.config.robot_detection_noise_scale
        s_inv, det = inv2(s)
        nu = robot.sensor.innovation(np.array([rng_, brg]), zhat)
        d2 = quad2(nu, s_inv)
        slam.logw += -0.5 * d2 - 0.5 * np.log(np.maximum(det, 1e-300)) - LOG_2PI
        if slam.config.reacquires_by_robots:
            reacquire.note_robot_detection(robot, float(event.stamp), other_id, bool(d2.min() <= reacquire.ROBOT_GATE),
                                           slam.config.reacquire_robots_window_s)
            if robot.blind is not None:  # held: the detection is a point of its window, with its own robot
                point = window_point(robot.sensor, pose, target[:, :2], slam.weights(), np.array([rng_, brg]))
                robot.blind.robots.append((float(event.stamp), point))
        slam.counts["robot_detections_used"] += 1
