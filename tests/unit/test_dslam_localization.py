"""D-SLAM localization: covariance intersection (consistent for any correlation), observation estimate, prediction."""

import numpy as np
import pytest

from robots.models import RangeBearingSensor, UnicycleModel
from services.dslam.localization import (choose_omega, covariance_intersection, intersect, localize,
                                         observation_estimate, pose_from_points, predict)

R = np.diag([0.05**2, np.radians(1.0) ** 2])


def random_joint(rng, size=6):
    a = rng.standard_normal((size, size + 2))
    return a @ a.T / size


@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_ci_is_consistent_for_any_cross_correlation(criterion):
    """For cross-covariances from valid joint covariances, up to full correlation, P_CI ⪰ the true error covariance."""
    rng = np.random.default_rng(0)
    for trial in range(200):
        joint = random_joint(rng)
        if trial % 4 == 0:  # fully correlated: b is a linear image of a's error
            base = random_joint(rng, 3)
            t = rng.standard_normal((3, 3))
            joint = np.block([[base, base @ t.T], [t @ base, t @ base @ t.T + 1e-9 * np.eye(3)]])
        p_a, p_b, p_ab = joint[:3, :3], joint[3:, 3:], joint[:3, 3:]
        _, p_ci, omega = covariance_intersection(np.zeros(3), p_a, np.zeros(3), p_b, criterion)
        k_a = omega * p_ci @ np.linalg.inv(p_a)
        k_b = (1 - omega) * p_ci @ np.linalg.inv(p_b)
        true = k_a @ p_a @ k_a.T + k_b @ p_b @ k_b.T + k_a @ p_ab @ k_b.T + k_b @ p_ab.T @ k_a.T
        assert np.min(np.linalg.eigvalsh(p_ci - true)) > -1e-9 * np.max(np.abs(true))


@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_omega_minimises_the_criterion(criterion):
    rng = np.random.default_rng(1)
    for _ in range(20):
        y_a, y_b = np.linalg.inv(random_joint(rng, 3)), np.linalg.inv(random_joint(rng, 3))
        omega = choose_omega(y_a, y_b, criterion)
        grid = np.linspace(0, 1, 2001)
        fused = grid[:, None, None] * y_a + (1 - grid)[:, None, None] * y_b
        cost = np.trace(np.linalg.inv(fused), axis1=1, axis2=2) if criterion == "trace" else -np.linalg.slogdet(fused)[1]
        chosen = omega * y_a + (1 - omega) * y_b
        value = np.trace(np.linalg.inv(chosen)) if criterion == "trace" else -np.linalg.slogdet(chosen)[1]
        assert value <= cost.min() + 1e-6 * abs(cost.min())


def test_ci_of_an_estimate_with_itself_returns_it():
    p = np.diag([0.1, 0.2, 0.01])
    mean, cov, _ = covariance_intersection(np.array([1.0, 2.0, 0.3]), p, np.array([1.0, 2.0, 0.3]), p)
    np.testing.assert_allclose(mean, [1.0, 2.0, 0.3])
    np.testing.assert_allclose(cov, p, rtol=1e-6)


def test_ci_accepts_rank_deficient_information():
    """One landmark seen: the observation estimate has rank-2 information; CI still gives a proper estimate."""
    y_a = np.diag([10.0, 10.0, 100.0])
    y_b = np.diag([50.0, 50.0, 0.0])
    mean, cov, omega = intersect(np.zeros(3), y_a, y_b, y_b @ np.array([0.1, -0.1, 0.0]), angle_index=2)
    assert 0 < omega < 1 and np.all(np.linalg.eigvalsh(cov) > 0)
    assert mean[0] > 0 and mean[1] < 0 and mean[2] == pytest.approx(0.0)


def test_observation_estimate_recovers_the_pose_from_noiseless_observations():
    rng = np.random.default_rng(2)
    landmarks = rng.uniform(-6, 6, size=(5, 2))
    pose = np.array([0.5, -0.3, 0.4])
    sensor = RangeBearingSensor((0.2, 0.05))
    z = sensor.observe(pose, landmarks)
    guess = pose + np.array([0.3, -0.2, 0.1])
    estimate = observation_estimate(sensor, guess, z, R, landmarks, np.eye(10) * 1e-4)
    assert estimate.full_rank
    np.testing.assert_allclose(estimate.pose, pose, atol=1e-8)
    np.testing.assert_allclose(estimate.gradient, estimate.info @ (estimate.pose - guess), atol=1e-8)
    fused, cov, _ = localize(guess, np.diag([0.5, 0.5, 0.1]), estimate)
    assert np.linalg.norm(fused[:2] - pose[:2]) < np.linalg.norm(guess[:2] - pose[:2])


def test_landmark_uncertainty_widens_the_observation_estimate():
    landmarks = np.array([[3.0, 1.0], [2.0, -2.0], [4.0, 0.0]])
    sensor = RangeBearingSensor()
    z = sensor.observe(np.zeros(3), landmarks)
    sharp = observation_estimate(sensor, np.zeros(3), z, R, landmarks, np.zeros((6, 6)))
    common = np.kron(np.ones((3, 3)), np.eye(2)) * 0.04  # the three landmarks share one offset error
    vague = observation_estimate(sensor, np.zeros(3), z, R, landmarks, common + 1e-6 * np.eye(6))
    cov_sharp, cov_vague = np.linalg.inv(sharp.info), np.linalg.inv(vague.info)
    assert cov_vague[0, 0] > cov_sharp[0, 0] + 0.03 and cov_vague[1, 1] > cov_sharp[1, 1] + 0.03


def test_pose_from_points_with_a_sensor_offset():
    pose = np.array([2.0, -1.0, 2.5])
    sensor = RangeBearingSensor((0.3, -0.1))
    world = np.array([[4.0, 1.0], [0.0, 0.0], [1.0, 3.0]])
    z = sensor.observe(pose, world)
    local = np.column_stack([z[:, 0] * np.cos(z[:, 1]), z[:, 0] * np.sin(z[:, 1])])
    np.testing.assert_allclose(pose_from_points(local, world, (0.3, -0.1)), pose, atol=1e-12)


def test_predict_is_the_ekf_prediction_of_the_model():
    model = UnicycleModel()
    control, q, p = np.array([1.0, 0.2]), np.diag([0.01, 0.001]), np.diag([1e-4, 2e-4, 1e-5])
    pose, cov = predict(np.zeros(3), p, model, control, q, 0.5)
    f_pose, f_control = model.jacobians(np.zeros(3), control, 0.5)
    np.testing.assert_allclose(pose, model.step(np.zeros(3), control, 0.5))
    np.testing.assert_allclose(cov, f_pose @ p @ f_pose.T + f_control @ q @ f_control.T)

