"""Association requests built to stress the solvers, shared by the query tests and benchmarks/query_flood.py."""

from __future__ import annotations

import numpy as np

from robots.models import RangeBearingSensor
from schemas.association import AssociationRequest


def dense_request(m: int, n: int, seed: int = 0) -> AssociationRequest:
    """Every measurement gates every landmark (landmarks packed in a metre, wide covariances): the worst case of
    JCBB's search and of the LP."""
    rng = np.random.default_rng(seed)
    landmarks = np.column_stack([rng.uniform(4.0, 5.0, n), rng.uniform(-0.5, 0.5, n)])
    z = RangeBearingSensor().observe(np.zeros(3), landmarks[rng.integers(0, n, m)]) + rng.normal(0, [0.05, 0.01], (m, 2))
    z[:, 0] = np.abs(z[:, 0])
    return AssociationRequest(measurements=z, noise=np.diag([0.05**2, 0.01**2]), landmarks=landmarks,
                              landmark_covs=np.tile(np.eye(2) * 0.5, (n, 1, 1)), pose=np.zeros(3),
                              pose_cov=np.diag([0.5, 0.5, 0.05]))
