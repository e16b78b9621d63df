"""The evaluator's bookkeeping (services/evaluation/service.py) without a router, fed synthetic samples: a robot's
new run (token gone, truth at seq 0 again, stamps going back) is scored apart from the run that ended, while
truth going back with the token still there is refused."""

import numpy as np
import pytest

from schemas.codec import encode
from schemas.config import EvaluateSettings
from schemas.messages import Estimate, GroundTruth, PoseEstimate, RobotEstimate
from services.evaluation.service import Evaluator, Series

PREFIX = "fleet"
FIRST_RUN = np.array([1.0, 0.0, 0.0])  # the direction each run drives in: the two runs share stamps, not poses
SECOND_RUN = np.array([0.0, 1.0, np.pi / 2])


def true_pose(direction: np.ndarray, seq: int) -> np.ndarray:
    return np.array([0.05 * seq * direction[0], 0.05 * seq * direction[1], direction[2]])


def central(seq: int, robot_stamp: float, pose: np.ndarray) -> bytes:
    return encode(Estimate(seq=seq, stamp=float(seq), particles=10, effective_particles=10.0,
                           robots=[RobotEstimate(robot_id="r1", stamp=robot_stamp, pose=pose, cov=np.eye(3) * 0.01)],
                           landmarks=np.zeros((0, 2)), landmark_covs=np.zeros((0, 2, 2))))


async def run(evaluator: Evaluator, direction: np.ndarray, last_seq: int, dslam_seq0: int, central_seq0: int,
              error: float, late_central: bytes | None = None) -> None:
    """r1's truth from seq 0 to ``last_seq`` (stamps 0.1 s apart from 0), and D-SLAM's and central's estimates of
    it ``error`` metres off in y; the estimators' seq numbers go on from ``dslam_seq0`` and ``central_seq0``.
    ``late_central``: a central estimate that arrives just after the first truth."""
    for seq in range(last_seq + 1):
        stamp, pose = 0.1 * seq, true_pose(direction, seq)
        estimated = pose + np.array([0.0, error, 0.0])
        await evaluator.handle("truth", f"{PREFIX}/robots/r1/truth",
                               encode(GroundTruth(robot_id="r1", seq=seq, stamp=stamp, pose=pose)))
        if seq == 0 and late_central is not None:
            await evaluator.handle("central", f"{PREFIX}/central/estimate", late_central)
        await evaluator.handle("dslam_pose", f"{PREFIX}/dslam/pose/r1",
                               encode(PoseEstimate(robot_id="r1", seq=dslam_seq0 + seq, stamp=stamp, pose=estimated,
                                                   cov=np.eye(3) * 0.01)))
        await evaluator.handle("central", f"{PREFIX}/central/estimate", central(central_seq0 + seq, stamp, estimated))


def evaluator(tmp_path) -> Evaluator:
    return Evaluator(EvaluateSettings(prefix=PREFIX, out=str(tmp_path / "report")))


async def test_a_robot_that_left_and_starts_again_at_seq_0_is_scored_as_a_new_run(tmp_path):
    judge = evaluator(tmp_path)
    await run(judge, FIRST_RUN, 50, dslam_seq0=0, central_seq0=0, error=0.1)
    await judge.handle("gone", f"{PREFIX}/robots/r1/alive", b"")
    # central had not seen the new run yet: its estimate still carries the first run's last pose
    late = central(51, 5.0, true_pose(FIRST_RUN, 50) + np.array([0.0, 0.1, 0.0]))
    await run(judge, SECOND_RUN, 30, dslam_seq0=51, central_seq0=52, error=0.2, late_central=late)

    assert dict(judge.rejected) == {}
    assert judge.runs_ended == {"r1": 1}
    truth, trajectories = judge.collected()
    assert {rid: len(t) for rid, t in truth.items()} == {"r1#run1": 51, "r1": 31}
    for name in ("central", "dslam"):
        assert set(trajectories[name]) == {"r1#run1", "r1"}
        assert trajectories[name]["r1"].stamps.tolist() == pytest.approx([0.1 * k for k in range(31)])
    metrics, _ = judge.score()
    for name in ("central", "dslam"):
        ate = metrics["summary"][name]["ate_rmse_m"]
        assert ate["r1#run1"] == pytest.approx(0.1, abs=1e-9) and ate["r1"] == pytest.approx(0.2, abs=1e-9)
    await judge.tick()
    assert judge.extra["robot_restarts"] == 1.0 and judge.extra["robots_with_truth"] == 1.0


async def test_truth_going_back_while_the_token_stays_is_out_of_order(tmp_path):
    judge = evaluator(tmp_path)
    await run(judge, FIRST_RUN, 50, dslam_seq0=0, central_seq0=0, error=0.1)
    await run(judge, SECOND_RUN, 30, dslam_seq0=51, central_seq0=51, error=0.2)
    assert judge.rejected["out_of_order"] == 31  # the truth of seq 0..30 again
    assert judge.rejected["time_backwards"] == 31  # D-SLAM's poses going back to the start
    assert judge.runs_ended == {}
    truth, _ = judge.collected()
    assert {rid: len(t) for rid, t in truth.items()} == {"r1": 51}


def test_a_series_keeps_its_span_in_fixed_arrays_when_thinned():
    series = Series(limit=100)
    allocated = series.stamps.nbytes + series.poses.nbytes
    for k in range(1000):
        series.add(0.1 * k, np.array([0.1 * k, 0.0, 0.0]), np.eye(3) * k)
    path = series.trajectory()
    assert series.stamps.nbytes + series.poses.nbytes == allocated and series.covs.shape == (100, 3, 3)
    assert 50 <= len(path) <= 100
    assert path.stamps[0] == 0.0 and path.stamps[-1] == pytest.approx(99.9)
    assert np.all(np.diff(path.stamps) > 0)
    assert np.allclose(path.poses[:, 0], path.stamps) and np.allclose(path.covs[:, 0, 0], path.stamps * 10)


def test_a_series_replaces_a_repeated_stamp_and_drops_what_a_step_back_overtakes():
    series = Series(limit=100)
    for k in range(10):
        series.add(float(k), np.array([k, 0.0, 0.0]))
    series.add(9.0, np.array([90.0, 0.0, 0.0]), np.eye(3))  # the same stamp: replaced, with a covariance now
    assert len(series) == 10 and series.trajectory().poses[-1, 0] == 90.0
    series.add(4.5, np.array([-1.0, 0.0, 0.0]))  # back in time: the samples after 4.5 go
    path = series.trajectory()
    assert path.stamps.tolist() == [0.0, 1.0, 2.0, 3.0, 4.0, 4.5] and path.poses[-1, 0] == -1.0
    assert np.all(np.isnan(path.covs))  # only the dropped sample had one


def test_a_copy_scored_elsewhere_does_not_move_while_the_series_fills():
    series = Series(limit=4)
    for k in range(4):
        series.add(float(k), np.array([k, 0.0, 0.0]))
    path = series.trajectory()
    for k in range(4, 8):
        series.add(float(k), np.array([k, 0.0, 0.0]))  # thins in place
    assert path.stamps.tolist() == [0.0, 1.0, 2.0, 3.0]
