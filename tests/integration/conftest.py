"""Fixtures of the multi-host tests: a real Compose v2 binary and a lab of network namespaces."""

from __future__ import annotations

import pytest

from tests.integration.compose import compose_binary
from tests.integration.netns import NetnsLab, netns_unavailable


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
