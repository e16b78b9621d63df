"""Timing offsets between a robot's detections, its odometry and its truth, measured without any filter (the
numeric part of ``benchmarks/sensor_timing.py``; see there for the method)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from robots.dataset import RobotLog
from robots.models import dead_reckon, robot_models


def best_shift(shifts: np.ndarray, scores: np.ndarray) -> float:
    """The δ of the smallest score, refined by a parabola through it and its two neighbours."""
    k = int(np.argmin(scores))
    if 0 < k < len(shifts) - 1:
        a, b, c = scores[k - 1: k + 2]
        curvature = a - 2 * b + c
        if curvature > 0:
            return float(shifts[k] + 0.5 * (a - c) / curvature * (shifts[1] - shifts[0]))
    return float(shifts[k])


def dead_reckoning(log: RobotLog) -> tuple[np.ndarray, np.ndarray]:
    """(stamps, poses with unwrapped heading) of the odometry integrated from the origin."""
    model, _ = robot_models(log.info)
    poses = dead_reckon(model, log.odom_control, log.odom_dt)
    poses[:, 2] = np.unwrap(poses[:, 2])  # interpolated: a wrap from π to −π would sweep through 0
    return np.append(log.odom_stamp[0] - log.odom_dt[0], log.odom_stamp), poses


def scan_of_detection(log: RobotLog) -> np.ndarray:
    """The scan index (D,) of every detection."""
    return np.repeat(np.arange(log.scan_stamp.size), np.diff(log.scan_offsets))


def detections_at(log: RobotLog, stamps: np.ndarray, poses: np.ndarray, t: np.ndarray) -> np.ndarray:
    """World positions (D, 2) of every detection from the poses (x, y, unwrapped θ) interpolated at its time ``t``
    (the robot's sensor model, mounting offset included)."""
    _, sensor = robot_models(log.info)
    at = np.column_stack([np.interp(t, stamps, poses[:, j]) for j in range(3)])
    return sensor.inverse(at, np.column_stack([log.det_range, log.det_bearing]))


def detection_scatter(log: RobotLog, shifts: np.ndarray, window: float, gate: float) -> np.ndarray:
    """Per δ, the mean distance of detection pairs from different scans within ``window`` s and ``gate`` m."""
    stamps, poses = dead_reckoning(log)
    scan_of = scan_of_detection(log)
    stamped = log.scan_stamp[scan_of]
    scores = []
    for shift in shifts:
        points = detections_at(log, stamps, poses, stamped + shift)
        pairs = cKDTree(points).query_pairs(gate, output_type="ndarray")
        a, b = scan_of[pairs[:, 0]], scan_of[pairs[:, 1]]
        keep = (a != b) & (np.abs(log.scan_stamp[a] - log.scan_stamp[b]) <= window)
        pairs = pairs[keep]
        scores.append(float(np.mean(np.linalg.norm(points[pairs[:, 0]] - points[pairs[:, 1]], axis=1))))
    return np.array(scores)


def detection_truth_error(log: RobotLog, landmarks: np.ndarray, ids: np.ndarray, shifts: np.ndarray) -> np.ndarray:
    """Per δ, the median distance of identified detections (placed from the truth at stamp + δ) to the survey."""
    slot = {int(i): k for k, i in enumerate(ids.tolist())}
    known = np.array([int(i) in slot for i in log.det_id.tolist()])
    where = landmarks[[slot.get(int(i), 0) for i in log.det_id.tolist()]]
    poses = log.truth_pose.copy()
    poses[:, 2] = np.unwrap(poses[:, 2])
    stamped = log.scan_stamp[scan_of_detection(log)]
    return np.array([float(np.median(np.linalg.norm(detections_at(log, log.truth_stamp, poses, stamped + s) - where,
                                                    axis=1)[known])) for s in shifts])


def odometry_truth_lag(log: RobotLog, shifts: np.ndarray) -> np.ndarray:
    """Per δ, the mean squared difference (rad²/s²) of the odometry's turn rate stamped t and the truth's at t + δ
    (both smoothed over 0.25 s): the motion an odometry reading stamped t describes happened at t + δ."""
    model, _ = robot_models(log.info)
    controls, _ = model.to_unicycle(log.odom_control)
    middle = log.odom_stamp - 0.5 * log.odom_dt
    grid = np.arange(max(middle[0], log.truth_stamp[0]) + 2.0, min(middle[-1], log.truth_stamp[-1]) - 2.0, 0.05)
    smooth = np.ones(5) / 5
    truth_rate = np.gradient(np.unwrap(log.truth_pose[:, 2]), log.truth_stamp)
    odometry = np.convolve(np.interp(grid, middle, controls[:, 1]), smooth, "same")
    return np.array([float(np.mean((np.convolve(np.interp(grid + s, log.truth_stamp, truth_rate), smooth, "same")
                                    - odometry) ** 2)) for s in shifts])
