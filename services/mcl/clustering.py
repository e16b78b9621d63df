"""Grid clustering of the particle set into pose hypotheses (Sehestedt and Schneider,
"Monte Carlo Localization in Highly Symmetric Environments", §5.2).

A coarse fixed grid (about 2 m × 2 m × 45°) gives a first estimate: each
occupied cell is a piece of a cluster. Neighbouring cells (the 26 around a
cell, heading wrapping round) are fused when their mean poses are close in
the state space, and the connected pieces are the clusters. A cluster is
significant when it holds enough of the weight and its particles match the
scan well on average ("clusters with a high average weight").
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from robots.models import wrap_angle
from services.mcl import kernels


@dataclass
class Clusters:
    """Clusters of a particle set, heaviest first: labels per particle, then per cluster."""

    labels: np.ndarray  # (P,) cluster index of each particle
    weight: np.ndarray  # (m,) share of the total weight
    count: np.ndarray  # (m,) particles
    mean: np.ndarray  # (m, 3) weighted mean pose (circular mean heading)
    cov: np.ndarray  # (m, 3, 3) weighted covariance (heading deviations wrapped)
    quality: np.ndarray  # (m,) mean match quality of the cluster's particles

    def __len__(self) -> int:
        return int(self.weight.size)

    def significant(self, min_weight: float, min_quality: float, max_count: int) -> np.ndarray:
        """Indices of the significant clusters (heaviest first, at most ``max_count``)."""
        keep = np.flatnonzero((self.weight >= min_weight) & (self.quality >= min_quality))
        return keep[:max_count]


def grid_labels(poses: np.ndarray, cell_xy: float, cell_theta: float, merge_xy: float, merge_theta: float,
                compiled: bool = True) -> np.ndarray:
    """Cluster label ``(P,)`` of each pose: occupied grid cells, fused with close neighbours (``compiled``: by
    the numba kernel :func:`services.mcl.kernels.merge_cells_kernel`; False: this scipy reference)."""
    poses = np.asarray(poses, float)
    if poses.shape[0] == 0:
        return np.zeros(0, np.int64)
    turns = max(1, int(round(2 * math.pi / cell_theta)))
    ix = np.floor(poses[:, 0] / cell_xy).astype(np.int64)
    iy = np.floor(poses[:, 1] / cell_xy).astype(np.int64)
    it = np.mod(np.floor((poses[:, 2] + math.pi) / (2 * math.pi / turns)).astype(np.int64), turns)
    ix -= ix.min() - 1
    iy -= iy.min() - 1
    ny = int(iy.max()) + 2
    keys = (ix * ny + iy) * turns + it
    cells, cell_of = np.unique(keys, return_inverse=True)
    m = cells.size
    count = np.bincount(cell_of, minlength=m)
    mean_xy = np.stack([np.bincount(cell_of, poses[:, k], m) for k in (0, 1)], -1) / count[:, None]
    mean_theta = np.arctan2(np.bincount(cell_of, np.sin(poses[:, 2]), m), np.bincount(cell_of, np.cos(poses[:, 2]), m))
    theta_steps = (-1, 0, 1) if turns > 2 else ((0, 1) if turns == 2 else (0,))
    steps = np.array([d for d in itertools.product((-1, 0, 1), (-1, 0, 1), theta_steps) if any(d)])  # (S, 3)
    if compiled and kernels.AVAILABLE:
        return kernels.merge_cells_kernel(cells, ny, turns, steps, mean_xy, mean_theta, merge_xy, merge_theta)[cell_of]
    cx, rest = np.divmod(cells, ny * turns)
    cy, ct = np.divmod(rest, turns)
    neighbour = ((cx[:, None] + steps[:, 0]) * ny + (cy[:, None] + steps[:, 1])) * turns
    neighbour += np.mod(ct[:, None] + steps[:, 2], turns)
    pos = np.minimum(np.searchsorted(cells, neighbour), m - 1)
    hit = cells[pos] == neighbour
    a, b = np.nonzero(hit)[0], pos[hit]
    close = (np.linalg.norm(mean_xy[a] - mean_xy[b], axis=-1) <= merge_xy) & (
        np.abs(wrap_angle(mean_theta[a] - mean_theta[b])) <= merge_theta
    )
    graph = coo_matrix((np.ones(int(close.sum())), (a[close], b[close])), shape=(m, m))
    _, component = connected_components(graph, directed=False)
    return component[cell_of]


def cluster_statistics(poses: np.ndarray, weights: np.ndarray, labels: np.ndarray, quality: np.ndarray) -> Clusters:
    """Weight share, size, weighted mean and covariance, mean quality of every cluster, heaviest first.

    Particles labelled −1 belong to no cluster (they still count in the total weight).
    """
    poses, weights = np.asarray(poses, float), np.asarray(weights, float)
    total = weights.sum()
    w = weights / total if total > 0 else np.full(weights.size, 1.0 / max(weights.size, 1))
    member = labels >= 0
    _, dense = np.unique(labels[member], return_inverse=True)
    m = int(dense.max()) + 1 if dense.size else 0
    poses, w, quality = poses[member], w[member], np.asarray(quality, float)[member]
    count = np.bincount(dense, minlength=m)
    mass = np.bincount(dense, w, m)
    # inside a cluster of (numerically) zero weight, every particle counts equally
    inner = np.where(mass[dense] > 1e-300, w / np.maximum(mass[dense], 1e-300), 1.0 / count[dense])
    mean = np.empty((m, 3))
    mean[:, 0] = np.bincount(dense, inner * poses[:, 0], m)
    mean[:, 1] = np.bincount(dense, inner * poses[:, 1], m)
    mean[:, 2] = np.arctan2(np.bincount(dense, inner * np.sin(poses[:, 2]), m),
                            np.bincount(dense, inner * np.cos(poses[:, 2]), m))
    dev = poses - mean[dense]
    dev[:, 2] = wrap_angle(dev[:, 2])
    cov = np.empty((m, 3, 3))
    for a in range(3):
        for b in range(a, 3):
            cov[:, a, b] = cov[:, b, a] = np.bincount(dense, inner * dev[:, a] * dev[:, b], m)
    mean_quality = np.bincount(dense, quality, m) / np.maximum(count, 1)
    order = np.argsort(-mass, kind="stable")
    rank = np.empty(m, np.int64)
    rank[order] = np.arange(m)
    out = np.full(labels.shape, -1, np.int64)
    out[member] = rank[dense]
    return Clusters(labels=out, weight=mass[order], count=count[order], mean=mean[order], cov=cov[order],
                    quality=mean_quality[order])


def cluster_particles(poses, weights, quality, cell_xy, cell_theta, merge_xy, merge_theta, prune: float,
                      compiled: bool = True) -> Clusters:
    """Grid clustering of the particles that carry weight, then the statistics of each cluster.

    Particles lighter than ``prune`` times the heaviest one join no cluster, so
    that a haze of implausible samples (right after a global initialisation)
    cannot chain distinct hypotheses into one.
    """
    weights = np.asarray(weights, float)
    labels = np.full(weights.shape, -1, np.int64)
    active = weights >= prune * weights.max() if weights.size else np.zeros(0, bool)
    labels[active] = grid_labels(np.asarray(poses)[active], cell_xy, cell_theta, merge_xy, merge_theta, compiled)
    return cluster_statistics(poses, weights, labels, quality)
