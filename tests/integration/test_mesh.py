"""Routers that form a mesh (``fleetslam router --connect``): a robot on one router is fused by a central on another;
secured, the routers know each other by their certificates and every client keeps, through the other router, the
rights it has at its own, and no more."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from schemas.config import FleetSettings
from schemas.messages import Estimate
from schemas.transport import open_session
from tests.helpers import REPO, Collector, Processes, client_session, free_port, put_until_seen, wait_for_port, \
    wait_until

pytestmark = pytest.mark.integration

MAKE_CERTS = REPO / "deploy" / "make-certs.sh"


def _router(processes: Processes, name: str, endpoint: str, *extra: str) -> None:
    processes.start(name, "router", "--listen", endpoint, *extra)
    wait_for_port(int(endpoint.rsplit(":", 1)[1]))


def test_a_robot_on_one_router_is_fused_by_central_on_another(processes):
    a, b = f"tcp/127.0.0.1:{free_port()}", f"tcp/127.0.0.1:{free_port()}"
    prefix = "mesh"
    processes.env.update(FLEETSLAM_PREFIX=prefix, FLEETSLAM_CONNECT_TIMEOUT_S="10")
    _router(processes, "router-a", a)
    _router(processes, "router-b", b, "--connect", a)
    session = client_session(a)
    try:
        estimates = Collector(session, f"{prefix}/central/estimate")
        processes.start("central", "central", env={"FLEETSLAM_ZENOH_CONNECT": b})
        processes.start("robot", "robot", "--id", "r1", "--duration", "4", "--speedup", "4", "--start-delay", "2",
                        env={"FLEETSLAM_ZENOH_CONNECT": a})
        wait_until(lambda: any(r.robot_id == "r1" for e in estimates.decoded(Estimate) for r in e.robots), 60,
                   what="central (on router B) fusing r1 (on router A), seen from router A")
    finally:
        session.close()


def _certs(folder: Path, users: str) -> Path:
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed")
    subprocess.run(["sh", str(MAKE_CERTS), str(folder), "router,localhost,127.0.0.1", users], check=True,
                   capture_output=True)
    return folder


def test_secured_routers_know_each_other_by_certificate_and_rights_hold_across_them(processes, tmp_path):
    tls, secrets = _certs(tmp_path / "tls", "r1 r2 central monitor"), tmp_path / "secrets"
    a, b = f"tls/127.0.0.1:{free_port()}", f"tls/127.0.0.1:{free_port()}"
    prefix = "smesh"
    secured = ("--prefix", prefix, "--secrets-dir", str(secrets), "--tls-dir", str(tls), "--robot-users", "r1,r2",
               "--service-users", "central,monitor")
    _router(processes, "router-a", a, *secured)
    _router(processes, "router-b", b, *secured, "--connect", a)

    def session(user: str, endpoint: str):
        return open_session(FleetSettings(
            zenoh_connect=endpoint, prefix=prefix, connect_timeout_s=5, zenoh_user=user,
            zenoh_password=(secrets / f"{user}.password").read_text().strip(), tls_root_ca=str(tls / "ca.pem"),
            tls_cert=str(tls / f"{user}.pem"), tls_key=str(tls / f"{user}-key.pem")))

    opened = [session("r1", a), session("monitor", b), session("central", b), session("r2", b)]
    r1, monitor, central, r2 = opened
    try:
        seen = Collector(monitor, f"{prefix}/**")
        r1_estimates, r2_hears_r1 = Collector(r1, f"{prefix}/central/estimate"), Collector(r2, f"{prefix}/robots/r1/**")
        put_until_seen(r1, f"{prefix}/robots/r1/odom", b"across the mesh", seen, timeout=20)
        put_until_seen(central, f"{prefix}/central/estimate", b"fused", r1_estimates, timeout=20)
        r1.put(f"{prefix}/robots/r2/odom", b"forged")  # r1 may not write r2's keys: refused at router A
        r1.put(f"{prefix}/central/estimate", b"forged")
        put_until_seen(r1, f"{prefix}/robots/r1/odom", b"after the forgery", seen, timeout=10)
        assert not any(payload == b"forged" for _, payload in seen.snapshot())
        assert r2_hears_r1.count() == 0  # a robot does not read another robot's streams, through any router
    finally:
        for item in reversed(opened):
            item.close()


def test_a_password_only_secured_router_refuses_to_connect_to_others_and_says_why(tmp_path):
    result = subprocess.run([sys.executable, "-m", "services.cli", "router", "--listen", f"tcp/127.0.0.1:{free_port()}",
                             "--secrets-dir", str(tmp_path / "secrets"), "--connect", "tcp/127.0.0.1:9"],
                            cwd=REPO, capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and "--tls-dir" in result.stderr, result.stderr


def test_a_router_started_before_the_one_it_connects_to_joins_it_when_it_comes(processes):
    a, b = f"tcp/127.0.0.1:{free_port()}", f"tcp/127.0.0.1:{free_port()}"
    _router(processes, "router-b", b, "--connect", a)  # A is not there yet
    wait_until(lambda: "connecting to" in processes.log("router-b"), 10, what="router B up")
    _router(processes, "router-a", a)
    on_a, on_b = client_session(a), client_session(b)
    try:
        seen = Collector(on_a, "late/**")
        put_until_seen(on_b, "late/x", b"joined", seen, timeout=20)
    finally:
        on_b.close()
        on_a.close()
