"""The kernels' helpers give their references' results: the angle wrap the numpy reference's bit for bit, its
shortcut within ±3 included (for angles a kernel can meet: validated input is finite, and numba's floor is an
integer); the normal CDF scipy's to the last bits."""

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


def test_the_kernel_normal_cdf_matches_scipy_and_its_shortcuts_are_exact():
    """ndtr inside kernels: scipy's value to the last bits everywhere, and exactly scipy's 1.0 and 0.0 where it
    returns them without computing (beyond 8.5 and below −39)."""
    from scipy.special import ndtr as reference_ndtr

    from services.compiled import ndtr

    rng = np.random.default_rng(1)
    edges = np.array([8.5, -39.0, 8.3, -37.6, 0.5 * math.sqrt(2.0), -0.5 * math.sqrt(2.0), 0.0])
    x = np.concatenate([edges, np.nextafter(edges, np.inf), np.nextafter(edges, -np.inf), rng.uniform(-45.0, 12.0, 20_000),
                        rng.normal(0.0, 2.0, 20_000), rng.uniform(7.5, 8.6, 2_000), rng.uniform(-40.0, -37.0, 2_000)])
    got = np.array([ndtr(float(value)) for value in x])
    expected = reference_ndtr(x)
    np.testing.assert_allclose(got, expected, rtol=1e-13, atol=1e-300)  # subnormals: libm and Cephes round apart
    beyond = (x > 8.5) | (x < -39.0)
    assert beyond.sum() > 1000 and np.array_equal(got[beyond], expected[beyond])
    assert np.all(got[expected < 1.0] < 1.0) and np.all(got[expected > 0.0] > 0.0)  # no shortcut taken too soon
