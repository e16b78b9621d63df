"""D-SLAM recast measurement (Wang, Huang, Dissanayake, eqs. 3, 4, 7-9): invariance, Jacobians, covariance, initialisation."""

import numpy as np
import pytest

from robots.models import RangeBearingSensor, rotation, wrap_angle
from services.dslam.recast import (angle_rows, choose_reference, initialise, innovation, map_measurement, recast,
                                   scan_points)

R = np.diag([0.05**2, np.radians(1.0) ** 2])


def random_points(rng, m):
    return rng.uniform(-5.0, 5.0, size=(m, 2))


@pytest.mark.parametrize("m", [2, 3, 6])
def test_jacobian_matches_finite_differences(m):
    rng = np.random.default_rng(m)
    points = random_points(rng, m)
    z, jac = map_measurement(points)
    assert z.shape == (2 * m - 3,) and jac.shape == (2 * m - 3, m, 2)
    eps = 1e-6
    for i in range(m):
        for a in range(2):
            shifted = points.copy()
            shifted[i, a] += eps
            numeric = innovation(map_measurement(shifted)[0], z) / eps
            np.testing.assert_allclose(jac[:, i, a], numeric, atol=1e-5)


def test_z_map_is_invariant_under_shift_and_rotation():
    rng = np.random.default_rng(1)
    points = random_points(rng, 5)
    moved = points @ rotation(2.1).T + np.array([30.0, -7.0])
    np.testing.assert_allclose(innovation(map_measurement(moved)[0], map_measurement(points)[0]), 0.0, atol=1e-12)


def test_recast_of_a_noiseless_scan_equals_h_map_of_the_landmarks():
    """z_map from (range, bearing) in the sensor frame equals H_map(X) of the world positions, sensor offset or not."""
    rng = np.random.default_rng(2)
    landmarks = random_points(rng, 5) + 10.0
    pose = np.array([8.0, 9.0, 0.7])
    sensor = RangeBearingSensor((0.3, -0.1))
    z_map, r_map = recast(sensor.observe(pose, landmarks), R)
    np.testing.assert_allclose(innovation(z_map, map_measurement(landmarks)[0]), 0.0, atol=1e-12)
    assert r_map.shape == (7, 7) and np.all(np.linalg.eigvalsh(r_map) > 0)


def test_recast_covariance_matches_monte_carlo():
    """R_map by the Jacobian of the recasting against the sample covariance of z_map from noisy scans."""
    rng = np.random.default_rng(3)
    truth = np.array([[3.0, 0.5], [2.0, 2.5], [4.0, -1.5], [1.5, -2.0]])
    exact = RangeBearingSensor().observe(np.zeros(3), truth)
    z_true, r_map = recast(exact, R)
    noisy = exact + rng.standard_normal((5000, 4, 2)) @ np.linalg.cholesky(R).T
    errors = np.array([innovation(map_measurement(scan_points(z, R)[0])[0], z_true) for z in noisy])
    sample_cov = np.cov(errors.T)
    scale = np.sqrt(np.outer(np.diag(r_map), np.diag(r_map)))
    np.testing.assert_allclose(sample_cov / scale, r_map / scale, atol=0.05)
    np.testing.assert_allclose(np.diag(sample_cov), np.diag(r_map), rtol=0.1)


def test_angle_rows_are_the_odd_rows():
    np.testing.assert_array_equal(np.flatnonzero(angle_rows(7)), [1, 3, 5])


def test_innovation_wraps_angles_only():
    nu = innovation(np.array([1.0, 3.1, 2.0]), np.array([0.5, -3.1, 1.0]))
    np.testing.assert_allclose(nu, [0.5, wrap_angle(6.2), 1.0])


def test_initialise_places_new_features_exactly_from_noiseless_z_map():
    rng = np.random.default_rng(4)
    points = random_points(rng, 5)
    z, _ = map_measurement(points)
    pairs = z[1:].reshape(-1, 2)  # (α_i12, d_1i) of features 3..m
    np.testing.assert_allclose(initialise(points[0], points[1], pairs), points[2:], atol=1e-12)


def test_choose_reference_takes_the_farthest_pair_nearest_first():
    points = np.array([[1.0, 0.0], [5.0, 0.0], [1.2, 0.3], [0.5, 4.0], [9.0, 9.0]])
    first, second = choose_reference(points, np.array([0, 1, 2, 3]))
    assert {first, second} == {1, 3}
    assert np.linalg.norm(points[first]) <= np.linalg.norm(points[second])
    with pytest.raises(ValueError):
        choose_reference(points, np.array([2]))
