"""Robot models: Jacobians against central finite differences, angle wrapping, SE(2) algebra."""

import math

import numpy as np
import pytest

from robots.models import (
    AckermannModel,
    RangeBearingSensor,
    UnicycleModel,
    compose_start_jacobian,
    in_field_of_view,
    se2_between,
    se2_compose,
    se2_inverse,
    wrap_angle,
)


def numerical_jacobian(f, x, eps=1e-6, angle_rows=()):
    x = np.asarray(x, float)
    columns = []
    for i in range(x.size):
        step = np.zeros_like(x)
        step[i] = eps
        diff = f(x + step) - f(x - step)
        for row in angle_rows:
            diff[row] = wrap_angle(diff[row])
        columns.append(diff / (2 * eps))
    return np.stack(columns, -1)


@pytest.mark.parametrize("control", [(1.0, 0.5), (0.7, 0.0), (0.0, 0.3), (-0.4, -1.2), (2.0, 1e-7)])
@pytest.mark.parametrize("dt", [0.01, 0.5])
def test_unicycle_jacobians_match_finite_differences(control, dt):
    model = UnicycleModel()
    pose, u = np.array([1.0, -2.0, 2.9]), np.array(control)
    f_pose, f_control = model.jacobians(pose, u, dt)
    np.testing.assert_allclose(f_pose, numerical_jacobian(lambda p: model.step(p, u, dt), pose, angle_rows=(2,)), atol=1e-6)
    np.testing.assert_allclose(f_control, numerical_jacobian(lambda c: model.step(pose, c, dt), u, angle_rows=(2,)), atol=1e-6)


@pytest.mark.parametrize("control", [(3.0, 0.2), (5.0, -0.5), (1.0, 0.0)])
def test_ackermann_jacobians_match_finite_differences(control):
    model = AckermannModel(wheelbase=2.83, encoder_offset=0.76)
    pose, u, dt = np.array([0.5, 0.2, -3.0]), np.array(control), 0.025
    f_pose, f_control = model.jacobians(pose, u, dt)
    np.testing.assert_allclose(f_pose, numerical_jacobian(lambda p: model.step(p, u, dt), pose, angle_rows=(2,)), atol=1e-6)
    np.testing.assert_allclose(f_control, numerical_jacobian(lambda c: model.step(pose, c, dt), u, angle_rows=(2,)), atol=1e-6)


def test_ackermann_encoder_speed_conversion_and_yaw_rate():
    model = AckermannModel(wheelbase=2.0, encoder_offset=0.5)
    steer = 0.3
    (v_c, w), _ = model.to_unicycle(np.array([2.0, steer]))
    assert v_c == pytest.approx(2.0 / (1 - math.tan(steer) * 0.5 / 2.0))
    assert w == pytest.approx(v_c * math.tan(steer) / 2.0)


def test_unicycle_exact_arc_closes_a_circle():
    model = UnicycleModel()
    pose = np.array([0.0, 0.0, 0.0])
    for _ in range(100):
        pose = model.step(pose, np.array([2 * math.pi, 2 * math.pi]), 0.01)
    np.testing.assert_allclose(pose, [0.0, 0.0, 0.0], atol=1e-9)


@pytest.mark.parametrize("offset", [(0.0, 0.0), (3.78, 0.5), (-0.2, -0.4)])
def test_sensor_jacobians_match_finite_differences(offset):
    sensor = RangeBearingSensor(offset)
    pose, landmark = np.array([1.0, 2.0, 3.1]), np.array([-4.0, 0.5])
    h_pose, h_lm = sensor.jacobians(pose, landmark)
    np.testing.assert_allclose(h_pose, numerical_jacobian(lambda p: sensor.observe(p, landmark), pose, angle_rows=(1,)), atol=1e-6)
    np.testing.assert_allclose(h_lm, numerical_jacobian(lambda m: sensor.observe(pose, m), landmark, angle_rows=(1,)), atol=1e-6)
    z = sensor.observe(pose, landmark)
    g_pose, g_z = sensor.inverse_jacobians(pose, z)
    np.testing.assert_allclose(g_pose, numerical_jacobian(lambda p: sensor.inverse(p, z), pose), atol=1e-6)
    np.testing.assert_allclose(g_z, numerical_jacobian(lambda zz: sensor.inverse(pose, zz), z), atol=1e-6)


def test_compose_start_jacobian_matches_finite_differences():
    start, delta = np.array([1.0, -2.0, 2.6]), np.array([0.7, -1.3, 0.4])
    np.testing.assert_allclose(compose_start_jacobian(start, delta),
                               numerical_jacobian(lambda x: se2_compose(x, delta), start, angle_rows=(2,)), atol=1e-6)


