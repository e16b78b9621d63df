"""Metrics on hand-computed cases: ATE (raw, aligned), RPE, map error, association accuracy, NEES, timing."""

import math

import numpy as np
import pytest
from scipy.stats import chi2

from robots.models import fit_se2, transform_points
from services.evaluation.metrics import (
    Trajectory,
    association_accuracy,
    ate,
    fleet_alignment,
    interpolate_poses,
    map_alignment,
    map_error,
    nees,
    nees_summary,
    rpe,
    score_estimates,
    timing_stats,
    trajectory_metrics,
)


def _line(n=11, speed=1.0):
    t = np.arange(n, dtype=float)
    return t, np.column_stack([speed * t, np.zeros(n), np.zeros(n)])


def test_ate_of_a_constant_3_4_offset_is_5_raw_and_0_aligned():
    _, truth = _line()
    estimated = truth[:, :2] + [3.0, 4.0]
    assert ate(estimated, truth[:, :2])["rmse_m"] == pytest.approx(5.0)
    aligned = ate(estimated, truth[:, :2], align=True)
    assert aligned["rmse_m"] == pytest.approx(0.0, abs=1e-9)
    assert aligned["alignment"][:2] == pytest.approx([-3.0, -4.0])


def test_fit_se2_recovers_a_rigid_motion_and_alignment_removes_it():
    rng = np.random.default_rng(3)
    points = rng.uniform(-5, 5, (20, 2))
    motion = np.array([1.5, -2.0, math.radians(30.0)])
    moved = transform_points(motion, points)
    assert fit_se2(points, moved) == pytest.approx(motion)
    assert ate(points, moved, align=True)["rmse_m"] == pytest.approx(0.0, abs=1e-9)
    # Rotation is not scale: a shrunk copy keeps an error after alignment.
    assert ate(0.5 * points, moved, align=True)["rmse_m"] > 0.5


def test_rpe_of_a_10_percent_odometry_scale_error_is_0_1_m_per_second():
    t, truth = _line()
    estimated = truth.copy()
    estimated[:, 0] *= 1.1
    result = rpe(t, estimated, truth, delta_s=1.0)
    assert result["pairs"] == 10
    assert result["translation_rmse_m"] == pytest.approx(0.1)
    assert result["rotation_rmse_rad"] == pytest.approx(0.0)
    shifted = truth + [5.0, -2.0, 0.0]
    assert rpe(t, shifted, truth, 1.0)["translation_rmse_m"] == pytest.approx(0.0, abs=1e-12)


def test_rpe_sees_a_heading_drift_of_0_01_rad_per_second():
    t, truth = _line()
    estimated = truth.copy()
    estimated[:, 2] = 0.01 * t
    assert rpe(t, estimated, truth, 2.0)["rotation_rmse_rad"] == pytest.approx(0.02)


def test_map_error_matches_with_a_cutoff_and_counts_missed_and_spurious():
    truth = np.array([[0.0, 0.0], [10.0, 0.0]])
    estimated = np.array([[0.3, 0.4], [50.0, 50.0]])
    result = map_error(estimated, truth, cutoff=1.0)
    assert (result["matched"], result["missed"], result["spurious"]) == (1, 1, 1)
    assert result["rmse_m"] == pytest.approx(0.5)
    assert result["pairs"] == [[0, 0]]


def test_map_error_uses_the_optimal_assignment_not_greedy_nearest():
    truth = np.array([[0.0, 0.0], [1.0, 0.0]])
    estimated = np.array([[0.6, 0.0], [1.7, 0.0]])  # greedy: first -> (1,0) at 0.4, second unmatched
    result = map_error(estimated, truth, cutoff=1.0)
    assert result["matched"] == 2
    assert result["rmse_m"] == pytest.approx(math.sqrt((0.6**2 + 0.7**2) / 2))


def test_map_error_of_an_empty_map():
    result = map_error(np.zeros((0, 2)), np.ones((3, 2)))
    assert (result["matched"], result["missed"], result["spurious"], result["rmse_m"]) == (0, 3, 0, None)


