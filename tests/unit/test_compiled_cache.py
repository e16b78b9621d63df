"""A kernel's on-disk cache is renewed when the helpers it may inline change (``services.compiled``): numba itself
renews it only when the kernel's own file changes, so a kernel would keep an old ``wrap_angle`` or ``ndtr``."""

from __future__ import annotations

import importlib.util
import sys

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
