"""The monitor and the evaluator over a real router: the same robot id run twice in a row (its token goes away
in between, its seq numbers and stamps start again) is a new run for them, not a burst of messages out of order."""

from __future__ import annotations

import json
import signal

import numpy as np
import pytest

from robots.simulator import simulate
from schemas.keys import Keys
from schemas.messages import ServiceStats
from tests.helpers import Collector, wait_until

pytestmark = pytest.mark.integration

ORDER_REFUSALS = ("duplicate", "out_of_order", "time_backwards")


def test_a_robot_run_twice_is_a_new_run_for_the_monitor_and_the_evaluator(router, processes, zsession, prefix,
                                                                          tmp_path):
    keys = Keys(prefix)
    report = tmp_path / "report"
    eval_stats = Collector(zsession, keys.eval_stats)
    monitor_stats = Collector(zsession, keys.stats("monitor"))
    evaluator = processes.start("evaluate", "evaluate", "--out", str(report), "--stats-period-s", "0.3")
    monitor = processes.start("monitor", "monitor", "--plain", "--json-out", str(tmp_path / "monitor.json"))
    wait_until(lambda: eval_stats.count() > 0 and monitor_stats.count() > 0, 30, what="both observers' first stats")
    truth_per_run = simulate("arena", seed=0, duration=3.0, robot_ids=["r1"]).robots["r1"].truth_stamp.size
    for turn in (1, 2):
        robot = processes.start(f"r1-run{turn}", "robot", "--id", "r1", "--world", "arena", "--seed", "0", "--rate",
                                "10", "--duration", "3", "--speedup", "10", "--start-delay", "0.3")
        assert robot.wait(timeout=30) == 0

    def evaluator_saw_both_runs():
        last = eval_stats.decoded(ServiceStats)[-1]
        return last if last.messages_in.get("truth", 0) >= 2 * truth_per_run else None

    last = wait_until(evaluator_saw_both_runs, 15, what="the evaluator to take in both runs' truth")
    assert last.extra["robot_restarts"] == 1.0 and last.extra["robots_with_truth"] == 1.0, last.extra
    assert not {reason for reason in last.rejected if reason in ORDER_REFUSALS}, last.rejected

    assert processes.stop(monitor, signal.SIGTERM, timeout=20) < 20
    assert processes.stop(evaluator, signal.SIGTERM, timeout=20) < 20
    summary = json.loads((tmp_path / "monitor.json").read_text())
    assert summary["robots"]["r1"]["restarts"] == 1 and summary["robot_restarts"] == 1, summary["robots"]
    assert summary["robots"]["r1"]["truth"] == 2 * truth_per_run, summary["robots"]
    assert not {reason for reason in summary["rejected"] if reason in ORDER_REFUSALS}, summary["rejected"]
    metrics = json.loads((report / "metrics.json").read_text())
    assert metrics["robot_restarts"] == {"r1": 1}
    for name in ("truth_r1.tum", "truth_r1_run1.tum"):  # each run's truth on its own: r1#run1 is the first run
        assert np.loadtxt(report / name).shape == (truth_per_run, 8)