def test_association_accuracy_by_majority_label():
    true_ids = [1, 1, 2, 2, -1, 3]
    labels = [7, 7, 8, 7, -1, -1]  # label 7 stands for 1, 8 for 2; the 4th is wrong, the last is a miss
    result = association_accuracy(true_ids, labels)
    assert result["correct"] == 4 and result["detections"] == 6
    assert result["accuracy"] == pytest.approx(4 / 6)
    assert result["labels"] == 2


def test_nees_hand_case_and_chi_square_bounds():
    assert nees(np.array([[1.0, 0.0]]), np.array([np.diag([4.0, 1.0])]))[0] == pytest.approx(0.25)
    single = nees_summary(np.array([1.0]), dof=2)
    assert single["lower"] == pytest.approx(chi2.ppf(0.025, 2))
    assert single["upper"] == pytest.approx(chi2.ppf(0.975, 2))


def test_nees_of_a_consistent_filter_is_inside_the_bounds_and_of_an_overconfident_one_outside():
    rng = np.random.default_rng(0)
    cov = np.array([[0.5, 0.1, 0.0], [0.1, 0.3, 0.0], [0.0, 0.0, 0.02]])
    errors = rng.multivariate_normal(np.zeros(3), cov, 2000)
    covs = np.broadcast_to(cov, (2000, 3, 3))
    good = nees_summary(nees(errors, covs), 3)
    assert good["consistent"] and good["lower"] < good["mean"] < good["upper"]
    assert good["within"] == pytest.approx(0.95, abs=0.02)
    bad = nees_summary(nees(3.0 * errors, covs), 3)
    assert not bad["consistent"] and bad["mean"] > bad["upper"]


def test_timing_stats_in_milliseconds():
    stats = timing_stats(np.arange(1, 101) / 1000.0)
    assert stats["median_ms"] == pytest.approx(50.5)
    assert stats["p99_ms"] == pytest.approx(99.01)
    assert stats["max_ms"] == pytest.approx(100.0)
    assert timing_stats(np.zeros(0))["median_ms"] is None


def test_interpolation_across_the_angle_wrap_and_gaps():
    stamps = np.array([0.0, 1.0, 5.0])
    poses = np.array([[0.0, 0.0, 3.1], [2.0, 0.0, -3.1], [6.0, 0.0, -3.1]])
    at = interpolate_poses(stamps, poses, np.array([0.5, 3.0, 7.0]), max_gap=1.5)
    assert at[0, 0] == pytest.approx(1.0)
    assert abs(at[0, 2]) == pytest.approx(math.pi, abs=1e-9)  # through π, not through 0
    assert np.all(np.isnan(at[1])) and np.all(np.isnan(at[2]))  # across the gap; outside the span
    exact = interpolate_poses(stamps, poses, np.array([5.0]), max_gap=1.5)
    assert exact[0, 0] == pytest.approx(6.0)


def test_trajectory_metrics_with_position_only_truth_at_an_antenna_offset():
    t = np.linspace(0, 10, 51)
    body = np.column_stack([t, np.zeros_like(t), np.full_like(t, 0.5)])
    antenna = (2.0, 0.5)
    gps = np.column_stack([transform_points(body, antenna), np.full_like(t, np.nan)])
    result = trajectory_metrics(Trajectory(t, body), Trajectory(t[::5], gps[::5]), truth_offset=antenna)
    assert result["ate_rmse_m"] == pytest.approx(0.0, abs=1e-9)
    assert result["gps_rmse_m"] == pytest.approx(0.0, abs=1e-9) and result["gps_fixes"] == 11
    assert "heading_rmse_rad" not in result and not result["heading_known"]
    plain = trajectory_metrics(Trajectory(t, body), Trajectory(t[::5], gps[::5]))
    assert plain["ate_rmse_m"] == pytest.approx(math.hypot(2.0 * math.cos(0.5) - 0.5 * math.sin(0.5),
                                                           2.0 * math.sin(0.5) + 0.5 * math.cos(0.5)))


def test_score_estimates_summarises_every_estimator():
    t, truth = _line()
    shifted = truth + [0.0, 1.0, 0.0]
    landmarks = np.array([[0.0, 5.0], [5.0, 5.0]])
    metrics, curves = score_estimates(
        {"a": {"r1": Trajectory(t, shifted)}}, {"r1": Trajectory(t, truth)},
        {"a": (landmarks + 0.1, None), "b": (np.zeros((0, 2)), None)}, landmarks)
    assert metrics["summary"]["a"]["ate_rmse_m"]["r1"] == pytest.approx(1.0)
    assert metrics["summary"]["a"]["landmarks"] == {"estimated": 2, "matched": 2, "missed": 0, "spurious": 0}
    assert metrics["summary"]["b"]["landmarks"]["missed"] == 2
    assert curves["a"]["r1"]["position_error_m"] == pytest.approx(np.ones(11))


