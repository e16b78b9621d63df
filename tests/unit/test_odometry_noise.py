"""The odometry noise gain (robots/odometry_noise.py): its covariance algebra against sampling, and that it finds how
loose an announced covariance is on constructed robots; FastSLAM's gain with it on a simulated fleet."""

from __future__ import annotations

import numpy as np
import pytest

from robots.models import RangeBearingSensor, se2_compose, wrap_angle
from robots.odometry_noise import OdometryNoiseGain, displacement_cov, increment_sums


def _increments(rng: np.random.Generator, count: int) -> tuple[np.ndarray, np.ndarray]:
    deltas = np.column_stack([rng.uniform(0.05, 0.3, count), rng.normal(0.0, 0.02, count), rng.normal(0.0, 0.1, count)])
    roots = rng.normal(0.0, 1.0, (count, 3, 3)) * np.array([0.01, 0.005, 0.003])  # small: first order holds
    return deltas, roots @ np.swapaxes(roots, -1, -2) + 1e-6 * np.eye(3)


def test_displacement_cov_is_the_sum_over_increments_of_their_levered_errors():
    rng = np.random.default_rng(0)
    deltas, covs = _increments(rng, 25)
    pose, sums, brute = np.zeros(3), [0.0] * 17, np.zeros((2, 2))
    ends, world_covs = [], []
    for delta, cov in zip(deltas, covs):
        c, s = np.cos(pose[2]), np.sin(pose[2])
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        pose = se2_compose(pose, delta)
        sums = [a + b for a, b in zip(sums, increment_sums(cov.tolist(), float(pose[2] - delta[2]), pose))]
        ends.append(pose[:2].copy())
        world_covs.append(rot @ cov @ rot.T)
    point = pose[:2] + np.array([2.0, 1.0])
    for end, cov in zip(ends, world_covs):
        lever = point - end
        b = np.array([[1.0, 0.0, -lever[1]], [0.0, 1.0, lever[0]]])
        brute += b @ cov @ b.T
    xx, xy, yy = displacement_cov(sums, point)
    assert np.allclose([[xx, xy], [xy, yy]], brute, rtol=1e-9, atol=1e-12)


def test_displacement_cov_agrees_with_sampled_dead_reckoning():
    rng = np.random.default_rng(1)
    deltas, covs = _increments(rng, 20)
    z = np.array([3.0, 0.4])
    sensor = RangeBearingSensor((0.2, 0.0))
    gain = OdometryNoiseGain()
    for delta, cov in zip(deltas, covs):
        gain.move(delta, cov)
    place = sensor.inverse(np.asarray(gain.pose), z)
    xx, xy, yy = displacement_cov(gain.sums, place)
    draws = 20000
    poses = np.zeros((draws, 3))
    for delta, cov in zip(deltas, covs):
        poses = se2_compose(poses, delta + rng.multivariate_normal(np.zeros(3), cov, draws))
    sampled = np.cov(sensor.inverse(poses, z).T)
    assert np.allclose([[xx, xy], [xy, yy]], sampled, rtol=0.08, atol=2e-4)


