"""``fleetslam evaluate`` over a real router: truth from a real robot, estimates published by the test;
live stats on {prefix}/eval/stats, rejections counted, a report folder on SIGTERM."""

import json
import signal

import numpy as np
import pytest

from robots.simulator import simulate
from schemas.keys import Keys
from schemas.messages import Estimate, PoseEstimate, RobotEstimate, ServiceStats
from schemas.transport import StreamPublisher
from tests.helpers import Collector, wait_until

pytestmark = pytest.mark.integration

OFFSET = np.array([0.3, 0.4, 0.0])  # central's estimate is off by 0.5 m: ATE 0.5


def test_evaluator_scores_live_estimates_and_writes_a_report(router, processes, zsession, prefix, tmp_path):
    keys = Keys(prefix)
    report = tmp_path / "report"
    stats = Collector(zsession, keys.eval_stats)
    evaluator = processes.start("evaluate", "evaluate", "--out", str(report), "--stats-period-s", "0.3")
    wait_until(lambda: stats.count() > 0, 15, what="the evaluator's first stats")
    robot = processes.start("r1", "robot", "--id", "r1", "--world", "arena", "--seed", "0", "--rate", "10",
                            "--duration", "3", "--speedup", "10", "--start-delay", "0.3")
    assert robot.wait(timeout=30) == 0
    truth = simulate("arena", seed=0, duration=3.0, robot_ids=["r1"])
    log = truth.robots["r1"]

    central = StreamPublisher(zsession, keys.central_estimate)
    dslam = StreamPublisher(zsession, keys.dslam_pose("r1"))
    for seq, k in enumerate(range(0, log.truth_stamp.size, 3)):
        stamp = float(log.truth_stamp[k])
        estimate = Estimate(seq=seq, stamp=stamp, particles=10, effective_particles=10.0,
                            robots=[RobotEstimate(robot_id="r1", stamp=stamp, pose=log.truth_pose[k] + OFFSET,
                                                  cov=np.eye(3) * 0.01)],
                            landmarks=truth.landmarks + [0.05, 0.0], landmark_covs=np.tile(np.eye(2) * 0.01, (15, 1, 1)))
        central.put(estimate)
        dslam.put(PoseEstimate(robot_id="r1", seq=seq, stamp=stamp, pose=log.truth_pose[k], cov=np.eye(3) * 0.01))
    central.put(estimate)  # a duplicate
    central.put(b"\x01garbage")  # a malformed payload

    def live_ate():
        last = stats.decoded(ServiceStats)[-1]
        scored = "central.r1.ate_m" in last.extra and "dslam.r1.ate_m" in last.extra
        return last if scored and sum(last.rejected.values()) >= 2 else None

    last = wait_until(live_ate, 15, what="live ATE in the evaluator's stats")
    assert last.extra["central.r1.ate_m"] == pytest.approx(0.5, abs=1e-6)
    assert last.extra["dslam.r1.ate_m"] == pytest.approx(0.0, abs=1e-6)
    assert last.extra["central.landmarks_matched"] == 15
    assert last.rejected.get("duplicate") == 1

    assert processes.stop(evaluator, signal.SIGTERM, timeout=20) < 20
    assert evaluator.returncode == 0
    metrics = json.loads((report / "metrics.json").read_text())
    central_summary = metrics["summary"]["central"]
    assert central_summary["ate_rmse_m"]["r1"] == pytest.approx(0.5, abs=1e-6)
    assert central_summary["map_rmse_m"] == pytest.approx(0.05, abs=1e-6)
    assert central_summary["landmarks"] == {"estimated": 15, "matched": 15, "missed": 0, "spurious": 0}
    assert metrics["summary"]["dslam"]["ate_rmse_m"]["r1"] == pytest.approx(0.0, abs=1e-6)
    assert sum(metrics["rejected"].values()) >= 2
    for name in ("truth_r1.tum", "central_r1.tum", "dslam_r1.tum", "map_central.png", "map_dslam.png", "errors.png"):
        assert (report / name).stat().st_size > 0
    rows = np.loadtxt(report / "central_r1.tum")
    assert rows.shape[1] == 8 and rows.shape[0] == len(range(0, log.truth_stamp.size, 3))
