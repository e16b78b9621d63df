"""Compiled (numba) kernels of MCL: the scan likelihood (:mod:`services.mcl.likelihood` keeps the numpy
reference), the merging of grid cells into clusters (:mod:`services.mcl.clustering` keeps the scipy one) and the
candidate poses of sensor resetting (:mod:`services.mcl.resetting` keeps the numpy reference).

One loop per particle does what the vectorised reference does with (P, n, K)
temporaries: the observed points carried to the world, the best of the
candidate landmarks of each point's grid cell by the ray-frame innovation,
the Gaussian-plus-clutter-floor log-likelihood, and the negative information
(landmarks predicted well inside the view that no observation matched). It
computes in double precision (the reference in single), so the two agree to
rounding except where a point sits on a gate or view boundary.

The cell merging is a union-find over each occupied cell's 26 neighbours,
found by binary search in the sorted cell keys, instead of a sparse graph.

Compiled on first use and cached on disk (``cache=True``); :func:`warm_up`
compiles them ahead of the first scan (:mod:`services.compiled`).
"""

from __future__ import annotations

import math

import numpy as np

from robots import kernels as robot_kernels

from services.compiled import AVAILABLE, njit, wrap_angle


@njit
def _cell_row(x: float, y: float, origin: np.ndarray, cell: float, nx: int, ny: int) -> int:
    """Row of a :class:`services.mcl.likelihood.CellIndex` table for a point (clipped onto the grid)."""
    ix = int((x - origin[0]) * (1.0 / cell))
    iy = int((y - origin[1]) * (1.0 / cell))
    ix = min(max(ix, 0), nx - 1)
    iy = min(max(iy, 0), ny - 1)
    return ix * ny + iy


@njit
def scan_log_likelihood_kernel(poses, body, ranges, bearings, ux, uy, info, match_scale, floor, padded,
                               match_table, match_origin, match_cell, match_nx, match_ny,
                               view_table, view_origin, view_cell, view_nx, view_ny,
                               offset_a, offset_b, gate, far, near, half, full_circle, log_miss):
    """Log-likelihood ``(P,)`` of one scan for each pose: the kernel of
    :func:`services.mcl.likelihood._chunk_log_likelihood` (same model, same candidates). ``far``, ``near`` and
    ``half``: the range limits and half field of view less their margins (surely visible inside them)."""
    count = poses.shape[0]
    n = body.shape[0]
    out = np.empty(count)
    matched = np.empty(n, np.int64)
    cos_half = math.cos(max(half, 0.0))
    for p in range(count):
        x, y, theta = poses[p, 0], poses[p, 1], poses[p, 2]
        c, s = math.cos(theta), math.sin(theta)
        loglik = 0.0
        distinct = 0
        for j in range(n):
            ex = x + c * body[j, 0] - s * body[j, 1]
            ey = y + s * body[j, 0] + c * body[j, 1]
            row = _cell_row(ex, ey, match_origin, match_cell, match_nx, match_ny)
            best, best_m2, best_radial, best_across = -1, np.inf, 0.0, 0.0
            for k in range(match_table.shape[1]):
                landmark = match_table[row, k]
                dx = padded[landmark, 0] - ex
                dy = padded[landmark, 1] - ey
                bx = c * dx + s * dy
                by = c * dy - s * dx
                radial = bx * ux[j] + by * uy[j]
                across = (by * ux[j] - bx * uy[j]) / ranges[j]
                m2 = info[0, 0] * radial * radial + 2.0 * info[0, 1] * radial * across + info[1, 1] * across * across
                if m2 < best_m2:
                    best, best_m2, best_radial, best_across = landmark, m2, radial, across
            loglik += math.log(match_scale * math.exp(-0.5 * best_m2) + floor)
            r = ranges[j] + best_radial
            phi = bearings[j] + best_across
            inside = near <= r <= far and (full_circle or abs(phi) <= half)
            if best_m2 <= gate and inside:
                seen = False
                for i in range(distinct):
                    if matched[i] == best:
                        seen = True
                        break
                if not seen:
                    matched[distinct] = best
                    distinct += 1
        px = x + offset_a * c - offset_b * s
        py = y + offset_a * s + offset_b * c
        row = _cell_row(px, py, view_origin, view_cell, view_nx, view_ny)
        visible = 0
        for k in range(view_table.shape[1]):
            landmark = view_table[row, k]
            dx = padded[landmark, 0] - px
            dy = padded[landmark, 1] - py
            r2 = dx * dx + dy * dy
            if r2 <= far * far and r2 >= near * near:
                if full_circle or c * dx + s * dy >= math.sqrt(r2) * cos_half:
                    visible += 1
        out[p] = loglik + max(visible - distinct, 0) * log_miss
    return out


