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
here is their reference. The random draws are taken in one place
(:func:`_checked_poses`), the same for both.
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
    poses = _checked_poses(z, points, lmap, model, total, count, pair_sigmas, rng, compiled and kernels.AVAILABLE)
    poses[:, :2] += rng.normal(0.0, jitter_xy, size=(count, 2))
    poses[:, 2] = wrap_angle(poses[:, 2] + rng.normal(0.0, jitter_theta, size=count))
    return poses


def _shuffled_hits_first(hit: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Indices in random order, those with ``hit`` first."""
    order = rng.permutation(hit.size)
    return order[np.argsort(~hit[order], kind="stable")]


def _checked_poses(z: np.ndarray, points: np.ndarray, lmap: LandmarkMap, model: ScanModel, total: int, count: int,
                   pair_sigmas: float, rng: np.random.Generator, compiled: bool) -> np.ndarray:
    """``count`` of ``total`` aligned poses (:func:`_aligned_poses`), those passing the one-point check first (when
    ``total`` > ``count``). The random draws are taken here, in one order for both ways of doing the geometry: by
    the kernels (``compiled``) or by the numpy reference."""
    n = z.shape[0]
    first = rng.integers(n, size=total)
    second, lo, hi, pick_u = first, np.zeros(total, np.int64), np.zeros(total, np.int64), np.zeros(0)
    if n >= 2 and lmap.pair_distance.size:
        second = (first + rng.integers(1, n, size=total)) % n
        windows = kernels.pair_windows_kernel if compiled else _pair_windows
        lo, hi = windows(points, _point_variance(z, model), first, second, lmap.pair_distance, pair_sigmas)
        pick_u = rng.random(int(np.count_nonzero(hi > lo)))
    singles = total - pick_u.size
    single_theta, single_anchor = np.zeros(0), np.zeros(0, np.int64)
    if singles:
        single_theta = rng.uniform(-math.pi, math.pi, singles)
        single_anchor = rng.integers(lmap.count, size=singles)
    check = rng.integers(n, size=total) if total > count else np.zeros(0, np.int64)
    if compiled:
        index = lmap.match_index
        poses, hit = kernels.candidate_poses_kernel(
            points, first, second, lo, hi, pick_u, lmap.pair_first, lmap.pair_second, lmap.landmarks, single_theta,
            single_anchor, check, lmap.padded, index.table, index.origin, index.cell, index.shape[0], index.shape[1],
            model.match_radius())
    else:
        poses = _aligned_poses(points, first, second, lo, hi, pick_u, single_theta, single_anchor, lmap)
        hit = _lands_on_landmark(poses, points, check, lmap, model) if check.size else np.zeros(total, bool)
    if total > count:
        poses = poses[_shuffled_hits_first(hit, rng)[:count]]
    return poses


def _pair_windows(points: np.ndarray, point_var: np.ndarray, first: np.ndarray, second: np.ndarray,
                  pair_distance: np.ndarray, pair_sigmas: float) -> tuple[np.ndarray, np.ndarray]:
    """For each draw, the window [lo, hi) of the landmark pairs (sorted by distance) as far apart as its observed
    points ``first`` and ``second``, within ``pair_sigmas`` standard deviations (the reference of
    :func:`services.mcl.kernels.pair_windows_kernel`)."""
    seen = np.linalg.norm(points[second] - points[first], axis=-1)
    tolerance = pair_sigmas * np.sqrt(point_var[first] + point_var[second])
    return (np.searchsorted(pair_distance, seen - tolerance, side="left"),
            np.searchsorted(pair_distance, seen + tolerance, side="right"))


def _aligned_poses(points: np.ndarray, first: np.ndarray, second: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                   pick_u: np.ndarray, single_theta: np.ndarray, single_anchor: np.ndarray,
                   lmap: LandmarkMap) -> np.ndarray:
    """Poses that put two observations (``first``, ``second``) on a pair of landmarks as far apart, the pair at
    ``lo + ⌊u·(hi − lo)⌋`` of the draw's window; a draw without a window puts its first observation on the landmark
    ``single_anchor`` at heading ``single_theta`` (a circle round it). The reference of
    :func:`services.mcl.kernels.candidate_poses_kernel`."""
    poses = np.empty((first.size, 3))
    paired = hi > lo
    if pick_u.size:
        pick = np.minimum(lo[paired] + np.floor(pick_u * (hi - lo)[paired]).astype(np.int64), hi[paired] - 1)
        a, b = lmap.landmarks[lmap.pair_first[pick]], lmap.landmarks[lmap.pair_second[pick]]
        qa, qb = points[first[paired]], points[second[paired]]
        theta = np.arctan2(b[:, 1] - a[:, 1], b[:, 0] - a[:, 0]) - np.arctan2(qb[:, 1] - qa[:, 1], qb[:, 0] - qa[:, 0])
        poses[paired, :2] = a - np.einsum("nij,nj->ni", rotation(theta), qa)
        poses[paired, 2] = theta
    if single_theta.size:
        single = ~paired
        anchor = lmap.landmarks[single_anchor]
        poses[single, :2] = anchor - np.einsum("nij,nj->ni", rotation(single_theta), points[first[single]])
        poses[single, 2] = single_theta
    poses[:, 2] = wrap_angle(poses[:, 2])
    return poses


def _lands_on_landmark(poses: np.ndarray, points: np.ndarray, check: np.ndarray, lmap: LandmarkMap,
                       model: ScanModel) -> np.ndarray:
    """Whether the observed point ``check`` of each pose lands within the match radius of a landmark (the one-point
    check)."""
    ends = transform_points(poses, points[check])
    nearest = lmap.padded[lmap.match_index.lookup(ends)] - ends[:, None, :]
    return np.min(np.hypot(nearest[..., 0], nearest[..., 1]), axis=1) <= model.match_radius()


def _point_variance(z: np.ndarray, model: ScanModel) -> np.ndarray:
    """The variance ``(n,)`` of each observed point's position along any direction, at most: σ_r² + (r σ_φ)²."""
    sigma_r, sigma_b = np.sqrt(np.diag(model.noise_cov))
    return sigma_r**2 + (z[:, 0] * sigma_b) ** 2
