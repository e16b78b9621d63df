"""numba, in one place: whether it is there, the decorator every kernel uses, and the warm-up of all kernels.

Kernels are compiled on first use and cached on disk (``cache=True``; ``NUMBA_CACHE_DIR`` chooses where, the
image compiles them at build). A service warms them up before it subscribes, so that no scan waits for the
compiler. Without numba the numpy references run instead (numba is a declared dependency; this only keeps
the references usable).
"""

from __future__ import annotations

import math
import time

try:
    import numba
except ImportError:  # pragma: no cover - numba is a declared dependency
    numba = None

AVAILABLE = numba is not None


def njit(function):
    """Compile ``function`` in nopython mode, cached on disk, without the GIL (or leave it as it is)."""
    return numba.njit(cache=True, nogil=True)(function) if AVAILABLE else function


@njit
def wrap_angle(angle):
    """An angle wrapped to [−π, π) inside a kernel: the floor form of :func:`robots.models.wrap_angle`. Within ±3
    the floor is 0 whatever the rounding, so the angle itself is the same result, without the division."""
    if -3.0 <= angle <= 3.0:
        return angle
    return angle - 2.0 * math.pi * math.floor((angle + math.pi) / (2.0 * math.pi))


@njit
def ndtr(x):
    """The standard normal CDF inside a kernel, as scipy.special.ndtr computes it (Cephes): from erf near 0, from
    erfc in the tails, where 1 − erf would lose the digits. libm's erf/erfc differ from Cephes' in the last bits.
    Beyond 8.5 the tail (below 1e-17) rounds 1 − tail to 1.0 exactly, and below −39 erfc underflows to 0: those
    are returned without the call (most candidates of a scan are far inside the sensor's limits)."""
    if x > 8.5:
        return 1.0
    if x < -39.0:
        return 0.0
    z = x * (0.5 * math.sqrt(2.0))
    if abs(z) < 0.5 * math.sqrt(2.0):
        return 0.5 + 0.5 * math.erf(z)
    tail = 0.5 * math.erfc(abs(z))
    return 1.0 - tail if z > 0.0 else tail


KERNEL_GROUPS = ("association", "mcl", "fastslam")


def warm_up(groups: tuple[str, ...] = KERNEL_GROUPS) -> float:
    """Compile (or load from the cache) the kernels of ``groups`` (default: every kernel of the system, as the image
    build does) on tiny inputs; returns the seconds taken. A service warms only the groups it runs."""
    from importlib import import_module

    modules = {"association": "services.association.kernels", "mcl": "services.mcl.kernels",
               "fastslam": "central.fastslam.kernels"}
    unknown = set(groups) - set(modules)
    if unknown:
        raise ValueError(f"unknown kernel groups {sorted(unknown)} (known: {', '.join(KERNEL_GROUPS)})")
    started = time.perf_counter()
    for group in groups:
        import_module(modules[group]).warm_up()
    return time.perf_counter() - started