@njit
def _root(parent, i):
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@njit
def merge_cells_kernel(cells, ny, turns, steps, mean_xy, mean_theta, merge_xy, merge_theta):
    """Component ``(m,)`` of each occupied grid cell (``cells`` sorted keys (ix·ny + iy)·turns + it): a cell
    joins each neighbour (``steps`` (S, 3) offsets, heading wrapping round) whose mean pose is within
    ``merge_xy`` and ``merge_theta``; components numbered by their smallest cell, as
    ``scipy.sparse.csgraph.connected_components`` numbers them. The kernel of
    :func:`services.mcl.clustering.grid_labels`."""
    m = cells.shape[0]
    parent = np.arange(m)
    for a in range(m):
        cx = cells[a] // (ny * turns)
        rest = cells[a] - cx * ny * turns
        cy = rest // turns
        ct = rest - cy * turns
        for k in range(steps.shape[0]):
            key = ((cx + steps[k, 0]) * ny + (cy + steps[k, 1])) * turns + (ct + steps[k, 2]) % turns
            b = np.searchsorted(cells, key)
            if b >= m or cells[b] != key:
                continue
            dx = mean_xy[a, 0] - mean_xy[b, 0]
            dy = mean_xy[a, 1] - mean_xy[b, 1]
            dt = wrap_angle(mean_theta[a] - mean_theta[b])
            if math.sqrt(dx * dx + dy * dy) <= merge_xy and abs(dt) <= merge_theta:
                ra, rb = _root(parent, a), _root(parent, b)
                if ra != rb:
                    parent[max(ra, rb)] = min(ra, rb)
    component = np.empty(m, np.int64)
    label = np.full(m, -1, np.int64)
    count = 0
    for a in range(m):
        r = _root(parent, a)
        if label[r] < 0:
            label[r] = count
            count += 1
        component[a] = label[r]
    return component


@njit
def pair_windows_kernel(points, point_var, first, second, pair_distance, pair_sigmas):
    """For each draw, the window [lo, hi) of the landmark pairs (sorted by distance) whose distance agrees with that
    of its two observed points ``first``, ``second`` within ``pair_sigmas`` standard deviations: the kernel of
    :func:`services.mcl.resetting._pair_windows`, with the same arithmetic (so the same windows)."""
    count = first.shape[0]
    lo = np.empty(count, np.int64)
    hi = np.empty(count, np.int64)
    for d in range(count):
        f, g = first[d], second[d]
        dx = points[g, 0] - points[f, 0]
        dy = points[g, 1] - points[f, 1]
        seen = math.sqrt(dx * dx + dy * dy)
        tolerance = pair_sigmas * math.sqrt(point_var[f] + point_var[g])
        lo[d] = np.searchsorted(pair_distance, seen - tolerance, side="left")
        hi[d] = np.searchsorted(pair_distance, seen + tolerance, side="right")
    return lo, hi


