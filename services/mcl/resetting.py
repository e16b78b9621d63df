"""Sensor resetting (Lenser & Veloso 2000; Sehestedt and Schneider, "Monte Carlo Localization in Highly
Symmetric Environments", §3.1, §4.2): poses drawn from a scan and the map.

Two observations fix a pose once they are matched to two landmarks: the
distance between the observed points (in the robot frame) must equal the
distance between the landmarks, and aligning the one segment onto the other
gives the heading and the position. A draw picks a random pair of
observations and a random pair of landmarks whose distance agrees within
the noise (from a table of landmark pairs sorted by distance). With one
observation the robot lies on a circle around a random landmark; with none,
anywhere in the map's bounding box. The poses get a small jitter.

The caller weighs the candidates by the full scan likelihood and keeps the
best-supported ones: that is sampling from p(y | x) over the map.

The geometry of the draws (the pair windows, the aligned poses, the one-point
check) runs in numba kernels (:mod:`services.mcl.kernels`); the numpy code
here is their reference, and both take the same random draws in the same order.
"""

from __future__ import annotations

import math

import numpy as np

from robots.models import rotation, transform_points, wrap_angle
from services.mcl import kernels
from services.mcl.likelihood import LandmarkMap, ScanModel


def uniform_poses(lmap: LandmarkMap, count: int, margin: float, rng: np.random.Generator) -> np.ndarray:
    """``count`` poses uniform over the map's bounding box (grown by ``margin``) and every heading."""
    low, high = lmap.bounds(margin)
    xy = rng.uniform(low, high, size=(count, 2))
    return np.column_stack([xy, rng.uniform(-math.pi, math.pi, count)])


def poses_from_scan(observations: np.ndarray, lmap: LandmarkMap, model: ScanModel, count: int, pair_sigmas: float,
                    jitter_xy: float, jitter_theta: float, margin: float, rng: np.random.Generator,
                    draws: int = 1, compiled: bool = True) -> np.ndarray:
    """``count`` candidate poses ``(count, 3)`` consistent with (parts of) the scan and the map.

    With ``draws`` > 1 and at least three observations, ``draws`` times as many
    poses are drawn and those under which one more random observation also
    lands on a landmark come first (a one-point check, as in RANSAC): the wrong
    pair matches of a dense or regular map rarely pass it. ``compiled``: the
    geometry by the numba kernels (:mod:`services.mcl.kernels`), with the same
    random draws as this numpy reference, so the poses agree to rounding.
    """
    z = np.asarray(observations, float).reshape(-1, 2)
    n = z.shape[0]
    if n == 0 or lmap.count == 0:
        return uniform_poses(lmap, count, margin, rng)
    points = model.sensor.inverse(np.zeros(3), z)  # observed points in the robot frame (n, 2)
    total = count * draws if n >= 3 else count
    if compiled and kernels.AVAILABLE:
        poses = _checked_poses_compiled(z, points, lmap, model, total, count, pair_sigmas, rng)
    else:
        poses = _aligned_poses(z, points, lmap, model, total, pair_sigmas, rng)
        if total > count:
            ends = transform_points(poses, points[rng.integers(n, size=total)])
            nearest = lmap.padded[lmap.match_index.lookup(ends)] - ends[:, None, :]
            hit = np.min(np.hypot(nearest[..., 0], nearest[..., 1]), axis=1) <= model.match_radius()
            poses = poses[_shuffled_hits_first(hit, rng)[:count]]
    poses[:, :2] += rng.normal(0.0, jitter_xy, size=(count, 2))
    poses[:, 2] = wrap_angle(poses[:, 2] + rng.normal(0.0, jitter_theta, size=count))
    return poses


