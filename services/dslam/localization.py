"""Localization in D-SLAM (Wang, Huang, Dissanayake, "Implementation Issues and Experimental Evaluation of D-SLAM",
§2.3): a 3-dof estimate of each robot's pose.

Two estimates of the pose are combined by covariance intersection (CI),
because their correlation is unknown (the map they both depend on was built
from the same observations):

- the process-model estimate: the previous pose pushed through the motion
  model with the odometry (:func:`predict`);
- the estimate from the observations z_loc of mapped landmarks and the joint
  covariance of those landmarks (:func:`observation_estimate`, iterated
  Gauss-Newton). With one landmark it is rank-deficient: it is then kept in
  information form, linearised at the predicted pose, and CI still applies.

CI (Julier & Uhlmann): P⁻¹ = ω P_a⁻¹ + (1−ω) P_b⁻¹, x = P (ω P_a⁻¹ x_a + (1−ω) P_b⁻¹ x_b),
with ω in [0, 1] minimising the trace or the determinant of P. It is
consistent for any cross-correlation between the two estimates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robots.models import MotionModel, RangeBearingSensor, rotation, wrap_angle


def predict(pose: np.ndarray, cov: np.ndarray, model: MotionModel, control: np.ndarray, control_cov: np.ndarray,
            dt: float) -> tuple[np.ndarray, np.ndarray]:
    """The process-model estimate: pose and covariance after one control (EKF prediction)."""
    f_pose, f_control = model.jacobians(pose, control, dt)
    new_cov = f_pose @ cov @ f_pose.T + f_control @ control_cov @ f_control.T
    return model.step(pose, control, dt), 0.5 * (new_cov + new_cov.T)


@dataclass
class ObservationEstimate:
    """The pose information carried by observations of mapped landmarks.

    ``info`` is H_xᵀ S⁻¹ H_x and ``gradient`` = info · (x_obs − x_lin) when the
    estimate is full rank (then ``pose`` is x_obs), or H_xᵀ S⁻¹ ν at the
    linearisation point x_lin when it is not (then ``pose`` is x_lin).
    """

    pose: np.ndarray
    info: np.ndarray
    gradient: np.ndarray
    full_rank: bool
    iterations: int = 0


def _stacked(sensor: RangeBearingSensor, pose, observations, noise, landmarks, landmark_cov):
    """Residual ν (2m,), H_x (2m, 3) and S = R + H_L P_LL H_Lᵀ (2m, 2m) at ``pose``."""
    predicted = sensor.observe(pose, landmarks)
    residual = sensor.innovation(observations, predicted).ravel()
    h_pose, h_lm = sensor.jacobians(pose, landmarks)
    m = landmarks.shape[0]
    blocks = np.einsum("iab,ibjc,jdc->iajd", h_lm, landmark_cov.reshape(m, 2, m, 2), h_lm)
    blocks[np.arange(m), :, np.arange(m), :] += noise
    s = blocks.reshape(2 * m, 2 * m)
    return residual, h_pose.reshape(2 * m, 3), 0.5 * (s + s.T)


def _information(residual, h_pose, s) -> tuple[np.ndarray, np.ndarray]:
    """H_xᵀ S⁻¹ H_x and H_xᵀ S⁻¹ ν (one solve)."""
    weighted = np.linalg.solve(s, np.column_stack([h_pose, residual]))
    product = h_pose.T @ weighted
    info = product[:, :3]
    return 0.5 * (info + info.T), product[:, 3]


def observation_estimate(sensor: RangeBearingSensor, pose: np.ndarray, observations: np.ndarray, noise: np.ndarray,
                         landmarks: np.ndarray, landmark_cov: np.ndarray, iterations: int = 5,
                         tol: float = 1e-7) -> ObservationEstimate:
    """The estimate of the pose from z_loc (eq. 12) and the mapped landmarks, from the guess ``pose``.

    Gauss-Newton on Σ νᵀ S⁻¹ ν with S = R + H_L P_LL H_Lᵀ (landmark uncertainty,
    with its correlations, propagated into the observations). Rank-deficient
    (one landmark): the information at ``pose`` only.
    """
    pose = np.asarray(pose, float)
    residual, h_pose, s = _stacked(sensor, pose, observations, noise, landmarks, landmark_cov)
    info, gradient = _information(residual, h_pose, s)
    if not (np.all(np.isfinite(info)) and np.all(np.isfinite(gradient))):
        return ObservationEstimate(pose, np.zeros((3, 3)), np.zeros(3), False)
    if landmarks.shape[0] < 2 or np.linalg.cond(info) > 1e12:
        return ObservationEstimate(pose, info, gradient, False)
    current = pose.copy()
    done = 0
    for done in range(1, iterations + 1):
        step = np.linalg.solve(info, gradient)
        if not np.all(np.isfinite(step)) or np.max(np.abs(step[:2])) > 1e3:
            residual, h_pose, s = _stacked(sensor, pose, observations, noise, landmarks, landmark_cov)
            info, gradient = _information(residual, h_pose, s)
            return ObservationEstimate(pose, info, gradient, False, done)
        current = current + step
        current[2] = wrap_angle(current[2])
        residual, h_pose, s = _stacked(sensor, current, observations, noise, landmarks, landmark_cov)
        info, gradient = _information(residual, h_pose, s)
        if np.max(np.abs(step)) < tol:
            break
    delta = current - pose
    delta[2] = wrap_angle(delta[2])
    return ObservationEstimate(current, info, info @ delta, True, done)


def _ci_cost(omegas: np.ndarray, info_a: np.ndarray, info_b: np.ndarray, criterion: str) -> np.ndarray:
    """trace or log-determinant of (ω Y_a + (1−ω) Y_b)⁻¹ for a vector of ω (inf where singular)."""
    fused = omegas[:, None, None] * info_a + (1.0 - omegas)[:, None, None] * info_b
    sign, logdet = np.linalg.slogdet(fused)
    good = (sign > 0) & (logdet > -700)
    cost = np.full(omegas.shape, np.inf)
    if criterion == "det":
        cost[good] = -logdet[good]
    else:
        cost[good] = np.trace(np.linalg.inv(fused[good]), axis1=1, axis2=2)
    return cost


def choose_omega(info_a: np.ndarray, info_b: np.ndarray, criterion: str = "trace", tol: float = 1e-4) -> float:
    """ω in [0, 1] minimising trace or determinant of (ω Y_a + (1−ω) Y_b)⁻¹.

    Both costs are convex in ω: search a grid of 33 points, then narrow the
    bracket around the best point until the grid step is below ``tol``.
    """
    if criterion not in ("trace", "det"):
        raise ValueError(f"unknown CI criterion {criterion!r}: use 'trace' or 'det'")
    lo, hi = 0.0, 1.0
    while True:
        grid = np.linspace(lo, hi, 33)
        cost = _ci_cost(grid, info_a, info_b, criterion)
        best = int(np.argmin(cost))
        if not np.isfinite(cost[best]):
            raise np.linalg.LinAlgError("no ω gives a positive definite fused information")
        step = grid[1] - grid[0]
        if step <= tol:
            return float(grid[best])
        lo, hi = max(0.0, grid[best] - step), min(1.0, grid[best] + step)


def intersect(mean_a: np.ndarray, info_a: np.ndarray, info_b: np.ndarray, gradient_b: np.ndarray,
              criterion: str = "trace", angle_index: int | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """CI in information form: estimate a (mean, information) with b given as information and gradient at mean_a.

    Returns (mean, covariance, ω): x = x_a + (1−ω) P g_b, P = (ω Y_a + (1−ω) Y_b)⁻¹.
    """
    omega = choose_omega(info_a, info_b, criterion)
    fused = omega * info_a + (1.0 - omega) * info_b
    cov = np.linalg.inv(fused)
    mean = np.asarray(mean_a, float) + (1.0 - omega) * (cov @ gradient_b)
    if angle_index is not None:
        mean[angle_index] = wrap_angle(mean[angle_index])
    return mean, 0.5 * (cov + cov.T), omega


def covariance_intersection(mean_a: np.ndarray, cov_a: np.ndarray, mean_b: np.ndarray, cov_b: np.ndarray,
                            criterion: str = "trace", angle_index: int | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """CI of two full estimates (mean, covariance) whose cross-correlation is unknown; returns (mean, cov, ω)."""
    info_a = np.linalg.inv(cov_a)
    info_b = np.linalg.inv(cov_b)
    delta = np.asarray(mean_b, float) - np.asarray(mean_a, float)
    if angle_index is not None:
        delta[angle_index] = wrap_angle(delta[angle_index])
    return intersect(mean_a, info_a, info_b, info_b @ delta, criterion, angle_index)


def localize(prior_pose: np.ndarray, prior_cov: np.ndarray, estimate: ObservationEstimate,
             criterion: str = "trace") -> tuple[np.ndarray, np.ndarray, float]:
    """Combine the process-model estimate with the observation estimate by CI; returns (pose, cov, ω).

    ``estimate`` must have been linearised at ``prior_pose`` (its gradient is relative to it).
    """
    return intersect(prior_pose, np.linalg.inv(prior_cov), estimate.info, estimate.gradient, criterion, angle_index=2)


def pose_from_points(sensor_points: np.ndarray, world_points: np.ndarray,
                     offset: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """The pose that maps points seen in the sensor frame onto their world positions (2-D Kabsch).

    Used to place a robot whose start pose is unknown once it sees two mapped landmarks.
    """
    a = np.asarray(sensor_points, float)
    b = np.asarray(world_points, float)
    ca, cb = a.mean(0), b.mean(0)
    cross = (a - ca).T @ (b - cb)
    theta = np.arctan2(cross[0, 1] - cross[1, 0], cross[0, 0] + cross[1, 1])
    sensor_position = cb - rotation(theta) @ ca
    body = sensor_position - rotation(theta) @ np.asarray(offset, float)
    return np.array([body[0], body[1], wrap_angle(theta)])