@njit
def candidate_poses_kernel(points, first, second, lo, hi, pick_u, pair_first, pair_second, landmarks, single_theta,
                           single_anchor, check, padded, match_table, match_origin, match_cell, match_nx, match_ny,
                           match_radius):
    """Sensor resetting's candidate poses ``(T, 3)`` and, with ``check`` (one more observation per pose), whether
    that observation lands within ``match_radius`` of a landmark (``(T,)``; all False without it).

    A draw with a window of landmark pairs (hi > lo) takes the pair at ``lo + ⌊u·(hi − lo)⌋`` (``pick_u``, one
    uniform per such draw, in order) and aligns its two observed points onto it; the others put their first point
    on a landmark (``single_anchor``) at heading ``single_theta`` (in order). The kernel of
    :func:`services.mcl.resetting._aligned_poses` and its one-point check; the random draws come from the caller,
    in the reference's order."""
    count = first.shape[0]
    poses = np.empty((count, 3))
    paired_seen = 0
    single_seen = 0
    for d in range(count):
        qa_x, qa_y = points[first[d], 0], points[first[d], 1]
        if hi[d] > lo[d]:
            pick = min(lo[d] + int(math.floor(pick_u[paired_seen] * (hi[d] - lo[d]))), hi[d] - 1)  # u·n rounding to n
            paired_seen += 1
            a = pair_first[pick]
            b = pair_second[pick]
            ax, ay = landmarks[a, 0], landmarks[a, 1]
            qb_x, qb_y = points[second[d], 0], points[second[d], 1]
            theta = (math.atan2(landmarks[b, 1] - ay, landmarks[b, 0] - ax)
                     - math.atan2(qb_y - qa_y, qb_x - qa_x))
        else:
            theta = single_theta[single_seen]
            anchor = single_anchor[single_seen]
            single_seen += 1
            ax, ay = landmarks[anchor, 0], landmarks[anchor, 1]
        c, s = math.cos(theta), math.sin(theta)
        poses[d, 0] = ax - (c * qa_x - s * qa_y)
        poses[d, 1] = ay - (s * qa_x + c * qa_y)
        poses[d, 2] = wrap_angle(theta)
    hit = np.zeros(count, np.bool_)
    if check.shape[0] == 0:
        return poses, hit
    radius2 = match_radius * match_radius
    for d in range(count):
        c, s = math.cos(poses[d, 2]), math.sin(poses[d, 2])
        px, py = points[check[d], 0], points[check[d], 1]
        ex = poses[d, 0] + c * px - s * py
        ey = poses[d, 1] + s * px + c * py
        row = _cell_row(ex, ey, match_origin, match_cell, match_nx, match_ny)
        for k in range(match_table.shape[1]):
            landmark = match_table[row, k]
            dx = padded[landmark, 0] - ex
            dy = padded[landmark, 1] - ey
            if dx * dx + dy * dy <= radius2:
                hit[d] = True
                break
    return poses, hit


def warm_up() -> None:
    """Compile (or load from the cache) every kernel on tiny inputs (:func:`services.compiled.warm_up` times it)."""
    if AVAILABLE:
        table = np.zeros((1, 1), np.int64)
        one = np.ones(1)
        scan_log_likelihood_kernel(np.zeros((1, 3)), np.ones((1, 2)), one, one, one, one, np.eye(2), 1.0, 0.1,
                                   np.zeros((1, 2)), table, np.zeros(2), 1.0, 1, 1, table, np.zeros(2), 1.0, 1, 1,
                                   0.0, 0.0, 9.0, 5.0, 0.0, 1.0, False, -1.0)
        merge_cells_kernel(np.array([0, 1], np.int64), 3, 8, np.array([[0, 0, 1]], np.int64), np.zeros((2, 2)),
                           np.zeros(2), 1.0, 1.0)
        # two observations √2 apart, two landmarks 1.5 apart: both draws find the pair (0, 1) or (1, 0)
        points, landmarks = np.array([[1.0, 0.0], [0.0, 1.0]]), np.array([[0.0, 0.0], [1.5, 0.0]])
        first, second, pairs = np.array([0, 1]), np.array([1, 0]), np.array([0, 1])
        lo, hi = pair_windows_kernel(points, np.full(2, 0.01), first, second, np.full(2, 1.5), 3.0)
        candidate_poses_kernel(points, first, second, lo, hi, np.full(2, 0.5), pairs, pairs[::-1].copy(), landmarks,
                               np.zeros(0), np.zeros(0, np.int64), first, np.vstack([landmarks, [[1e9, 1e9]]]),
                               np.zeros((1, 1), np.int64), np.zeros(2), 10.0, 1, 1, 0.5)
        robot_kernels.warm_up()