def _detect(rng, sensor: RangeBearingSensor, pose: np.ndarray, landmarks: np.ndarray, r: np.ndarray,
            wrong_ids: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(ids, noisy range-bearing rows) of the landmarks within 6 m and ±0.6 rad of ``pose``; ``wrong_ids``: the
    share of detections given a wrong landmark's id."""
    seen = sensor.observe(pose, landmarks)
    view = (seen[:, 0] < 6.0) & (np.abs(seen[:, 1]) < 0.6)
    ids = np.flatnonzero(view)
    if wrong_ids:
        wrong = rng.random(ids.size) < wrong_ids
        ids[wrong] = rng.integers(0, len(landmarks), int(wrong.sum()))
    z = seen[view] + rng.multivariate_normal(np.zeros(2), r, ids.size)
    z[:, 1] = wrap_angle(z[:, 1])
    return ids, z


def _drive(fraction: float, seed: int, steps: int = 6000) -> OdometryNoiseGain:
    """A robot circling among landmarks whose odometry's real noise is ``fraction`` of what it announces; every
    landmark within 6 m and ±0.6 rad is detected with its id. The estimator's gain after ``steps`` scans."""
    rng = np.random.default_rng(seed)
    landmarks = rng.uniform(-8.0, 8.0, (30, 2))
    sensor = RangeBearingSensor((0.1, 0.0))
    announced = np.diag([0.05**2, 0.01**2, 0.02**2])  # per 0.1 s step, in the robot's frame
    r = np.diag([0.05**2, 0.01**2])
    estimator = OdometryNoiseGain(1.0, 2.0**-6, 4.0, 0.02)
    pose = np.array([5.0, 0.0, np.pi / 2])
    for _ in range(steps):
        delta = np.array([0.1, 0.0, 0.02])  # a circle of radius 5 m
        true = delta + rng.multivariate_normal(np.zeros(3), fraction * announced)
        pose = se2_compose(pose, true)
        estimator.move(delta, announced)
        ids, z = _detect(rng, sensor, pose, landmarks, r)
        estimator.scan(sensor.offset, ids.tolist(), z, r)
    return estimator


@pytest.mark.parametrize("fraction", [1.0 / 16, 0.25, 1.0, 2.0])
def test_the_gain_finds_how_loose_the_announced_odometry_is(fraction):
    estimator = _drive(fraction, seed=3)
    assert estimator.pairs > 500
    assert fraction / 1.6 < estimator.gain < fraction * 1.6, estimator.gain


def test_the_gain_stays_within_its_bounds():
    estimator = _drive(1.0 / 16, seed=4, steps=3000)
    bounded = OdometryNoiseGain(1.0, 0.5, 1.0, 0.02)
    bounded.step_gain(False)
    for _ in range(200):
        bounded.step_gain(False)
    assert bounded.gain == 0.5
    assert estimator.gain >= 2.0**-6


def _drive_turning(true_scale: float, seed: int, steps: int = 4000, wrong_ids: float = 0.0,
                   adapt: bool = True) -> OdometryNoiseGain:
    """A robot weaving among landmarks whose true turn is ``true_scale`` × its odometry's; its motion turns by the
    estimator's present turn scale × the odometry's, as FastSLAM's does (``wrong_ids``: see :func:`_detect`). The
    estimator after ``steps`` scans."""
    rng = np.random.default_rng(seed)
    landmarks = rng.uniform(-8.0, 8.0, (30, 2))
    sensor = RangeBearingSensor((0.1, 0.0))
    announced = np.diag([0.01**2, 0.002**2, 0.004**2])
    r = np.diag([0.05**2, 0.01**2])
    estimator = OdometryNoiseGain(1.0, 2.0**-6, 4.0, 0.02, turn_scale_bounds=(0.8, 1.25) if adapt else None)
    pose = np.array([5.0, 0.0, np.pi / 2])
    for k in range(steps):
        odometry = np.array([0.1, 0.0, 0.02 + 0.06 * np.sin(k / 40.0)])  # a weave around a circle of radius 5 m
        true = odometry * (1.0, 1.0, true_scale) + rng.multivariate_normal(np.zeros(3), announced)
        pose = se2_compose(pose, true)
        estimator.move(odometry * (1.0, 1.0, estimator.turn_scale), announced)
        ids, z = _detect(rng, sensor, pose, landmarks, r, wrong_ids)
        estimator.scan(sensor.offset, ids.tolist(), z, r)
    return estimator


@pytest.mark.parametrize("true_scale, wrong_ids", [(0.9, 0.0), (1.1, 0.0), (1.0, 0.0), (0.9, 0.1)])
def test_the_turn_scale_finds_how_much_the_odometry_over_or_under_counts_its_turns(true_scale, wrong_ids):
    estimator = _drive_turning(true_scale, seed=5, wrong_ids=wrong_ids)
    assert estimator.turn_pairs > 80
    assert abs(estimator.turn_scale - true_scale) < 0.025, estimator.turn_scale


def test_the_turn_scale_stays_one_unless_it_adapts():
    assert _drive_turning(0.9, seed=5, steps=500, adapt=False).turn_scale == 1.0
