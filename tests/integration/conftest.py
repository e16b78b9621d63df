"""Fixtures of the integration tests: the numba kernels compiled once, a real Compose v2 binary and a lab of
network namespaces."""

from __future__ import annotations

import logging

import pytest

from services import compiled

from tests.integration.compose import compose_binary
from tests.integration.netns import NetnsLab, netns_unavailable


@pytest.fixture(scope="session", autouse=True)
def kernels_in_the_cache():
    """Compile every numba kernel once, into the on-disk cache the services' processes load from. In a fresh clone
    the cache is empty: without this the first test's six services each compiled every kernel at once (two
    minutes on two busy cores) and the fleet's start timed out."""
    seconds = compiled.warm_up()
    logging.getLogger(__name__).info("numba kernels compiled or loaded in %.1f s", seconds)


@pytest.fixture(scope="session")
def compose_bin():
    """The docker-compose binary (fetched by `make test`, or here); skips, saying why, when it cannot be had."""
    binary, why = compose_binary()
    if binary is None:
        pytest.skip(f"no Docker Compose v2 binary: {why}")
    return binary


@pytest.fixture
def netns_lab(request):
    """An empty lab of network namespaces, always removed afterwards; skips, saying why, when not root."""
    why = netns_unavailable()
    if why:
        pytest.skip(why)
    lab = NetnsLab(request.node.name[:12].replace("_", "")[:12] or "lab")
    yield lab
    lab.close()
