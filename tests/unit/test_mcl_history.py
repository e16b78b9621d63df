"""The scan history of Monte Carlo localization (services.mcl.history): poses drawn from a scan must also explain
the robot's earlier scans, carried back along its odometry."""

from __future__ import annotations

import math
import pickle

import numpy as np

from robots.models import se2_between, se2_compose, wrap_angle
from schemas.messages import RobotInfo, SensorSpec
from services.mcl.config import MclConfig
from services.mcl.core import MonteCarloLocalizer
from services.mcl.history import ScanHistory

R = np.diag([0.05**2, math.radians(1.0) ** 2])


def test_history_carries_a_present_pose_back_to_where_each_scan_was_taken():
    """With the world and the odometry in different frames, the true present pose is carried back onto the true
    pose of each earlier scan."""
    frame = np.array([3.0, -1.0, 0.7])  # the world pose of the odometry's origin
    odometry = [np.array([0.0, 0.0, 0.0]), np.array([1.0, 0.2, 0.3]), np.array([1.5, 1.0, 0.9])]
    history = ScanHistory(max_scans=5, max_turn=10.0)
    for pose in odometry[:2]:
        history.move(pose)
        history.add(np.array([[1.0, 0.0]]), None)
    history.move(odometry[2])
    seen = []

    def likelihood(poses, observations, targets):
        seen.append(poses.copy())
        return np.ones(poses.shape[0])

    present = se2_compose(frame, odometry[2])
    total = history.log_likelihood(present[None], likelihood)
    assert total.tolist() == [2.0]
    np.testing.assert_allclose(seen[0][0], se2_compose(frame, odometry[1]), atol=1e-12)  # newest first
    np.testing.assert_allclose(seen[1][0], se2_compose(frame, odometry[0]), atol=1e-12)
    np.testing.assert_allclose(se2_between(odometry[0], odometry[1]), se2_between(seen[1][0], seen[0][0]), atol=1e-12)


def test_history_keeps_the_last_scans_with_detections_until_the_robot_has_turned_too_far():
    history = ScanHistory(max_scans=2, max_turn=1.0)
    history.add(np.zeros((0, 2)), None)
    assert len(history) == 0  # a scan without detections is not kept
    for k in range(3):
        history.add(np.array([[1.0, float(k)]]), None)
    assert len(history) == 2 and [s.observations[0, 1] for s in history.usable()] == [2.0, 1.0]
    history.move(np.array([0.0, 0.0, 0.6]))
    history.add(np.array([[1.0, 3.0]]), None)
    history.move(np.array([0.0, 0.0, -0.1]))  # 0.7 rad back: 1.3 rad turned since the scan before last
    assert [s.observations[0, 1] for s in history.usable()] == [3.0]
    assert history.log_likelihood(np.zeros((4, 3)), lambda p, z, t: np.full(p.shape[0], -1.0)).tolist() == [-1.0] * 4
    history.clear()
    assert len(history) == 0
    assert ScanHistory(max_scans=0, max_turn=1.0).log_likelihood(np.zeros((3, 3)), None).tolist() == [0.0] * 3


def _localizer(history_scans: int) -> tuple[MonteCarloLocalizer, np.ndarray, np.ndarray]:
    """A robot that saw landmarks C and D, drove 2 m south, and now sees landmark A alone: the present scan fits
    a circle around every landmark, the earlier one only the true pose. Returns (filter, scan, true pose)."""
    landmarks = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 3.0], [-1.0, 3.5]])  # A, B (far away), C, D (next to A)
    spec = SensorSpec(max_range=2.5, fov=2 * math.pi, noise_cov=R)
    info = RobotInfo(robot_id="r1", stamp=0.0, motion_model="unicycle", sensor=spec, odom_rate_hz=1.0,
                     scan_rate_hz=1.0, start_pose=[-2.0, 2.0, -math.pi / 2])
    config = MclConfig(variant="mcl", history_scans=history_scans, seed=3)
    mcl = MonteCarloLocalizer(landmarks, info, config)
    # C and D seen from (-2, 2), facing south
    past = np.array([[math.hypot(2.0, 1.0), math.atan2(1.0, 2.0) + math.pi / 2],
                     [math.hypot(1.0, 1.5), math.atan2(1.5, 1.0) + math.pi / 2]])
    mcl.update(past)
    for _ in range(4):
        mcl.predict(np.array([0.5, 0.0]), 1.0, np.diag([1e-6, 1e-6]))
    return mcl, np.array([[2.0, math.pi / 2]]), np.array([-2.0, 0.0, -math.pi / 2])


def test_a_global_restart_weighs_the_poses_drawn_from_a_scan_by_the_earlier_scans():
    """One detection fits a circle around each of the four landmarks: without the history every pose drawn from
    it weighs the same and few lie near the truth; with it, most of the weight does."""
    def weight_near_truth(history_scans: int) -> float:
        mcl, scan, truth = _localizer(history_scans)
        mcl.initialize_global(scan, count=500)
        near = (np.hypot(*(mcl.particles[:, :2] - truth[:2]).T) < 0.5) & (
            np.abs(wrap_angle(mcl.particles[:, 2] - truth[2])) < 0.3)
        return float(mcl.weights[near].sum())

    assert weight_near_truth(0) < 0.1
    assert weight_near_truth(5) > 0.6


def test_poses_added_from_a_scan_pay_for_the_earlier_scans_the_tracked_particles_explain():
    """A tracked filter on the true pose: poses drawn from the ambiguous scan come out near the truth, and their
    evidence is charged the earlier scans' likelihood the tracked particles already explained."""
    mcl, scan, truth = _localizer(5)
    drawn, evidence = mcl._draw_from_scan(scan, 200)
    assert np.mean(np.hypot(*(drawn[:, :2] - truth[:2]).T) < 0.5) > 0.6
    plain, plain_evidence = _localizer(0)[0]._draw_from_scan(scan, 200)
    assert np.mean(np.hypot(*(plain[:, :2] - truth[:2]).T) < 0.5) < 0.2
    assert evidence < plain_evidence


def test_a_filter_pickled_before_the_history_existed_restores_with_an_empty_one():
    """A service checkpoint of an older filter (no ``history`` attribute) restores; the history then fills."""
    mcl, scan, _ = _localizer(5)
    old = mcl.__dict__.copy()
    del old["history"]
    restored = MonteCarloLocalizer.__new__(MonteCarloLocalizer)
    restored.__setstate__(old)
    assert len(restored.history) == 0 and restored.history.max_scans == 5
    restored.update(scan)
    assert len(restored.history) == 1
    again = pickle.loads(pickle.dumps(mcl))
    assert len(again.history) == len(mcl.history) == 1
