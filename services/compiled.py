"""numba, in one place: whether it is there, the decorator every kernel uses, and the warm-up of all kernels.

Kernels are compiled on first use and cached on disk (``cache=True``; ``NUMBA_CACHE_DIR`` chooses where, the
image compiles them at build). A service warms them up before it subscribes, so that no scan waits for the
compiler. Without numba the numpy references run instead (numba is a declared dependency; this only keeps
the references usable).
"""

from __future__ import annotations

import time

try:
    import numba
except ImportError:  # pragma: no cover - numba is a declared dependency
    numba = None

AVAILABLE = numba is not None


def njit(function):
    """Compile ``function`` in nopython mode, cached on disk, without the GIL (or leave it as it is)."""
    return numba.njit(cache=True, nogil=True)(function) if AVAILABLE else function


def warm_up() -> float:
    """Compile (or load from the cache) every kernel of the system on tiny inputs; returns the seconds taken."""
    from central.fastslam import kernels as fastslam_kernels
    from services.association import kernels as association_kernels
    from services.mcl import kernels as mcl_kernels

    started = time.perf_counter()
    mcl_kernels.warm_up()
    association_kernels.warm_up()
    fastslam_kernels.warm_up()
    return time.perf_counter() - started
