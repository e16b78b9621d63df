"""`fleetslam demo` end to end: every process it starts comes up, robots publish, everything stops cleanly."""

import json
import subprocess
import sys

import pytest

from tests.helpers import REPO, free_port

pytestmark = pytest.mark.integration


def test_demo_runs_and_reports_per_robot_counts(tmp_path):
    out = tmp_path / "demo"
    result = subprocess.run(
        [sys.executable, "-m", "services.cli", "demo", "--duration", "4", "--robots", "3", "--speedup", "2",
         "--port", str(free_port()), "--out", str(out)],
        cwd=REPO, capture_output=True, text=True, timeout=150,
    )
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
    summary = json.loads((out / "demo.json").read_text())
    robots = summary["monitor"]["robots"]
    assert set(robots) >= {"r1", "r2", "r3"}
    for rid in ("r1", "r2", "r3"):
        assert robots[rid]["scan"] > 20 and robots[rid]["missing"] == 0
    assert summary["monitor"]["rejected"] == {}
    # a clean stop: every process exited by itself on SIGTERM, with code 0, inside the launcher's limits (10 s for
    # robots, 15 s for services, 30 s for the evaluator, which writes its report); the times are figures, printed
    assert summary["killed"] == [] and summary["exit_codes"], summary
    assert all(code == 0 for code in summary["exit_codes"].values()), summary["exit_codes"]
    assert set(summary["exit_codes"]) == set(summary["stop_s"])
    assert "messages per robot" in result.stdout
