"""Particle weights: normalised weights, effective sample size, systematic resampling, the best particle and the
weighted mean pose."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from robots.gaussian import systematic_resample
from robots.models import wrap_angle

if TYPE_CHECKING:
    from central.fastslam.association import ScanState
    from central.fastslam.core import FastSlam


def weights(logw: np.ndarray) -> np.ndarray:
    """Normalised weights of log-weights ``logw`` (uniform when none is finite)."""
    top = logw.max(initial=-np.inf)
    if np.isfinite(top):  # the common case, in three array operations: exp(−∞ − top) is already 0
        w = np.exp(logw - top)
        return w / w.sum()
    finite = np.isfinite(logw)
    if not finite.any():
        return np.full(logw.size, 1.0 / logw.size)
    w = np.where(finite, np.exp(logw - logw[finite].max()), 0.0)
    return w / w.sum()


def weighted_heading(headings: np.ndarray, w: np.ndarray) -> float:
    """The circular mean of particle ``headings`` ``(P,)`` with weights ``w``."""
    return float(np.arctan2(w @ np.sin(headings), w @ np.cos(headings)))


def weighted_pose(poses: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mean, covariance) of particle poses ``(P, 3)`` with weights ``w``: circular mean heading, residual
    headings wrapped."""
    theta = weighted_heading(poses[:, 2], w)
    mean = np.array([w @ poses[:, 0], w @ poses[:, 1], theta])
    resid = poses - mean
    resid[:, 2] = wrap_angle(resid[:, 2])
    return mean, np.einsum("p,pi,pj->ij", w, resid, resid)


def effective_particles(slam: FastSlam) -> float:
    """Effective sample size 1 / Σ w²."""
    w = slam.weights()
    return float(1.0 / (w * w).sum())


def select(slam: FastSlam, index: np.ndarray, scan: ScanState | None = None) -> None:
    """Keep particles ``index`` (with repetition), and the scan's bookkeeping with them."""
    slam.pose = slam.pose[index]
    slam.turn_gain = slam.turn_gain[index]
    slam.logw = slam.logw[index]
    slam.map.select(index)
    if scan is not None:
        scan.select(index)


def resample(slam: FastSlam, count: int, scan: ScanState | None = None) -> None:
    """Systematic resampling to ``count`` equally weighted particles (remembering where the heaviest went)."""
    w = slam.weights()
    index = systematic_resample(w, count, slam.rng)
    best = int(np.argmax(w))
    select(slam, index, scan)
    slam.logw = np.zeros(count)
    hits = np.flatnonzero(index == best)
    slam.best_hint = int(hits[0]) if hits.size else 0
    slam.counts["resamples"] += 1


def normalise_and_resample(slam: FastSlam) -> None:
    """Shift the log-weights to a maximum of 0; resample to N when the effective sample size falls below
    ``resample_ess``·N. Weights that are all zero (no finite log-weight) are reset to uniform (counted)."""
    top = slam.logw.max()
    if math.isfinite(top):  # the common case: no NaN nor +∞, and −∞ − top stays −∞
        slam.logw = slam.logw - top
    else:
        finite = np.isfinite(slam.logw)
        if not finite.any():
            slam.logw = np.zeros(slam.logw.size)
            slam.counts["degenerate_weights"] += 1
            return
        slam.logw = np.where(finite, slam.logw - slam.logw[finite].max(), -np.inf)
    if effective_particles(slam) < slam.config.resample_ess * slam.logw.size:
        resample(slam, slam.config.particles)


def best_particle(slam: FastSlam) -> int:
    """The highest-weight particle (after a resampling: a child of the heaviest particle before it)."""
    w = slam.weights()
    if w.max() - w.min() < 1e-12:
        return min(slam.best_hint, w.size - 1)
    return int(np.argmax(w))