@pytest.mark.parametrize("offset", [(0.0, 0.0), (0.3, -0.1)])
def test_pose_seeing_a_point_sees_it_as_observed(offset):
    """Every pose around a point at the given world directions sees the point at the observation, and its sensor
    lies in that direction from it."""
    sensor = RangeBearingSensor(offset)
    point, observation = np.array([2.0, -1.0]), np.array([3.0, 0.4])
    directions = np.linspace(-3.0, 3.0, 7)
    poses = sensor.pose_seeing(np.broadcast_to(point, (7, 2)), np.broadcast_to(observation, (7, 2)), directions)
    np.testing.assert_allclose(sensor.observe(poses[:, None, :], point[None])[:, 0], np.broadcast_to(observation, (7, 2)),
                               atol=1e-12)
    at = point - sensor.sensor_position(poses)[0]
    np.testing.assert_allclose(wrap_angle(np.arctan2(at[:, 1], at[:, 0]) - directions), 0.0, atol=1e-12)


def test_sensor_position_of_one_pose_is_the_stacks_own():
    """One pose takes a scalar path: the same position and derivative, to the bit, as the same pose in a stack."""
    sensor = RangeBearingSensor((0.3, -0.1))
    poses = np.random.default_rng(4).uniform(-5.0, 5.0, (9, 3))
    stacked = sensor.sensor_position(poses)
    for k, pose in enumerate(poses):
        one = sensor.sensor_position(pose)
        assert one[0].shape == one[1].shape == (2,)
        np.testing.assert_array_equal(one[0], stacked[0][k])
        np.testing.assert_array_equal(one[1], stacked[1][k])


def test_sensor_inverse_recovers_landmarks_vectorised():
    rng = np.random.default_rng(3)
    sensor = RangeBearingSensor((0.3, -0.1))
    poses = rng.uniform(-5, 5, (7, 1, 3))
    landmarks = rng.uniform(-10, 10, (7, 11, 2))
    z = sensor.observe(poses, landmarks)
    assert z.shape == (7, 11, 2)
    np.testing.assert_allclose(sensor.inverse(poses, z), landmarks, atol=1e-9)
    h_pose, h_lm = sensor.jacobians(poses, landmarks)
    assert h_pose.shape == (7, 11, 2, 3) and h_lm.shape == (7, 11, 2, 2)


def test_observation_of_a_landmark_straight_ahead_and_to_the_left():
    sensor = RangeBearingSensor()
    z = sensor.observe(np.array([1.0, 1.0, math.pi / 2]), np.array([[1.0, 3.0], [0.0, 1.0]]))
    np.testing.assert_allclose(z, [[2.0, 0.0], [1.0, math.pi / 2]], atol=1e-12)


@pytest.mark.parametrize(
    "angle, wrapped",
    [(0.0, 0.0), (math.pi, -math.pi), (-math.pi, -math.pi), (3 * math.pi, -math.pi), (2 * math.pi, 0.0),
     (math.pi - 1e-12, math.pi - 1e-12), (-3 * math.pi / 2, math.pi / 2), (100.0, 100.0 - 32 * math.pi)],
)
def test_wrap_angle_lands_in_half_open_interval(angle, wrapped):
    result = float(wrap_angle(angle))
    assert -math.pi <= result < math.pi
    assert result == pytest.approx(wrapped, abs=1e-9)


def test_innovation_wraps_the_bearing():
    nu = RangeBearingSensor.innovation(np.array([1.0, math.pi - 0.1]), np.array([1.0, -math.pi + 0.1]))
    np.testing.assert_allclose(nu, [0.0, -0.2], atol=1e-12)


def test_se2_inverse_and_between():
    a, b = np.array([1.0, 2.0, 0.7]), np.array([-3.0, 0.5, -2.5])
    np.testing.assert_allclose(se2_compose(a, se2_inverse(a)), [0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(se2_compose(a, se2_between(a, b)), b, atol=1e-12)


def test_field_of_view_mask():
    obs = np.array([[1.0, 0.0], [1.0, 0.61], [7.0, 0.0], [0.1, 0.0]])
    assert in_field_of_view(obs, max_range=6.0, fov=1.2, min_range=0.3).tolist() == [True, False, False, False]


def test_block_diagonal_is_scipys_block_diag():
    import scipy.linalg

    from robots.gaussian import block_diagonal

    rng = np.random.default_rng(3)
    for shape in [(1, 2, 2), (4, 2, 2), (3, 2, 3), (5, 3, 3)]:
        blocks = rng.normal(size=shape)
        assert np.array_equal(block_diagonal(blocks), scipy.linalg.block_diag(*blocks))


def test_covariance_update_is_the_ekf_updates_covariance():
    from robots.gaussian import ekf_covariance_update, ekf_update

    rng = np.random.default_rng(4)
    a = rng.normal(size=(3, 3))
    prior = a @ a.T + 0.1 * np.eye(3)
    h = rng.normal(size=(4, 3))
    noise = np.diag([0.1, 0.01, 0.2, 0.02])
    _, full = ekf_update(np.zeros(3), prior, rng.normal(size=4), h, noise)
    alone = ekf_covariance_update(prior, h, noise)
    assert np.array_equal(alone, full)
    # the information form says the same: P⁺⁻¹ = P⁻¹ + Hᵀ R⁻¹ H
    assert np.allclose(np.linalg.inv(alone), np.linalg.inv(prior) + h.T @ np.linalg.inv(noise) @ h)
