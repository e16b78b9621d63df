"""Shared fixtures: a real Zenoh router process, real fleetslam processes, a client session."""

from __future__ import annotations

import os
from dataclasses import dataclass

import pytest

from tests.helpers import Processes, client_session, free_port, wait_for_port


@dataclass
class Router:
    endpoint: str
    port: int
    env: dict[str, str]


def pytest_addoption(parser):
    parser.addoption("--crash-seed", type=int, default=20261123,
                     help="seed of the kill moments of tests/integration/test_crash_restart.py "
                     "(benchmarks/crash_restart.py runs it over many seeds)")
    parser.addoption("--crash-kills", choices=("all", "none"), default="all",
                     help="none: test_crash_restart.py kills nothing, so copy B against copy A measures how far two "
                     "untouched live runs differ (the benchmark's control)")


@pytest.fixture
def crash_seed(request) -> int:
    return request.config.getoption("--crash-seed")


@pytest.fixture
def crash_kills(request) -> bool:
    return request.config.getoption("--crash-kills") == "all"


@pytest.fixture(autouse=True)
def clean_environment(monkeypatch):
    """Every test starts from a clean environment: no ``FLEETSLAM_*`` variable of the caller reaches it (and
    so none reaches the processes it starts)."""
    for name in [name for name in os.environ if name.startswith("FLEETSLAM_")]:
        monkeypatch.delenv(name)


@pytest.fixture
def processes(tmp_path):
    """A group of fleetslam processes; all are stopped at the end of the test."""
    group = Processes(tmp_path, {**os.environ, "PYTHONUNBUFFERED": "1"})
    yield group
    group.stop_all()


@pytest.fixture
def router(processes, tmp_path) -> Router:
    """A router process on a free loopback port; children started after it connect to it."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    prefix = f"t{port}"
    processes.env.update(FLEETSLAM_ZENOH_CONNECT=endpoint, FLEETSLAM_PREFIX=prefix, FLEETSLAM_CONNECT_TIMEOUT_S="10")
    processes.start("router", "router", "--listen", endpoint)
    wait_for_port(port)
    return Router(endpoint=endpoint, port=port, env=dict(processes.env))


@pytest.fixture
def zsession(router):
    """A client session of the test itself, connected to the router."""
    session = client_session(router.endpoint)
    yield session
    session.close()


@pytest.fixture
def prefix(router) -> str:
    return router.env["FLEETSLAM_PREFIX"]
