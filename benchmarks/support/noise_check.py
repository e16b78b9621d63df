"""Whether a robot's noise model fits its own data, without truth (the numeric part of
``benchmarks/odometry_noise.py``; see there for the method)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from benchmarks.support.timing import dead_reckoning, detections_at, scan_of_detection
from robots.dataset import RobotLog
from robots.models import dead_reckon, robot_models


def within_gate_second_moment(variance: np.ndarray, gate: float) -> np.ndarray:
    """E[|d|² | |d| < gate] for d ~ N(0, variance/2 · I₂) (``variance`` the trace): what a pair's squared distance
    averages to once the gate has kept the far pairs out. ``variance`` itself when the gate is far beyond it, gate²/2
    (a disc filled evenly) when it is far below.
    """
    half = np.asarray(variance, float) / 2.0
    x = gate * gate / (2.0 * np.maximum(half, 1e-300))
    kept = -np.expm1(-x)  # P(|d| < gate)
    return 2.0 * half * (kept - x * np.exp(-x)) / np.maximum(kept, 1e-300)


def pair_scatter(log: RobotLog, bins: np.ndarray, gate: float = 1.0, draws: int = 30, seed: int = 0,
                 odom_scale: float = 1.0, sensor_scale: float = 1.0) -> list[dict]:
    """Per interval ``(bins[i], bins[i + 1]]`` of time between two scans: the detection pairs (from different scans,
    placed from dead reckoning, closer than ``gate`` m: the same landmark), the RMS of their distance, and what the
    log's noise model predicts for it: the odometry's part (``draws`` dead reckonings with controls drawn from
    ``odom_scale`` × the odometry covariance, the same pairs) and the sensor's (each detection's range and bearing
    variances times ``sensor_scale``), both RMS. A model that fits predicts the measured RMS; one too loose predicts
    more. Where the model's scatter reaches the gate, the measured RMS cannot follow it past the gate:
    ``gated_m`` is the RMS the model predicts for the pairs the gate keeps (:func:`within_gate_second_moment` of
    each pair's predicted variance, as if isotropic), the figure to set against ``measured_m`` there.
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
    point = (log.scan_cov[0, 0] + ranges**2 * log.scan_cov[1, 1]) * sensor_scale  # a detection's variance (trace)
    sensor = point[a] + point[b]
    gated = within_gate_second_moment(odometry + sensor, gate)
    out = []
    for low, high in zip(bins[:-1], bins[1:]):
        inside = (apart > low) & (apart <= high)
        count = int(inside.sum())
        rms = (lambda v: float(np.sqrt(v[inside].mean())) if count else float("nan"))
        out.append({"from_s": float(low), "to_s": float(high), "pairs": count, "measured_m": rms(measured),
                    "odometry_m": rms(odometry), "sensor_m": rms(sensor), "predicted_m": rms(odometry + sensor),
                    "gated_m": rms(gated)})
    return out
