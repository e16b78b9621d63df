"""Compiled (numba) kernels of the robot models; the numpy functions in :mod:`robots.models` stay the references.

- :func:`integrate_controls`: a robot's buffered controls as one Gaussian relative motion
  (:func:`robots.models.integrate_controls`, unicycle and Ackermann models). FastSLAM and MCL both predict once
  per scan from it (each particle draws once from the result instead of once per control).
"""

from __future__ import annotations

import math

import numpy as np

from robots.models import AckermannModel, UnicycleModel
from services.compiled import njit, wrap_angle


@njit
def integrate_controls_kernel(ackermann, wheelbase, encoder_offset, controls, dts, covs):
    """(Δ̄ ``(3,)``, Σ_Δ ``(3, 3)``): the reference's exact arcs composed from the origin, and Σ Σ_k M_k G_k Q_k
    G_kᵀ M_kᵀ with M_k the lever of the end pose about pose k and G_k the control Jacobian."""
    count = controls.shape[0]
    path = np.zeros((count + 1, 3))
    g = np.zeros((count, 3, 2))
    heading_sum = 0.0
    for k in range(count):
        v, w = controls[k, 0], controls[k, 1]
        j00, j01, j10, j11 = 1.0, 0.0, 0.0, 1.0
        if ackermann:
            tan_a = math.tan(w)
            sec2 = 1.0 + tan_a * tan_a
            den = 1.0 - tan_a * encoder_offset / wheelbase
            v_e = v
            v = v_e / den
            w = v * tan_a / wheelbase
            j00 = 1.0 / den
            j01 = v_e * (encoder_offset / wheelbase) * sec2 / (den * den)
            j10 = j00 * tan_a / wheelbase
            j11 = (j01 * tan_a + v * sec2) / wheelbase
        dt = dts[k]
        h = 0.5 * w * dt
        if abs(h) < 1e-4:
            sinc, dsinc = 1.0 - h * h / 6.0, -h / 3.0
        else:
            sinc, dsinc = math.sin(h) / h, (h * math.cos(h) - math.sin(h)) / (h * h)
        chord = v * dt * sinc
        step_x, step_y, step_theta = chord * math.cos(h), chord * math.sin(h), wrap_angle(w * dt)  # the arc from the origin
        heading = heading_sum
        c, s = math.cos(heading), math.sin(heading)
        path[k + 1, 0] = path[k, 0] + (c * step_x - s * step_y)
        path[k + 1, 1] = path[k, 1] + (s * step_x + c * step_y)
        heading_sum += step_theta
        path[k + 1, 2] = wrap_angle(heading_sum)
        alpha = path[k, 2] + h
        ca, sa = math.cos(alpha), math.sin(alpha)
        dd_dw = v * dt * dsinc * 0.5 * dt
        f00, f01 = dt * sinc * ca, dd_dw * ca - chord * sa * 0.5 * dt
        f10, f11 = dt * sinc * sa, dd_dw * sa + chord * ca * 0.5 * dt
        f20, f21 = 0.0, dt
        g[k, 0, 0], g[k, 0, 1] = f00 * j00 + f01 * j10, f00 * j01 + f01 * j11
        g[k, 1, 0], g[k, 1, 1] = f10 * j00 + f11 * j10, f10 * j01 + f11 * j11
        g[k, 2, 0], g[k, 2, 1] = f20 * j00 + f21 * j10, f20 * j01 + f21 * j11
    end = path[count].copy()
    cov = np.zeros((3, 3))
    for k in range(count):
        lever_x, lever_y = -(end[1] - path[k + 1, 1]), end[0] - path[k + 1, 0]
        m = np.empty((3, 2))
        for col in range(2):
            m[0, col] = g[k, 0, col] + lever_x * g[k, 2, col]
            m[1, col] = g[k, 1, col] + lever_y * g[k, 2, col]
            m[2, col] = g[k, 2, col]
        for i in range(3):
            t0 = m[i, 0] * covs[k, 0, 0] + m[i, 1] * covs[k, 1, 0]
            t1 = m[i, 0] * covs[k, 0, 1] + m[i, 1] * covs[k, 1, 1]
            for j in range(3):
                cov[i, j] += t0 * m[j, 0] + t1 * m[j, 1]
    for i in range(3):
        for j in range(i + 1, 3):
            half = 0.5 * (cov[i, j] + cov[j, i])
            cov[i, j] = cov[j, i] = half
    return end, cov


def integrate_controls(model, controls: np.ndarray, dts: np.ndarray, covs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`robots.models.integrate_controls` by the kernel, for the unicycle and Ackermann models."""
    if isinstance(model, AckermannModel):
        ackermann, wheelbase, offset = True, float(model.wheelbase), float(model.encoder_offset)
    elif isinstance(model, UnicycleModel):
        ackermann, wheelbase, offset = False, 1.0, 0.0
    else:
        raise TypeError(f"no kernel for the motion model {model!r}")
    return integrate_controls_kernel(ackermann, wheelbase, offset, np.asarray(controls, float).reshape(-1, 2),
                                     np.asarray(dts, float).ravel(), np.asarray(covs, float).reshape(-1, 2, 2))


def warm_up() -> None:
    """Compile (or load from the cache) the kernel for both motion models on tiny inputs."""
    for model in (UnicycleModel(), AckermannModel()):
        integrate_controls(model, np.array([[1.0, 0.1]]), np.array([0.1]), np.eye(2)[None] * 0.01)


__all__ = ["integrate_controls", "integrate_controls_kernel", "warm_up"]
