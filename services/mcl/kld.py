"""KLD-sampling (Fox 2003; eq. 2 of Sehestedt and Schneider, "Monte Carlo Localization in Highly
Symmetric Environments"): how many samples the posterior needs.

With k bins of a fixed grid over (x, y, θ) holding at least one sample, the
number of samples that keeps the Kullback-Leibler distance between the sample
approximation and the true (piecewise constant) posterior below ε with
probability 1 − δ is

    N = (k − 1) / (2ε) · (1 − 2/(9(k − 1)) + sqrt(2/(9(k − 1))) · z_(1−δ))³,

z_(1−δ) the upper 1 − δ quantile of the standard normal distribution (2.326
for δ = 0.01) — the quantile, not δ itself.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.special


def normal_quantile(delta: float) -> float:
    """z_(1−δ): the upper 1 − δ quantile of the standard normal distribution."""
    return float(scipy.special.ndtri(1.0 - delta))


def kld_sample_size(bins, epsilon: float, delta: float) -> np.ndarray:
    """Eq. 2 for ``bins`` (k, scalar or array); 0 where k ≤ 1 (one bin needs no spread)."""
    k = np.asarray(bins, float)
    dof = np.maximum(k - 1.0, 1.0)
    a = 2.0 / (9.0 * dof)
    size = dof / (2.0 * epsilon) * (1.0 - a + np.sqrt(a) * normal_quantile(delta)) ** 3
    return np.where(k > 1, np.ceil(size), 0.0)


def bin_keys(poses: np.ndarray, bin_xy: float, bin_theta: float) -> np.ndarray:
    """One integer key ``(P,)`` per pose: its cell of the KLD grid."""
    poses = np.asarray(poses, float)
    ix = np.floor(poses[:, 0] / bin_xy).astype(np.int64)
    iy = np.floor(poses[:, 1] / bin_xy).astype(np.int64)
    turns = int(math.ceil(2 * math.pi / bin_theta))
    it = np.mod(np.floor((poses[:, 2] + math.pi) / bin_theta).astype(np.int64), turns)
    span = 1 << 21
    return ((ix + span // 2) * span + (iy + span // 2)) * turns + it


def support(poses: np.ndarray, bin_xy: float, bin_theta: float) -> int:
    """k: the number of bins holding at least one pose."""
    return int(np.unique(bin_keys(poses, bin_xy, bin_theta)).size) if len(poses) else 0


def kld_prefix_size(keys: np.ndarray, epsilon: float, delta: float, n_min: int, n_max: int) -> int:
    """Fox's sequential rule over samples in draw order: the first n with n ≥ N(k(n)), k(n) the bins of the first n."""
    keys = np.asarray(keys)[:n_max]
    if keys.size == 0:
        return n_min
    first = np.zeros(keys.size, bool)
    first[np.unique(keys, return_index=True)[1]] = True
    needed = kld_sample_size(np.cumsum(first), epsilon, delta)
    n = np.arange(1, keys.size + 1)
    done = np.flatnonzero((n >= needed) & (n >= n_min))
    return int(n[done[0]]) if done.size else int(keys.size)
