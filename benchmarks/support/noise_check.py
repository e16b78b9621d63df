"""Whether a robot's noise model fits its own data, without truth (the numeric part of
``benchmarks/odometry_noise.py``; see there for the method)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from benchmarks.support.timing import dead_reckoning, detections_at, scan_of_detection
from robots.dataset import RobotLog
from robots.models import dead_reckon, robot_models


def pair_scatter(log: RobotLog, bins: np.ndarray, gate: float = 1.0, draws: int = 30, seed: int = 0,
                 odom_scale: float = 1.0) -> list[dict]:
    """Per interval ``(bins[i], bins[i + 1]]`` of time between two scans: the detection pairs (from different scans,
    placed from dead reckoning, closer than ``gate`` m: the same landmark), the RMS of their distance, and what the
    log's noise model predicts for it: the odometry's part (``draws`` dead reckonings with controls drawn from
    ``odom_scale`` × the odometry covariance, the same pairs) and the sensor's (each detection's range and bearing
    variances), both RMS. A model that fits predicts the measured RMS; one too loose predicts more.
    """
    stamps, poses = dead_reckoning(log)
    scan_of = scan_of_detection(log)
    t = log.scan_stamp[scan_of]
    placed = detections_at(log, stamps, poses, t)
    pairs = cKDTree(placed).query_pairs(gate, output_type="ndarray")
    pairs = pairs[scan_of[pairs[:, 0]] != scan_of[pairs[:, 1]]]
    a, b = pairs[:, 0], pairs[:, 1]
    apart = np.abs(t[a] - t[b])
    measured = np.sum((placed[a] - placed[b]) ** 2, axis=1)
    model, _ = robot_models(log.info)
    cov = np.broadcast_to(log.odom_cov, (log.odom_control.shape[0], 2, 2)) * odom_scale
    chol = np.linalg.cholesky(cov)
    rng = np.random.default_rng(seed)
    odometry = np.zeros(pairs.shape[0])
    for _ in range(draws):
        controls = log.odom_control + np.einsum("kij,kj->ki", chol, rng.standard_normal(log.odom_control.shape))
        drawn = dead_reckon(model, controls, log.odom_dt)
        drawn[:, 2] = np.unwrap(drawn[:, 2])
        moved = detections_at(log, stamps, drawn, t) - placed
        odometry += np.sum((moved[a] - moved[b]) ** 2, axis=1) / draws
    ranges = log.det_range
    point = log.scan_cov[0, 0] + ranges**2 * log.scan_cov[1, 1]  # a detection's variance in the plane (trace)
    sensor = point[a] + point[b]
    out = []
    for low, high in zip(bins[:-1], bins[1:]):
        inside = (apart > low) & (apart <= high)
        count = int(inside.sum())
        rms = (lambda v: float(np.sqrt(v[inside].mean())) if count else float("nan"))
        out.append({"from_s": float(low), "to_s": float(high), "pairs": count, "measured_m": rms(measured),
                    "odometry_m": rms(odometry), "sensor_m": rms(sensor), "predicted_m": rms(odometry + sensor)})
    return out
