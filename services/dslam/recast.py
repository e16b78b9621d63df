"""The recast measurement of D-SLAM (Wang, Huang, Dissanayake,
"Implementation Issues and Experimental Evaluation of D-SLAM", eqs. 3, 4, 7, 8).

A scan of m range-bearing observations is turned into points in the sensor
frame (eq. 4); the part of the scan that does not depend on the robot, z_map,
is made of distances and angles among those points (eq. 3):

    z_map = [d_12, α_312, d_13, α_412, d_14, ..., α_m12, d_1m]

with f1 the anchor and f2 the second reference feature. z_map is invariant
under shift and rotation, so the same function of the absolute landmark
positions is the mapping measurement model H_map(X) (eq. 8). Its covariance
R_map comes from the Jacobian of the recasting at the measured values.

Rows of z_map: row 0 is d_12; for the k-th other feature (k = 1, 2, ...) row
2k-1 is the angle α_k12 and row 2k the distance d_1k.
"""

from __future__ import annotations

import numpy as np

from robots.models import wrap_angle


def angle_rows(size: int) -> np.ndarray:
    """Mask of the angle rows of a z_map vector of ``size`` = 2m-3 rows."""
    rows = np.arange(size)
    return (rows % 2 == 1)


def map_measurement(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """z_map of ``points`` (m, 2) ordered [f1, f2, others...] and its Jacobian (2m-3, m, 2).

    This is H_map (eq. 8) when the points are absolute landmark positions, and
    the recasting of eq. 3 when they are the scan's points in the sensor frame.
    """
    points = np.asarray(points, float)
    m = points.shape[0]
    if m < 2:
        raise ValueError("z_map needs at least two features")
    size = 2 * m - 3
    z = np.empty(size)
    jac = np.zeros((size, m, 2))
    base = points[1] - points[0]
    base_sq = float(base @ base)
    base_len = np.sqrt(base_sq)
    z[0] = base_len
    jac[0, 1] = base / base_len
    jac[0, 0] = -base / base_len
    if m > 2:
        rel = points[2:] - points[0]  # (m-2, 2)
        rel_sq = np.einsum("ij,ij->i", rel, rel)
        rel_len = np.sqrt(rel_sq)
        k = np.arange(m - 2)
        angle_row, dist_row = 2 * k + 1, 2 * k + 2
        z[angle_row] = wrap_angle(np.arctan2(rel[:, 1], rel[:, 0]) - np.arctan2(base[1], base[0]))
        z[dist_row] = rel_len
        d_rel = np.stack([-rel[:, 1], rel[:, 0]], -1) / rel_sq[:, None]  # d atan2(rel) / d rel
        d_base = np.array([-base[1], base[0]]) / base_sq  # d atan2(base) / d base
        jac[angle_row, k + 2] = d_rel
        jac[angle_row, 1] = -d_base
        jac[angle_row, 0] = -d_rel + d_base
        jac[dist_row, k + 2] = rel / rel_len[:, None]
        jac[dist_row, 0] = -rel / rel_len[:, None]
    return z, jac


def scan_points(observations: np.ndarray, noise: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points (m, 2) in the sensor frame (eq. 4) and their covariances (m, 2, 2).

    ``noise`` is the covariance of one (range, bearing) pair, (2, 2) or (m, 2, 2).
    """
    observations = np.asarray(observations, float)
    r, phi = observations[:, 0], observations[:, 1]
    c, s = np.cos(phi), np.sin(phi)
    points = np.stack([r * c, r * s], -1)
    jac = np.empty((r.shape[0], 2, 2))
    jac[:, 0, 0], jac[:, 0, 1] = c, -r * s
    jac[:, 1, 0], jac[:, 1, 1] = s, r * c
    noise = np.broadcast_to(np.asarray(noise, float), (r.shape[0], 2, 2))
    return points, jac @ noise @ np.swapaxes(jac, -1, -2)


def recast(observations: np.ndarray, noise: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(z_map, R_map) of observations (m, 2) ordered [f1, f2, others...] (eqs. 3, 4).

    R_map = J diag(C_i) Jᵀ, with J the Jacobian of z_map with respect to the
    points and C_i the covariance of point i, all at the measured values.
    """
    points, point_covs = scan_points(observations, noise)
    m = points.shape[0]
    joint = np.zeros((m, 2, m, 2))
    joint[np.arange(m), :, np.arange(m), :] = point_covs
    return recast_points(points, joint.reshape(2 * m, 2 * m))


def recast_points(points: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(z_map, R_map) of points (m, 2) ordered [f1, f2, others...] with joint covariance ``cov`` (2m, 2m).

    The points may come from one scan (independent) or from a local map built
    over several scans (correlated through the robot's motion): z_map is
    invariant under shift and rotation, so any frame will do.
    """
    z, jac = map_measurement(points)
    jac = jac.reshape(jac.shape[0], -1)
    r_map = jac @ np.asarray(cov, float) @ jac.T
    return z, 0.5 * (r_map + r_map.T)


def innovation(z: np.ndarray, predicted: np.ndarray) -> np.ndarray:
    """z_map − H_map(X̂) with the angle rows wrapped to [-π, π)."""
    nu = np.asarray(z, float) - np.asarray(predicted, float)
    rows = angle_rows(nu.shape[0])
    nu[rows] = wrap_angle(nu[rows])
    return nu


def choose_reference(points: np.ndarray, candidates: np.ndarray, spread: np.ndarray | None = None) -> tuple[int, int]:
    """The best-conditioned reference pair among ``candidates`` (indices into ``points``).

    The angle noise of every α_i12 contains the direction noise of the base
    f1→f2, which falls as 1/d_12: take the candidate pair farthest apart, and as
    anchor f1 the less noisy one: smaller ``spread`` (e.g. covariance trace per
    point), by default the one nearer the sensor (points in the sensor frame).
    """
    candidates = np.asarray(candidates, int)
    if candidates.shape[0] < 2:
        raise ValueError("a reference pair needs two mapped features")
    p = points[candidates]
    gaps = np.linalg.norm(p[:, None, :] - p[None, :, :], axis=-1)
    a, b = np.unravel_index(int(np.argmax(gaps)), gaps.shape)
    first, second = int(candidates[a]), int(candidates[b])
    spread = np.linalg.norm(points, axis=1) if spread is None else np.asarray(spread, float)
    if spread[second] < spread[first]:
        first, second = second, first
    return first, second


def initialise(anchor: np.ndarray, second: np.ndarray, z_new: np.ndarray) -> np.ndarray:
    """New feature positions (k, 2) from the estimates of f1, f2 and their (α_i12, d_1i) (eq. 9)."""
    z_new = np.asarray(z_new, float).reshape(-1, 2)
    alpha12 = np.arctan2(second[1] - anchor[1], second[0] - anchor[0])
    heading = alpha12 + z_new[:, 0]
    return anchor + z_new[:, 1:2] * np.stack([np.cos(heading), np.sin(heading)], -1)
