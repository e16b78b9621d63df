"""Two-stage cluster resampling (Sehestedt and Schneider, "Monte Carlo Localization in Highly Symmetric
Environments", §5.1); the systematic resampling inside each cluster is :func:`robots.gaussian.systematic_resample`.

Two-stage sampling first draws clusters, then particles inside each cluster.
With the weights normalised per cluster (η(x) = 1/C_j, eqs. 6-7) every
significant cluster is drawn equally often, so each hypothesis keeps its
share of samples however its weight compares with the others'; inside a
cluster the particles are drawn systematically.
"""

from __future__ import annotations

import numpy as np

from robots.gaussian import systematic_resample


def two_stage_resample(weights: np.ndarray, labels: np.ndarray, clusters: np.ndarray, count: int,
                       rng: np.random.Generator, memory: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Draw ``count`` particles: an equal share for each cluster in ``clusters``, systematic inside each.

    Returns the indices and the new weights. Particles of clusters that are not
    listed (insignificant ones) are not drawn: their slots go to the listed
    clusters. The drawn particles of cluster j share the weight C_j^memory
    (C_j the cluster's weight): with memory 0 every cluster weighs the same
    afterwards (eq. 7), with memory 1 the hypotheses keep their Bayesian
    weights, and in between old evidence fades geometrically, so a consistent
    difference between hypotheses accumulates while chance differences
    between equivalent ones stay bounded.
    """
    weights = np.asarray(weights, float)
    clusters = np.asarray(clusters, np.int64)
    m = clusters.size
    shares = np.full(m, count // m, np.int64)
    shares[rng.permutation(m)[: count - shares.sum()]] += 1
    indices, new_weights = [], []
    for cluster, share in zip(clusters, shares):
        members = np.flatnonzero(labels == cluster)
        if share == 0 or members.size == 0:
            continue
        mass = weights[members].sum()
        indices.append(members[systematic_resample(weights[members], int(share), rng)])
        new_weights.append(np.full(share, mass**memory / share if mass > 0 else 0.0))
    index = np.concatenate(indices)
    weight = np.concatenate(new_weights)
    total = weight.sum()
    return index, weight / total if total > 0 else np.full(index.size, 1.0 / index.size)