def _shuffled_hits_first(hit: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Indices in random order, those with ``hit`` first."""
    order = rng.permutation(hit.size)
    return order[np.argsort(~hit[order], kind="stable")]


def _checked_poses_compiled(z: np.ndarray, points: np.ndarray, lmap: LandmarkMap, model: ScanModel, total: int,
                            count: int, pair_sigmas: float, rng: np.random.Generator) -> np.ndarray:
    """``count`` of ``total`` aligned poses, those passing the one-point check first (when ``total`` > ``count``):
    :func:`_aligned_poses` and the check of :func:`poses_from_scan` by the kernels, drawing the same random numbers
    in the same order."""
    n = z.shape[0]
    first = rng.integers(n, size=total)
    second, lo, hi, pick_u = first, np.zeros(total, np.int64), np.zeros(total, np.int64), np.zeros(0)
    if n >= 2 and lmap.pair_distance.size:
        second = (first + rng.integers(1, n, size=total)) % n
        lo, hi = kernels.pair_windows_kernel(points, _point_variance(z, model), first, second, lmap.pair_distance,
                                             pair_sigmas)
        pick_u = rng.random(int(np.count_nonzero(hi > lo)))
    singles = total - pick_u.size
    single_theta, single_anchor = np.zeros(0), np.zeros(0, np.int64)
    if singles:
        single_theta = rng.uniform(-math.pi, math.pi, singles)
        single_anchor = rng.integers(lmap.count, size=singles)
    check = rng.integers(n, size=total) if total > count else np.zeros(0, np.int64)
    index = lmap.match_index
    poses, hit = kernels.candidate_poses_kernel(
        points, first, second, lo, hi, pick_u, lmap.pair_first, lmap.pair_second, lmap.landmarks, single_theta,
        single_anchor, check, lmap.padded, index.table, index.origin, index.cell, index.shape[0], index.shape[1],
        model.match_radius())
    if total > count:
        poses = poses[_shuffled_hits_first(hit, rng)[:count]]
    return poses


def _aligned_poses(z: np.ndarray, points: np.ndarray, lmap: LandmarkMap, model: ScanModel, count: int,
                   pair_sigmas: float, rng: np.random.Generator) -> np.ndarray:
    """Poses that put two random observations on two landmarks as far apart (one observation: on a circle)."""
    n = z.shape[0]
    point_var = _point_variance(z, model)
    poses = np.empty((count, 3))
    paired = np.zeros(count, bool)
    first = rng.integers(n, size=count)
    if n >= 2 and lmap.pair_distance.size:
        second = (first + rng.integers(1, n, size=count)) % n
        seen = np.linalg.norm(points[second] - points[first], axis=-1)
        tolerance = pair_sigmas * np.sqrt(point_var[first] + point_var[second])
        lo = np.searchsorted(lmap.pair_distance, seen - tolerance, side="left")
        hi = np.searchsorted(lmap.pair_distance, seen + tolerance, side="right")
        paired = hi > lo
        pick = lo[paired] + np.floor(rng.random(int(paired.sum())) * (hi - lo)[paired]).astype(np.int64)
        a, b = lmap.landmarks[lmap.pair_first[pick]], lmap.landmarks[lmap.pair_second[pick]]
        qa, qb = points[first[paired]], points[second[paired]]
        theta = np.arctan2(b[:, 1] - a[:, 1], b[:, 0] - a[:, 0]) - np.arctan2(qb[:, 1] - qa[:, 1], qb[:, 0] - qa[:, 0])
        poses[paired, :2] = a - np.einsum("nij,nj->ni", rotation(theta), qa)
        poses[paired, 2] = theta
    single = ~paired
    k = int(single.sum())
    if k:
        theta = rng.uniform(-math.pi, math.pi, k)
        anchor = lmap.landmarks[rng.integers(lmap.count, size=k)]
        poses[single, :2] = anchor - np.einsum("nij,nj->ni", rotation(theta), points[first[single]])
        poses[single, 2] = theta
    poses[:, 2] = wrap_angle(poses[:, 2])
    return poses


def _point_variance(z: np.ndarray, model: ScanModel) -> np.ndarray:
    """The variance ``(n,)`` of each observed point's position along any direction, at most: σ_r² + (r σ_φ)²."""
    sigma_r, sigma_b = np.sqrt(np.diag(model.noise_cov))
    return sigma_r**2 + (z[:, 0] * sigma_b) ** 2
