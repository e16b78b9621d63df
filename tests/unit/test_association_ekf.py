"""The EKF-SLAM baseline: runs with every association method, scores its decisions, follows one robot."""

from __future__ import annotations

import numpy as np
import pytest

from schemas.contract import OdomEvent, ScanEvent
from robots.simulator import simulate
from schemas.association import CLUTTER, NEW
from schemas.contract import RunOptions
from services.baselines.ekf_slam import EkfConfig, EkfSlam, make_estimator


def run(dataset, association: str, settings: dict | None = None):
    infos = [log.info for log in dataset.robots.values()]
    estimator = make_estimator(RunOptions(estimator="ekf", association=association, settings=settings or {}), infos)
    handlers = {OdomEvent: estimator.on_odometry, ScanEvent: estimator.on_scan}
    for event in dataset.events():
        handlers[type(event)](event)
    return estimator


@pytest.fixture(scope="module")
def paper_run():
    return simulate("paper000", seed=3, duration=20.0)


@pytest.mark.parametrize("association", ["known", "nn", "ihgr", "exact", "jcbb", "auto"])
def test_every_method_maps_the_paper_world(paper_run, association):
    estimator = run(paper_run, association)
    log = paper_run.robots["r1"]
    pose, cov = estimator.poses()["r1"]
    assert np.hypot(*(pose[:2] - log.truth_pose[-1, :2])) < 0.5
    assert np.allclose(estimator.P, estimator.P.T) and np.all(np.linalg.eigvalsh(estimator.P) > -1e-9)
    view = estimator.landmark_map()
    seen = np.unique(log.det_id[log.det_id >= 0])
    assert view.means.shape[0] >= seen.size * 0.8
    matched = [np.min(np.linalg.norm(paper_run.landmarks[view.ids[k]] - view.means[k])) for k in range(view.means.shape[0])]
    assert np.median(matched) < 0.3  # landmarks sit near the true landmark they were started from
    metrics = estimator.extra_metrics()
    assert metrics["association"] == association
    assert 0.5 < metrics["association_accuracy"] <= 1.0
    assert "success" in metrics and "success_criterion" in metrics
    if association == "known":
        assert metrics["success"] and metrics["association_accuracy"] == 1.0


def test_success_is_only_reported_on_the_paper_world():
    estimator = run(simulate("arena", seed=0, duration=5.0, robot_ids=["r1"]), "exact")
    assert "success" not in estimator.extra_metrics()
    assert estimator.extra_metrics()["association_accuracy"] is not None


def test_one_robot_of_a_fleet_is_followed():
    fleet = simulate("arena", seed=1, duration=5.0, robots=2)
    estimator = run(fleet, "exact")
    assert set(estimator.poses()) == {"r1"}
    alone = run(simulate("arena", seed=1, duration=5.0, robot_ids=["r1"]), "exact")
    np.testing.assert_allclose(estimator.poses()["r1"][0], alone.poses()["r1"][0])


def test_unknown_association_is_refused():
    info = simulate("paper000", seed=0, duration=1.0).robots["r1"].info
    with pytest.raises(ValueError, match="unknown association"):
        make_estimator(RunOptions(estimator="ekf", association="magic"), [info])
    with pytest.raises(ValueError):
        make_estimator(RunOptions(estimator="ekf", association="exact"), [])


def test_decisions_are_scored_against_the_true_ids():
    estimator = EkfSlam("exact", EkfConfig())
    estimator.origin = [7, 8]
    assignment = np.array([0, 1, NEW, NEW, CLUTTER, NEW])
    labels = np.array([0, 1, -1, -1, -1, -1])
    true_ids = np.array([7, 7, 9, 8, 5, -1])  # right, wrong, new ok, duplicate, rejected, clutter started
    estimator._score(assignment, labels, true_ids)
    assert (estimator.decisions, estimator.wrong, estimator.duplicates, estimator.rejected) == (6, 2, 1, 1)
