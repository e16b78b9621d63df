"""Prediction over a batch of controls, drawn once per interval.

The filter only ever looks at a robot's pose when that robot's scan arrives,
so it needs p(x_end | x_start, u_1..u_K), not every pose in between. With the
controls' noise Gaussian and independent, and each step linearised about the
noise-free path, x_end = x_start ⊕ Δ with Δ ~ N(Δ̄, Σ_Δ), where

- Δ̄ is the noise-free relative motion (the K exact arcs of ``robots.models``
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

from __future__ import annotations

import numpy as np

from robots.models import MotionModel, rotation, se2_accumulate


def integrate_controls(model: MotionModel, controls: np.ndarray, dts: np.ndarray, covs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Δ̄ ``(3,)``, Σ_Δ ``(3, 3)``) of controls ``(K, 2)`` applied for ``dts`` ``(K,)`` with covariances ``(K, 2, 2)``."""
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
    jac = np.zeros(np.shape(theta) + (3, 3))
    jac[..., :2, :2] = rotation(theta)
    jac[..., 2, 2] = 1.0
    return jac
