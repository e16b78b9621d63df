"""The numeric helpers every filter shares: closed-form Gaussian algebra on stacks of 2-vectors and 2×2
matrices, a PSD square root, systematic resampling and the EKF-SLAM state operations (predict, update,
augment). One copy, imported by FastSLAM, D-SLAM, the EKF baseline and MCL."""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import scipy.special

from robots.models import wrap_angle

LOG_2PI = float(np.log(2.0 * np.pi))


@lru_cache(maxsize=256)
def chi2_quantile(probability: float, dof: int) -> float:
    """The chi-square quantile ε with P(τ ≤ ε) = ``probability`` for ``dof`` degrees of freedom (9.21 for 0.99 and
    2 dof): every association gate. Through ``scipy.special`` (``scipy.stats`` takes half a second to import)."""
    return float(scipy.special.chdtri(dof, 1.0 - probability))


@lru_cache(maxsize=64)
def diagonal_variances(sigmas: tuple[float, ...]) -> np.ndarray:
    """diag(σ²) of the standard deviations ``sigmas`` (a configuration's tuple), built once per tuple: shared, so
    read-only."""
    out = np.diag(np.square(sigmas))
    out.flags.writeable = False
    return out


def inv2(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(inverse, determinant) of a stack of 2×2 matrices ``(..., 2, 2)``."""
    a, b, c, d = s[..., 0, 0], s[..., 0, 1], s[..., 1, 0], s[..., 1, 1]
    det = a * d - b * c
    safe = np.where(np.abs(det) > 1e-300, det, 1e-300)
    inv = np.empty_like(s)
    inv[..., 0, 0], inv[..., 0, 1] = d / safe, -b / safe
    inv[..., 1, 0], inv[..., 1, 1] = -c / safe, a / safe
    return inv, det


def quad2(nu: np.ndarray, s_inv: np.ndarray) -> np.ndarray:
    """νᵀ S⁻¹ ν for stacks ``nu (..., 2)`` and ``s_inv (..., 2, 2)`` (broadcast)."""
    n0, n1 = nu[..., 0], nu[..., 1]
    return s_inv[..., 0, 0] * n0 * n0 + (s_inv[..., 0, 1] + s_inv[..., 1, 0]) * n0 * n1 + s_inv[..., 1, 1] * n1 * n1


def sandwich(a: np.ndarray, m: np.ndarray) -> np.ndarray:
    """A M Aᵀ for stacks of matrices (broadcast)."""
    return a @ m @ np.swapaxes(a, -1, -2)


def sandwich2(a: np.ndarray, m: np.ndarray) -> np.ndarray:
    """A M Aᵀ for stacks of 2×2 matrices with M symmetric, in closed form (several times faster than matmul)."""
    a00, a01, a10, a11 = a[..., 0, 0], a[..., 0, 1], a[..., 1, 0], a[..., 1, 1]
    m00, m01, m11 = m[..., 0, 0], m[..., 0, 1], m[..., 1, 1]
    t00, t01 = a00 * m00 + a01 * m01, a00 * m01 + a01 * m11
    t10, t11 = a10 * m00 + a11 * m01, a10 * m01 + a11 * m11
    out = np.empty(np.broadcast_shapes(a.shape, m.shape))
    out[..., 0, 0] = t00 * a00 + t01 * a01
    out[..., 0, 1] = out[..., 1, 0] = t00 * a10 + t01 * a11
    out[..., 1, 1] = t10 * a10 + t11 * a11
    return out


def ellipse_outlines(means: np.ndarray, covs: np.ndarray, probability: float = 0.95, points: int = 36) -> np.ndarray:
    """Closed outlines ``(n, points, 2)`` of the ``probability`` confidence ellipses of 2-D Gaussians (a covariance
    that is not positive semi-definite is clipped to its non-negative part): for plots and viewers."""
    from scipy.stats import chi2  # only plots and viewers draw ellipses: the filters need not load scipy.stats

    scale = math.sqrt(chi2.ppf(probability, 2))
    values, vectors = np.linalg.eigh(0.5 * (covs + np.swapaxes(covs, -1, -2)))
    radii = scale * np.sqrt(np.clip(values, 0.0, None))
    angle = np.linspace(0.0, 2 * math.pi, points)
    circle = np.stack([np.cos(angle), np.sin(angle)], -1)
    return means[:, None, :] + np.einsum("nij,nj,pj->npi", vectors, radii, circle)


def valid_cov2(cov: np.ndarray) -> bool:
    """True for a finite, symmetric, positive semi-definite 2×2 matrix (closed form: cheap enough per message)."""
    if cov.shape != (2, 2):
        return False
    a, b, c, d = float(cov[0, 0]), float(cov[0, 1]), float(cov[1, 0]), float(cov[1, 1])
    finite = math.isfinite(a) and math.isfinite(b) and math.isfinite(c) and math.isfinite(d)
    return finite and abs(b - c) <= 1e-9 + 1e-6 * abs(b) and a >= 0 and d >= 0 and a * d - b * c >= -1e-12 * max(a * d, 1e-300)


def valid_cov3(cov: np.ndarray) -> bool:
    """A finite, symmetric, positive semi-definite 3×3 covariance."""
    return (cov.shape == (3, 3) and bool(np.all(np.isfinite(cov))) and np.allclose(cov, cov.T, atol=1e-9, rtol=1e-6)
            and bool(np.all(np.linalg.eigvalsh(cov) >= -1e-12)))


def valid_placement(pose: np.ndarray, cov: np.ndarray, stamp: float | None = None) -> bool:
    """A finite pose ``(3,)`` with a valid 3×3 covariance (:func:`valid_cov3`), at a finite ``stamp`` if one is
    given: what an estimator accepts to place a robot."""
    return (pose.shape == (3,) and bool(np.all(np.isfinite(pose))) and valid_cov3(cov)
            and (stamp is None or math.isfinite(stamp)))


def sqrt_psd(cov: np.ndarray) -> np.ndarray:
    """A matrix L with L Lᵀ = cov for a symmetric positive semi-definite ``cov`` (stacks allowed).

    Cholesky when ``cov`` is positive definite, else an eigen-decomposition (robust to rank loss).
    """
    try:
        return np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        pass
    values, vectors = np.linalg.eigh(0.5 * (cov + np.swapaxes(cov, -1, -2)))
    return vectors * np.sqrt(np.clip(values, 0.0, None))[..., None, :]


def systematic_resample(weights: np.ndarray, count: int, rng: np.random.Generator | None,
                        offset: float | None = None) -> np.ndarray:
    """``count`` indices drawn by systematic (low-variance) resampling of ``weights`` (one uniform offset, equal
    steps); the weights need not be normalised (all-zero weights draw uniformly). A fixed ``offset`` in [0, 1)
    replaces the random one (no draw from ``rng``)."""
    weights = np.asarray(weights, float)
    total = weights.sum()
    if count <= 0 or weights.size == 0:
        return np.zeros(0, np.int64)
    cdf = np.cumsum(weights / total) if total > 0 else np.arange(1, weights.size + 1) / weights.size
    cdf[-1] = 1.0
    points = ((rng.random() if offset is None else offset) + np.arange(count)) / count
    return np.minimum(np.searchsorted(cdf, points, side="right"), weights.size - 1)


def ekf_predict_pose(x: np.ndarray, P: np.ndarray, model, control, control_cov, dt: float) -> None:
    """EKF-SLAM prediction in place: the pose x[:3] moves by one control of ``model``; the landmarks stay."""
    f_pose, f_control = model.jacobians(x[:3], control, dt)
    x[:3] = model.step(x[:3], control, dt)
    P[:3, :] = f_pose @ P[:3, :]
    P[:, :3] = P[:, :3] @ f_pose.T
    P[:3, :3] += f_control @ np.asarray(control_cov, float) @ f_control.T


def turn_slip(var_per_rad: float, turn: float) -> float:
    """Heading variance a turn of ``turn`` rad adds beyond the control noise: ``var_per_rad`` per radian turned
    (``RobotInfo.turn_slip_var``). Wheels slip in turns, so odometry's heading error grows with the angle turned,
    not only with time: on MR.CLAM 0.013–0.015 rad² per rad over 1–30 s windows of all five robots, where σ_ω alone
    leaves 28 % of the turning windows outside 3σ."""
    if var_per_rad <= 0.0:
        return 0.0
    return var_per_rad * abs(math.remainder(float(turn), 2.0 * math.pi))


def block_diagonal(blocks: np.ndarray) -> np.ndarray:
    """The block-diagonal matrix of ``blocks`` ``(n, a, b)``: ``(n·a, n·b)``, as ``scipy.linalg.block_diag(*blocks)``
    builds it, without its per-call checks (they cost more than the update itself, once per scan)."""
    blocks = np.asarray(blocks, float)
    n, a, b = blocks.shape
    out = np.zeros((n * a, n * b))
    index = np.arange(n)
    out.reshape(n, a, n, b)[index, :, index, :] = blocks
    return out


def ekf_update(x: np.ndarray, P: np.ndarray, nu: np.ndarray, h: np.ndarray, r: np.ndarray,
               angle_index: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """One batch EKF update in Joseph form: (x, P) after innovations ``nu`` with Jacobian ``h`` and noise ``r``."""
    gain, P = _joseph(P, h, r)
    x = x + gain @ nu
    x[angle_index] = wrap_angle(x[angle_index])
    return x, P


def ekf_covariance_update(P: np.ndarray, h: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The covariance of :func:`ekf_update` alone (the same arithmetic), for a covariance tracked without a mean."""
    return _joseph(P, h, r)[1]


def _joseph(P: np.ndarray, h: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Kalman gain, covariance after the update in Joseph form, symmetrised)."""
    ph = P @ h.T
    gain = np.linalg.solve(h @ ph + r, ph.T).T
    i_kh = np.eye(P.shape[0]) - gain @ h
    P = i_kh @ P @ i_kh.T + gain @ r @ gain.T
    return gain, 0.5 * (P + P.T)


def ekf_augment(x: np.ndarray, P: np.ndarray, sensor, z: np.ndarray, noise: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(x, P) grown by the landmark seen as ``z`` from the pose x[:3], with its cross-covariance to the state."""
    g_pose, g_z = sensor.inverse_jacobians(x[:3], z)
    cross = g_pose @ P[:3, :]
    d = x.shape[0]
    grown = np.zeros((d + 2, d + 2))
    grown[:d, :d] = P
    grown[d:, :d] = cross
    grown[:d, d:] = cross.T
    grown[d:, d:] = g_pose @ P[:3, :3] @ g_pose.T + g_z @ noise @ g_z.T
    return np.concatenate([x, sensor.inverse(x[:3], z)]), grown
