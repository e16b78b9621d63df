"""numba, in one place: whether it is there, the decorator every kernel uses, and the warm-up of all kernels.

Kernels are compiled on first use and cached on disk (``cache=True``; ``NUMBA_CACHE_DIR`` chooses where, the
image compiles them at build). A service warms them up before it subscribes, so that no scan waits for the
compiler. A kernel's cache is emptied when the helpers it may inline (this module, ``robots/kernels.py``)
changed, which numba does not see. Without numba the numpy references run instead (numba is a declared
dependency; this only keeps the references usable).
"""

from __future__ import annotations

import fcntl
import hashlib
import logging
import math
import os
import time
from pathlib import Path

try:
    import numba
except ImportError:  # pragma: no cover - numba is a declared dependency
    numba = None

AVAILABLE = numba is not None
log = logging.getLogger(__name__)

# The modules whose kernels other modules' kernels inline. numba renews a kernel's cache only when the kernel's own
# file changes, so a kernel of another module would keep the old helper after an edit of one of these.
HELPER_SOURCES = (Path(__file__), Path(__file__).resolve().parents[1] / "robots" / "kernels.py")


def sources_digest(paths=HELPER_SOURCES) -> str:
    """The SHA-256 of the files' contents (a missing file counts as empty)."""
    digest = hashlib.sha256()
    for path in paths:
        try:
            digest.update(Path(path).read_bytes())
        except OSError:
            pass
        digest.update(b"\0")
    return digest.hexdigest()


HELPERS_DIGEST = sources_digest()


def renew_cache_if_stale(dispatcher, digest: str) -> bool:
    """Empty ``dispatcher``'s on-disk cache when it was written with other helper sources than ``digest`` says, and
    note ``digest`` beside it (``{index}.helpers``): the kernel is then compiled afresh on its first call. True when
    it emptied the cache. This reaches into numba's cache object (``_cache``, its index file); if that is not
    there, the cache stays as it is."""
    cache = getattr(dispatcher, "_cache", None)
    index = getattr(getattr(cache, "_cache_file", None), "_index_path", None)
    if index is None or not hasattr(cache, "flush"):
        return False
    stamp = Path(f"{index}.helpers")
    try:
        if stamp.read_text() == digest:
            return False
    except OSError:
        pass
    try:
        cache.flush()
        stamp.write_text(digest)
    except OSError as exc:  # a read-only cache: numba itself falls back or compiles in memory
        log.debug("cannot renew the kernel cache %s: %s", index, exc)
        return False
    return True


def njit(function):
    """Compile ``function`` in nopython mode, cached on disk, without the GIL (or leave it as it is). The cache of a
    kernel outside this module is renewed when the helpers it may inline changed (:func:`renew_cache_if_stale`)."""
    if not AVAILABLE:
        return function
    dispatcher = numba.njit(cache=True, nogil=True)(function)
    if function.__module__ != __name__:
        renew_cache_if_stale(dispatcher, HELPERS_DIGEST)
    return dispatcher


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


def warm_up(groups: tuple[str, ...] = KERNEL_GROUPS, lock_dir: Path | None = None) -> float:
    """Compile (or load from the cache) the kernels of ``groups`` (default: every kernel of the system, as the image
    build does) on tiny inputs; returns the seconds taken. A service warms only the groups it runs. Each group is
    warmed under its lock (:func:`each_under_its_lock`, in ``lock_dir``, default :func:`lock_directory`): processes
    started together on an empty cache (a fleet, the test workers) compile different groups instead of each
    compiling all of them."""
    from importlib import import_module

    modules = {"association": "services.association.kernels", "mcl": "services.mcl.kernels",
               "fastslam": "central.fastslam.kernels"}
    unknown = set(groups) - set(modules)
    if unknown:
        raise ValueError(f"unknown kernel groups {sorted(unknown)} (known: {', '.join(KERNEL_GROUPS)})")
    started = time.perf_counter()
    each_under_its_lock(groups, lambda group: import_module(modules[group]).warm_up(),
                        lock_directory() if lock_dir is None else lock_dir)
    return time.perf_counter() - started


def lock_directory() -> Path:
    """Where the warm-up's locks are: numba's cache directory when ``NUMBA_CACHE_DIR`` names one (the image), else
    this package's ``__pycache__``, beside the kernels' caches."""
    return Path(os.environ.get("NUMBA_CACHE_DIR") or Path(__file__).parent / "__pycache__")


def each_under_its_lock(names, work, lock_dir: Path) -> None:
    """Call ``work(name)`` for every name, each under an exclusive lock file ``{lock_dir}/warm-{name}.lock``. A name
    whose lock another process holds is left for later while another is free, and waited for when none is: two
    processes on an empty cache compile different groups at once, and each then loads the other's from the cache.
    Where no lock can be made (a read-only directory) the work runs unlocked."""
    pending = list(names)
    while pending:
        chosen, handle = None, None
        for name in pending:
            handle = _lock(lock_dir, name, wait=False)
            if handle is not False:
                chosen = name
                break
        if chosen is None:
            chosen = pending[0]
            handle = _lock(lock_dir, chosen, wait=True)
        try:
            work(chosen)
        finally:
            if handle is not None:
                handle.close()  # closing the file releases its lock
        pending.remove(chosen)


def _lock(lock_dir: Path, name: str, wait: bool):
    """The open lock file of ``name``, locked; False when another process holds it and ``wait`` is False; None when
    no lock can be made here."""
    try:
        lock_dir.mkdir(parents=True, exist_ok=True)
        handle = open(lock_dir / f"warm-{name}.lock", "a")
    except OSError as exc:
        log.debug("no warm-up lock in %s: %s", lock_dir, exc)
        return None
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
    except BlockingIOError:
        handle.close()
        return False
    except OSError as exc:  # a file system without locks
        log.debug("cannot lock %s: %s", handle.name, exc)
        handle.close()
        return None
    return handle
