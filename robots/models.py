"""Robot models: the one place for motion, sensing, their Jacobians and angle wrapping.

Every function is vectorised with numpy broadcasting: a pose is ``(..., 3)``
(x, y, θ), a control ``(..., 2)``, a landmark ``(..., 2)``, an observation
``(..., 2)`` (range, bearing). Jacobians come back as ``(..., rows, cols)``.
Every filter of the project imports these; nothing else models a robot.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

TWO_PI = 2.0 * np.pi


def wrap_angle(angle):
    """Wrap angles to [-π, π) (floor form: about three times faster than np.mod on large arrays)."""
    angle = np.asarray(angle, dtype=float)
    return angle - TWO_PI * np.floor((angle + np.pi) / TWO_PI)


def rotation(theta) -> np.ndarray:
    """2-D rotation matrices ``(..., 2, 2)`` of the angles ``theta``."""
    c, s = np.cos(theta), np.sin(theta)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def se2_compose(a, b) -> np.ndarray:
    """Pose composition a ⊕ b (b expressed in a's frame)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    out = np.empty(x.shape + (3,))  # filled in place: np.stack costs more than the arithmetic on a few poses
    out[..., 0] = x
    out[..., 1] = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    out[..., 2] = wrap_angle(a[..., 2] + b[..., 2])
    return out


def se2_inverse(a) -> np.ndarray:
    """Inverse pose ⊖a."""
    a = np.asarray(a, float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack([-c * a[..., 0] - s * a[..., 1], s * a[..., 0] - c * a[..., 1], wrap_angle(-a[..., 2])], -1)


def se2_between(a, b) -> np.ndarray:
    """Relative pose ⊖a ⊕ b: b expressed in a's frame."""
    return se2_compose(se2_inverse(a), b)


def se2_accumulate(increments) -> np.ndarray:
    """Poses ``(K+1, 3)`` reached from the origin by composing body-frame increments ``(K, 3)`` in order.

    Row k+1 is increments[0] ⊕ … ⊕ increments[k] (a cumulative :func:`se2_compose`), vectorised over K.
    """
    increments = np.asarray(increments, float).reshape(-1, 3)
    heading = np.concatenate([[0.0], np.cumsum(increments[:, 2])])
    c, s = np.cos(heading[:-1]), np.sin(heading[:-1])
    dx = c * increments[:, 0] - s * increments[:, 1]
    dy = s * increments[:, 0] + c * increments[:, 1]
    path = np.zeros((increments.shape[0] + 1, 3))
    path[1:, 0] = np.cumsum(dx)
    path[1:, 1] = np.cumsum(dy)
    path[:, 2] = wrap_angle(heading)
    return path


def _sinc_half(h):
    """sin(h)/h and its derivative, stable at h = 0."""
    h = np.asarray(h, float)
    small = np.abs(h) < 1e-4
    safe = np.where(small, 1.0, h)
    s = np.where(small, 1.0 - h * h / 6.0, np.sin(safe) / safe)
    ds = np.where(small, -h / 3.0, (safe * np.cos(safe) - np.sin(safe)) / (safe * safe))
    return s, ds


def unicycle_step(pose, control, dt) -> np.ndarray:
    """Exact constant-(v, ω) arc over ``dt``: the chord has length v·dt·sinc(ω·dt/2) at heading θ + ω·dt/2."""
    pose, control = np.asarray(pose, float), np.asarray(control, float)
    v, w = control[..., 0], control[..., 1]
    h = 0.5 * w * dt
    s, _ = _sinc_half(h)
    d = v * dt * s
    alpha = pose[..., 2] + h
    return np.stack(
        [pose[..., 0] + d * np.cos(alpha), pose[..., 1] + d * np.sin(alpha), wrap_angle(pose[..., 2] + w * dt)], -1
    )


def unicycle_jacobians(pose, control, dt) -> tuple[np.ndarray, np.ndarray]:
    """Jacobians (F_pose ``(...,3,3)``, F_control ``(...,3,2)``) of :func:`unicycle_step`."""
    pose, control = np.asarray(pose, float), np.asarray(control, float)
    v, w = np.broadcast_arrays(control[..., 0], control[..., 1])
    shape = np.broadcast_shapes(pose.shape[:-1], v.shape)
    h = 0.5 * w * dt
    s, ds = _sinc_half(h)
    d = v * dt * s
    alpha = pose[..., 2] + h
    ca, sa = np.cos(alpha), np.sin(alpha)
    f_pose = np.zeros(shape + (3, 3))
    f_pose[..., 0, 0] = f_pose[..., 1, 1] = f_pose[..., 2, 2] = 1.0
    f_pose[..., 0, 2] = -d * sa
    f_pose[..., 1, 2] = d * ca
    dd_dw = v * dt * ds * 0.5 * dt
    f_control = np.zeros(shape + (3, 2))
    f_control[..., 0, 0] = dt * s * ca
    f_control[..., 1, 0] = dt * s * sa
    f_control[..., 0, 1] = dd_dw * ca - d * sa * 0.5 * dt
    f_control[..., 1, 1] = dd_dw * sa + d * ca * 0.5 * dt
    f_control[..., 2, 1] = dt
    return f_pose, f_control


@dataclass(frozen=True)
class UnicycleModel:
    """Differential-drive robot driven by (v, ω)."""

    name = "unicycle"

    def to_unicycle(self, control) -> tuple[np.ndarray, np.ndarray]:
        """(v, ω) controls and the Jacobian d(v, ω)/d(control) (identity)."""
        control = np.asarray(control, float)
        jac = np.broadcast_to(np.eye(2), control.shape[:-1] + (2, 2))
        return control, jac

    def step(self, pose, control, dt) -> np.ndarray:
        return unicycle_step(pose, control, dt)

    def jacobians(self, pose, control, dt) -> tuple[np.ndarray, np.ndarray]:
        f_pose, f_unicycle = unicycle_jacobians(pose, control, dt)
        return f_pose, f_unicycle


@dataclass(frozen=True)
class AckermannModel:
    """Car-like vehicle (Victoria Park, car park): control = (encoder speed, steering).

    The pose is the rear-axle centre. The encoder wheel sits ``encoder_offset``
    (H) beside it, so the centre speed is v_c = v_e / (1 − tan(α)·H/L), and the
    yaw rate is ω = v_c·tan(α)/L (ACFR model, Guivant & Nebot 2001).
    """

    wheelbase: float = 2.83
    encoder_offset: float = 0.76
    name = "ackermann"

    def to_unicycle(self, control) -> tuple[np.ndarray, np.ndarray]:
        """(v_c, ω) and the Jacobian d(v_c, ω)/d(v_e, α)."""
        control = np.asarray(control, float)
        v_e, steer = control[..., 0], control[..., 1]
        tan_a = np.tan(steer)
        sec2 = 1.0 + tan_a * tan_a
        g = 1.0 - tan_a * self.encoder_offset / self.wheelbase
        v_c = v_e / g
        w = v_c * tan_a / self.wheelbase
        dvc_dve = 1.0 / g
        dvc_da = v_e * (self.encoder_offset / self.wheelbase) * sec2 / (g * g)
        jac = np.empty(control.shape[:-1] + (2, 2))
        jac[..., 0, 0] = dvc_dve
        jac[..., 0, 1] = dvc_da
        jac[..., 1, 0] = dvc_dve * tan_a / self.wheelbase
        jac[..., 1, 1] = (dvc_da * tan_a + v_c * sec2) / self.wheelbase
        return np.stack([v_c, w], -1), jac

    def step(self, pose, control, dt) -> np.ndarray:
        unicycle, _ = self.to_unicycle(control)
        return unicycle_step(pose, unicycle, dt)

    def jacobians(self, pose, control, dt) -> tuple[np.ndarray, np.ndarray]:
        unicycle, dvw_du = self.to_unicycle(control)
        f_pose, f_unicycle = unicycle_jacobians(pose, unicycle, dt)
        return f_pose, f_unicycle @ dvw_du


MotionModel = UnicycleModel | AckermannModel


def motion_model(name: str, wheelbase: float | None = None, encoder_offset: float = 0.0) -> MotionModel:
    """The motion model named in a RobotInfo (an Ackermann model needs its wheelbase: no silent default)."""
    if name == "unicycle":
        return UnicycleModel()
    if name == "ackermann":
        if wheelbase is None or not wheelbase > 0:
            raise ValueError(f"an ackermann motion model needs a wheelbase > 0 (got {wheelbase})")
        return AckermannModel(wheelbase=wheelbase, encoder_offset=encoder_offset)
    raise ValueError(f"unknown motion model {name!r}")


def robot_models(info) -> tuple[MotionModel, "RangeBearingSensor"]:
    """(motion model, sensor) of a robot as its RobotInfo announces it: the one place every filter builds them.

    A RobotInfo is validated when decoded (an Ackermann robot without a wheelbase is refused there), so this
    only raises ValueError for an info built by hand that bypassed validation.
    """
    model = motion_model(info.motion_model, info.wheelbase, info.encoder_offset)
    sensor = RangeBearingSensor((float(info.sensor.offset[0]), float(info.sensor.offset[1])))
    return model, sensor


def dead_reckon(model: MotionModel, controls: np.ndarray, dts: np.ndarray) -> np.ndarray:
    """Poses ``(K+1, 3)`` from the origin after each of the controls ``(K, 2)`` applied for ``dts`` ``(K,)``, without
    noise (exact arcs; headings wrapped)."""
    unicycle, _ = model.to_unicycle(controls)
    return se2_accumulate(unicycle_step(np.zeros(3), unicycle, dts))


def integrate_controls(model: MotionModel, controls: np.ndarray, dts: np.ndarray, covs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Δ̄ ``(3,)``, Σ_Δ ``(3, 3)``) of controls ``(K, 2)`` applied for ``dts`` ``(K,)`` with covariances ``(K, 2, 2)``.

    Prediction over a batch of controls, drawn once per interval: the filter only ever looks at a robot's pose when that robot's scan arrives,
    so it needs p(x_end | x_start, u_1..u_K), not every pose in between. With the
    controls' noise Gaussian and independent, and each step linearised about the
    noise-free path, x_end = x_start ⊕ Δ with Δ ~ N(Δ̄, Σ_Δ), where

    - Δ̄ is the noise-free relative motion (the K exact arcs of ``model.step``
      composed in the start frame), and
    - Σ_Δ = Σ_k M_k G_k Q_k G_kᵀ M_kᵀ, G_k the control Jacobian of step k (from
      ``model.jacobians`` along the noise-free path) and M_k the Jacobian of the
      end pose with respect to the pose after step k. For exact arcs every pose
      Jacobian is I plus a θ column, so the product telescopes:
      M_k = I + [0 0 −(y_K − y_k); 0 0 x_K − x_k; 0 0 0].

    This is exactly the first-order result of drawing noise at each of the K
    steps, and Δ̄, Σ_Δ do not depend on the start pose (rigid invariance), so they
    are computed once per interval for every particle; the per-particle cost is
    one draw and one composition instead of K. The neglected terms are second
    order in the heading noise accumulated over one interval (the filter flushes
    at least every ``max_batch_s``), far below the spread of the particles.
    """
    controls, dts = np.asarray(controls, float), np.asarray(dts, float)
    increments = model.step(np.zeros(3), controls, dts)
    path = se2_accumulate(increments)
    _, f_control = model.jacobians(path[:-1], controls, dts)
    end = path[-1]
    lever = np.zeros((controls.shape[0], 3, 3))
    lever[:, 0, 0] = lever[:, 1, 1] = lever[:, 2, 2] = 1.0
    lever[:, 0, 2] = -(end[1] - path[1:, 1])
    lever[:, 1, 2] = end[0] - path[1:, 0]
    g = lever @ f_control
    cov = np.einsum("kij,kjl,kml->im", g, covs, g)
    return end, 0.5 * (cov + cov.T)


def compose_jacobian(theta: np.ndarray) -> np.ndarray:
    """d(x ⊕ Δ)/dΔ ``(..., 3, 3)`` for start headings ``theta``: a rotation of the position block."""
    c, s = np.cos(theta), np.sin(theta)
    jac = np.zeros(np.shape(theta) + (3, 3))
    jac[..., 0, 0], jac[..., 0, 1], jac[..., 1, 0], jac[..., 1, 1] = c, -s, s, c  # rotation(theta), without its stacks
    jac[..., 2, 2] = 1.0
    return jac


def compose_start_jacobian(start: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """d(x ⊕ Δ)/dx ``(3, 3)`` at start ``x`` ``(3,)`` and increment ``Δ`` ``(3,)``: the increment's lever arm turns
    with the start's heading."""
    c, s = np.cos(start[2]), np.sin(start[2])
    return np.array([[1.0, 0.0, -s * delta[0] - c * delta[1]], [0.0, 1.0, c * delta[0] - s * delta[1]], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class RangeBearingSensor:
    """Range-bearing sensor mounted at ``offset`` = (a, b) in the body frame (x forward, y left)."""

    offset: tuple[float, float] = (0.0, 0.0)

    def sensor_position(self, pose) -> tuple[np.ndarray, np.ndarray]:
        """Sensor position ``(..., 2)`` and its derivative with respect to θ."""
        pose = np.asarray(pose, float)
        a, b = self.offset
        if pose.ndim == 1:  # one pose (a scan's association): the same arithmetic without the array machinery
            c, s = math.cos(pose[2]), math.sin(pose[2])
            return (np.array([pose[0] + a * c - b * s, pose[1] + a * s + b * c]),
                    np.array([-a * s - b * c, a * c - b * s]))
        c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
        position, d_theta = np.empty(c.shape + (2,)), np.empty(c.shape + (2,))
        position[..., 0], position[..., 1] = pose[..., 0] + a * c - b * s, pose[..., 1] + a * s + b * c
        d_theta[..., 0], d_theta[..., 1] = -a * s - b * c, a * c - b * s
        return position, d_theta

    def observe(self, pose, landmarks) -> np.ndarray:
        """Predicted (range, bearing) ``(..., 2)`` of ``landmarks`` from ``pose`` (broadcast)."""
        pose = np.asarray(pose, float)
        position, _ = self.sensor_position(pose)
        delta = np.asarray(landmarks, float) - position
        r = np.hypot(delta[..., 0], delta[..., 1])
        phi = wrap_angle(np.arctan2(delta[..., 1], delta[..., 0]) - pose[..., 2])
        return np.stack([r, phi], -1)

    def jacobians(self, pose, landmarks) -> tuple[np.ndarray, np.ndarray]:
        """(H_pose ``(...,2,3)``, H_landmark ``(...,2,2)``) of :meth:`observe`."""
        pose = np.asarray(pose, float)
        position, d_theta = self.sensor_position(pose)
        delta = np.asarray(landmarks, float) - position
        dx, dy = delta[..., 0], delta[..., 1]
        q = np.maximum(dx * dx + dy * dy, 1e-18)
        r = np.sqrt(q)
        h_lm = np.empty(delta.shape[:-1] + (2, 2))
        h_lm[..., 0, 0] = dx / r
        h_lm[..., 0, 1] = dy / r
        h_lm[..., 1, 0] = -dy / q
        h_lm[..., 1, 1] = dx / q
        h_pose = np.empty(delta.shape[:-1] + (2, 3))
        h_pose[..., :, :2] = -h_lm
        d_theta = np.broadcast_to(d_theta, delta.shape)
        h_pose[..., 0, 2] = -(h_lm[..., 0, 0] * d_theta[..., 0] + h_lm[..., 0, 1] * d_theta[..., 1])
        h_pose[..., 1, 2] = -(h_lm[..., 1, 0] * d_theta[..., 0] + h_lm[..., 1, 1] * d_theta[..., 1]) - 1.0
        return h_pose, h_lm

    def observe_with_jacobian(self, pose, landmarks) -> tuple[np.ndarray, np.ndarray]:
        """(:meth:`observe`, H_landmark of :meth:`jacobians`) in one pass, for filters that need both per landmark."""
        pose = np.asarray(pose, float)
        position, _ = self.sensor_position(pose)
        delta = np.asarray(landmarks, float) - position
        dx, dy = delta[..., 0], delta[..., 1]
        q = dx * dx + dy * dy
        r = np.sqrt(q)
        q = np.maximum(q, 1e-18)
        rs = np.maximum(r, 1e-9)
        z = np.empty(delta.shape)
        z[..., 0] = r
        z[..., 1] = wrap_angle(np.arctan2(dy, dx) - pose[..., 2])
        h_lm = np.empty(delta.shape[:-1] + (2, 2))
        h_lm[..., 0, 0] = dx / rs
        h_lm[..., 0, 1] = dy / rs
        h_lm[..., 1, 0] = -dy / q
        h_lm[..., 1, 1] = dx / q
        return z, h_lm

    def inverse(self, pose, observation) -> np.ndarray:
        """Landmark position ``(..., 2)`` that would produce ``observation`` from ``pose``."""
        pose, observation = np.asarray(pose, float), np.asarray(observation, float)
        position, _ = self.sensor_position(pose)
        beta = pose[..., 2] + observation[..., 1]
        r = observation[..., 0]
        return position + np.stack([r * np.cos(beta), r * np.sin(beta)], -1)

    def pose_seeing(self, point, observation, direction) -> np.ndarray:
        """Robot pose ``(..., 3)`` whose sensor sees ``point`` ``(..., 2)`` at ``observation`` (range, bearing)
        ``(..., 2)`` while the world direction from the sensor to the point is ``direction`` ``(...)``: the one
        unknown a single detection of a known point leaves (the sensor on a circle around it)."""
        point, observation, direction = (np.asarray(v, float) for v in (point, observation, direction))
        r, bearing = observation[..., 0], observation[..., 1]
        at = point - r[..., None] * np.stack([np.cos(direction), np.sin(direction)], -1)
        theta = wrap_angle(direction - bearing)
        a, b = self.offset
        c, s = np.cos(theta), np.sin(theta)
        return np.stack([at[..., 0] - (a * c - b * s), at[..., 1] - (a * s + b * c), theta], -1)

    def inverse_jacobians(self, pose, observation) -> tuple[np.ndarray, np.ndarray]:
        """(G_pose ``(...,2,3)``, G_observation ``(...,2,2)``) of :meth:`inverse`."""
        pose, observation = np.asarray(pose, float), np.asarray(observation, float)
        _, d_theta = self.sensor_position(pose)
        beta = pose[..., 2] + observation[..., 1]
        r = observation[..., 0]
        cb, sb = np.cos(beta), np.sin(beta)
        shape = np.broadcast_shapes(pose.shape[:-1], observation.shape[:-1])
        g_obs = np.empty(shape + (2, 2))
        g_obs[..., 0, 0] = cb
        g_obs[..., 0, 1] = -r * sb
        g_obs[..., 1, 0] = sb
        g_obs[..., 1, 1] = r * cb
        g_pose = np.zeros(shape + (2, 3))
        g_pose[..., 0, 0] = g_pose[..., 1, 1] = 1.0
        g_pose[..., 0, 2] = d_theta[..., 0] - r * sb
        g_pose[..., 1, 2] = d_theta[..., 1] + r * cb
        return g_pose, g_obs

    @staticmethod
    def innovation(measured, predicted) -> np.ndarray:
        """z − ẑ with the bearing difference wrapped."""
        nu = np.asarray(measured, float) - np.asarray(predicted, float)
        nu[..., 1] = wrap_angle(nu[..., 1])
        return nu


def in_field_of_view(observations, max_range: float, fov: float, min_range: float = 0.0) -> np.ndarray:
    """Mask of (range, bearing) observations inside [min_range, max_range] and |bearing| ≤ fov/2."""
    observations = np.asarray(observations, float)
    r, phi = observations[..., 0], observations[..., 1]
    return (r >= min_range) & (r <= max_range) & (np.abs(phi) <= 0.5 * fov + 1e-12)


def transform_points(pose, points) -> np.ndarray:
    """Points ``(..., 2)`` given in the frame of ``pose`` expressed in the outer frame (R(θ)·p + t)."""
    pose, points = np.asarray(pose, float), np.asarray(points, float)
    c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    x, y = points[..., 0], points[..., 1]
    return np.stack([pose[..., 0] + c * x - s * y, pose[..., 1] + s * x + c * y], -1)


def fit_se2(source, target, weights=None) -> np.ndarray:
    """The pose T = (x, y, θ) minimising Σ wᵢ‖T·sourceᵢ − targetᵢ‖² over matched 2-D points.

    Closed form of Horn/Umeyama in the plane, without scale: centre both sets,
    θ = atan2(Σ w (a × b), Σ w (a · b)), then t = mean_target − R(θ)·mean_source.
    """
    source, target = np.asarray(source, float).reshape(-1, 2), np.asarray(target, float).reshape(-1, 2)
    w = np.ones(source.shape[0]) if weights is None else np.asarray(weights, float)
    if source.shape != target.shape or source.shape[0] == 0 or w.sum() <= 0:
        raise ValueError("fit_se2 needs the same non-zero number of source and target points")
    w = w / w.sum()
    mean_s, mean_t = w @ source, w @ target
    a, b = source - mean_s, target - mean_t
    dot = np.sum(w * (a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]))
    cross = np.sum(w * (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]))
    theta = float(np.arctan2(cross, dot))
    shift = mean_t - transform_points(np.array([0.0, 0.0, theta]), mean_s)
    return np.array([shift[0], shift[1], theta])