def test_fleet_alignment_uses_one_transform_for_every_robot_and_the_antenna_point():
    """Two robots in a frame rotated and shifted from the truth's: one SE(2) lines both up (errors ~0); moving
    one robot alone shows as its error, not hidden by a transform of its own."""
    rng = np.random.default_rng(0)
    stamps = np.arange(0.0, 20.0, 0.1)
    frame = np.array([3.0, -2.0, 0.7])
    offset = (0.5, 0.2)
    truth, estimated = {}, {}
    for rid in ("r1", "r2"):
        poses = np.column_stack([np.cumsum(rng.normal(0.1, 0.02, stamps.size)), np.cumsum(rng.normal(0, 0.05, stamps.size)),
                                 np.cumsum(rng.normal(0, 0.02, stamps.size))])
        antenna = transform_points(poses, np.array(offset))
        world = transform_points(frame, antenna)
        truth[rid] = Trajectory(stamps, np.column_stack([world, np.full(stamps.size, np.nan)]))
        estimated[rid] = Trajectory(stamps, poses)
    fit = fleet_alignment(estimated, truth, truth_offset=offset)
    np.testing.assert_allclose(fit["transform"], frame, atol=1e-6)
    assert max(fit["ate_rmse_m"].values()) < 1e-6
    shifted = dict(estimated, r2=Trajectory(stamps, estimated["r2"].poses + np.array([2.0, 0.0, 0.0])))
    errors = fleet_alignment(shifted, truth, truth_offset=offset)["ate_rmse_m"]
    assert errors["r2"] > 0.5 and errors["r1"] > 0.5


def test_plotted_tracks_break_at_a_global_localization_jump():
    from services.evaluation.report import break_at_jumps

    track = np.column_stack([np.r_[np.linspace(0.0, 1.0, 20), np.linspace(30.0, 31.0, 20)], np.zeros(40)])
    broken = break_at_jumps(track)
    assert broken.shape == (41, 2) and np.isnan(broken[20]).all()
    np.testing.assert_array_equal(broken[~np.isnan(broken[:, 0])], track)
    smooth = np.column_stack([np.linspace(0.0, 10.0, 50), np.zeros(50)])
    assert break_at_jumps(smooth) is smooth


def test_map_alignment_registers_a_map_in_another_frame_among_spurious_landmarks():
    """A survey of 15 landmarks mapped in an anchor robot's frame (turned 2 rad, moved 7 m, 3 cm of noise) among
    20 spurious ones: the fit recovers the frame and counts the 15 within 0.3 m and the 20 as spurious; a map with
    one landmark gets no fit."""
    rng = np.random.default_rng(3)
    survey = rng.uniform([0.0, -5.5], [6.0, 5.5], (15, 2))
    frame = np.array([4.0, -3.0, 2.0])  # the survey in the anchor's frame: T⁻¹
    inverse = np.array([*(-transform_points(np.array([0.0, 0.0, -frame[2]]), frame[:2])), -frame[2]])
    mapped = transform_points(inverse, survey) + rng.normal(0.0, 0.03, survey.shape)
    spurious = rng.uniform([-12.0, -12.0], [12.0, 12.0], (20, 2))
    spurious = spurious[np.linalg.norm(transform_points(frame, spurious)[:, None] - survey[None], axis=-1).min(1) > 1.5]
    result = map_alignment(np.concatenate([spurious, mapped]), survey)
    np.testing.assert_allclose(result["transform"][:2], frame[:2], atol=0.05)
    assert abs(math.remainder(result["transform"][2] - frame[2], math.tau)) < 0.02
    assert result["within_inlier"] == 15 and result["landmarks"]["matched"] == 15
    assert result["landmarks"]["spurious"] == spurious.shape[0] and result["map_rmse_m"] < 0.06
    assert map_alignment(mapped[:1], survey) == {}
