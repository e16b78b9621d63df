"""`fleetslam demo` end to end: every process it starts comes up, robots publish, everything stops cleanly;
secured by default (a client without credentials is refused), open with ``--open``."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from schemas.config import FleetSettings
from schemas.transport import ConnectError, open_session
from tests.helpers import REPO, free_port, wait_for_port

pytestmark = pytest.mark.integration


def _admitted(port: int) -> bool:
    """Whether the demo's router lets in a client without credentials (closed at once)."""
    try:
        open_session(FleetSettings(zenoh_connect=f"tcp/127.0.0.1:{port}", connect_timeout_s=1.0)).close()
    except ConnectError:
        return False
    return True


def _demo(out: Path, *flags: str) -> tuple[subprocess.CompletedProcess, dict, bool]:
    """Run a demo; (its result, its summary, whether an anonymous client was admitted while it ran)."""
    port = free_port()
    process = subprocess.Popen([sys.executable, "-m", "services.cli", "demo", "--port", str(port), "--out", str(out),
                                *flags], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        wait_for_port(port, timeout=60)
        admitted = _admitted(port)
        stdout, stderr = process.communicate(timeout=150)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    result = subprocess.CompletedProcess(process.args, process.returncode, stdout, stderr)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
    return result, json.loads((out / "demo.json").read_text()), admitted


def test_demo_runs_secured_and_reports_per_robot_counts(tmp_path):
    secrets = tmp_path / "secrets"
    result, summary, admitted = _demo(tmp_path / "demo", "--duration", "4", "--robots", "3", "--speedup", "2",
                                      "--secrets-dir", str(secrets))
    assert not admitted, "a client without credentials was let into the secured demo"
    assert summary["secured"] and "secured" in result.stdout
    users = {p.name.removesuffix(".password") for p in secrets.glob("*.password")}
    assert users >= {"r1", "r2", "r3", "r4", "world", "monitor", "central", "dslam", "assoc", "mcl", "evaluate"}
    robots = summary["monitor"]["robots"]
    assert set(robots) >= {"r1", "r2", "r3"}
    for rid in ("r1", "r2", "r3"):
        assert robots[rid]["scan"] > 20 and robots[rid]["missing"] == 0
    assert summary["monitor"]["rejected"] == {}
    # the world map comes from its own publisher (the robots may not write it): the evaluator scores maps with it
    assert summary["metrics"]["summary"]["central"]["map_rmse_m"] is not None
    # a clean stop: every process exited by itself on SIGTERM, with code 0, inside the launcher's limits (10 s for
    # robots, 15 s for services, 30 s for the evaluator, which writes its report); the times are figures, printed
    assert summary["killed"] == [] and summary["exit_codes"], summary
    assert all(code == 0 for code in summary["exit_codes"].values()), summary["exit_codes"]
    assert set(summary["exit_codes"]) == set(summary["stop_s"])
    assert "messages per robot" in result.stdout


def test_demo_open_runs_the_old_open_fleet(tmp_path):
    out = tmp_path / "demo"
    result, summary, admitted = _demo(out, "--open", "--duration", "2", "--robots", "1", "--unknown-start-robots", "0",
                                      "--speedup", "2", "--secrets-dir", str(tmp_path / "secrets"))
    assert admitted and not summary["secured"] and "OPEN" in result.stdout
    assert "this router is OPEN" in (out / "logs" / "router.log").read_text()
    assert summary["monitor"]["robots"]["r1"]["scan"] > 5
    assert not (tmp_path / "secrets").exists()
