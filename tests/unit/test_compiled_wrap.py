"""The kernels' angle wrap gives the numpy reference's result bit for bit, its shortcut within ±3 included (for
angles a kernel can meet: validated input is finite, and numba's floor is an integer)."""

from __future__ import annotations

import math

import numpy as np

from robots.models import wrap_angle as reference_wrap
from services.compiled import wrap_angle


def test_the_kernel_wrap_equals_the_reference_bit_for_bit():
    rng = np.random.default_rng(0)
    edges = [3.0, math.pi, 2.0 * math.pi, 0.0, 1e-300, 1e6]
    near_edges = [np.nextafter(edge, toward) for edge in edges for toward in (-np.inf, np.inf)]
    angles = np.concatenate([edges, near_edges, -np.array(edges + near_edges), [-0.0, np.nan],
                             rng.uniform(-20.0, 20.0, 20_000), rng.uniform(-3.2, 3.2, 20_000)])
    expected = reference_wrap(angles)
    got = np.array([wrap_angle(float(angle)) for angle in angles])
    assert np.array_equal(got.view(np.int64), expected.view(np.int64))
