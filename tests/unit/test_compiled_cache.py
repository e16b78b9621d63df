"""A kernel's on-disk cache is renewed when the helpers it may inline change (``services.compiled``): numba itself
renews it only when the kernel's own file changes, so a kernel would keep an old ``wrap_angle`` or ``ndtr``."""

from __future__ import annotations

import importlib.util
import sys
import time

import pytest

from services import compiled

numba = pytest.importorskip("numba")

HELPER_V1 = "def scale(x):\n    return 2.0 * x\n"


def _import(path, name):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture
def kernel_module(tmp_path):
    """A module of its own with a kernel, cached in its folder's ``__pycache__``."""
    path = tmp_path / "cache_probe_kernels.py"
    path.write_text("def kernel(x):\n    return x + 1.0\n")
    yield _import(path, "cache_probe_kernels")
    sys.modules.pop("cache_probe_kernels", None)


def _fresh(function, digest):
    """A new dispatcher of ``function``, renewed against ``digest``, called once: (emptied?, cache hits, misses)."""
    dispatcher = numba.njit(cache=True)(function)
    emptied = compiled.renew_cache_if_stale(dispatcher, digest)
    assert dispatcher(1.0) == 2.0
    return emptied, sum(dispatcher.stats.cache_hits.values()), sum(dispatcher.stats.cache_misses.values())


def test_a_kernel_cache_is_kept_for_the_same_helpers_and_renewed_for_others(kernel_module):
    first = _fresh(kernel_module.kernel, "helpers-a")
    assert first == (True, 0, 1)  # nothing noted yet: compiled and saved
    assert _fresh(kernel_module.kernel, "helpers-a") == (False, 1, 0)  # the same helpers: loaded from the cache
    assert _fresh(kernel_module.kernel, "helpers-b") == (True, 0, 1)  # a helper changed: compiled afresh
    assert _fresh(kernel_module.kernel, "helpers-b") == (False, 1, 0)


def test_the_digest_follows_every_helper_file(tmp_path):
    helper, other = tmp_path / "helper.py", tmp_path / "other.py"
    helper.write_text(HELPER_V1)
    other.write_text("")
    before = compiled.sources_digest((helper, other))
    assert compiled.sources_digest((helper, other)) == before
    helper.write_text(HELPER_V1.replace("2.0", "3.0"))
    assert compiled.sources_digest((helper, other)) != before
    helper.write_text(HELPER_V1)
    other.write_text("# a comment\n")
    assert compiled.sources_digest((helper, other)) != before


def test_the_system_kernels_outside_the_helpers_are_renewed_by_them():
    """Every module with kernels that inline a helper is covered: the helpers are compiled.py and robots/kernels.py,
    and the digest is taken of both."""
    names = {path.name for path in compiled.HELPER_SOURCES}
    assert names == {"compiled.py", "kernels.py"}
    assert all(path.is_file() for path in compiled.HELPER_SOURCES)
    assert compiled.HELPERS_DIGEST == compiled.sources_digest()


def test_workers_warming_up_together_take_different_groups_and_never_the_same_one_at_once(tmp_path):
    """Two warm-ups started together (test workers, a fleet's services on an empty cache) each warm every group,
    one group at a time per lock: the second takes the group the first does not hold, so they overlap on
    different groups, and no group is warmed by both at once."""
    import threading

    spans: list[tuple[str, int, float, float]] = []
    first_started = threading.Barrier(2, timeout=5.0)  # each worker's first group waits until both have started
    firsts: set[int] = set()
    guard = threading.Lock()

    def worker(number: int) -> None:
        def work(name: str) -> None:
            begun = time.monotonic()
            if number not in firsts:
                firsts.add(number)
                try:
                    first_started.wait()
                except threading.BrokenBarrierError:
                    pass
            with guard:
                spans.append((name, number, begun, time.monotonic()))
        compiled.each_under_its_lock(["fastslam", "association", "mcl"], work, tmp_path)

    threads = [threading.Thread(target=worker, args=(n,)) for n in (1, 2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=30.0)
    assert sorted((name, number) for name, number, _, _ in spans) == sorted(
        (name, n) for name in ("fastslam", "association", "mcl") for n in (1, 2))
    first = {number: min((s for s in spans if s[1] == number), key=lambda s: s[2])[0] for number in (1, 2)}
    assert first[1] != first[2], f"both workers began with {first[1]}: {spans}"
    assert not first_started.broken, "the second worker waited for the first one's group instead of taking another"
    for name in ("fastslam", "association", "mcl"):
        (_, _, a0, a1), (_, _, b0, b1) = sorted((s for s in spans if s[0] == name), key=lambda s: s[2])
        assert a1 <= b0, f"{name} warmed by both workers at once"


def test_a_warm_up_without_a_writable_lock_directory_still_warms_every_group(tmp_path):
    """Where no lock can be made (a read-only image), every group is warmed all the same, unlocked."""
    blocked = tmp_path / "file"
    blocked.write_text("not a directory")
    done = []
    compiled.each_under_its_lock(["a", "b"], done.append, blocked / "locks")
    assert done == ["a", "b"]
