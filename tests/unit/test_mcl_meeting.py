"""Detections between a robot being localized and a placed robot (:mod:`services.mcl.meeting`): their
likelihood and draws against simulated detections, the pose a robot's meetings fix on their own, and what a
meeting does to a Monte Carlo localizer."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robots.models import RangeBearingSensor, se2_accumulate, se2_compose, wrap_angle
from services.mcl.config import MclConfig
from services.mcl.core import MonteCarloLocalizer
from schemas.contract import OdomEvent, ScanEvent
from scipy.optimize._numdiff import approx_derivative

from services.mcl.meeting import (GATE, Meeting, MeetingDesk, MeetingLog, PlacedPoses, _forward_differences,
                                  _residual_function, draw, log_likelihood)
from robots.simulator import simulate

OTHER_SENSOR, OWN_SENSOR = RangeBearingSensor((0.1, 0.0)), RangeBearingSensor((0.2, 0.05))
NOISE = np.diag([0.02, 0.003])
OTHER_COV = np.diag([0.02, 0.01, 0.002])


def simulated_meeting(rng: np.random.Generator, robot: np.ndarray, other_true: np.ndarray, by_other: bool) -> Meeting:
    """A detection between ``robot`` and the other robot, with the noise of the detection and of the other's pose."""
    other_estimate = other_true + rng.multivariate_normal(np.zeros(3), OTHER_COV)
    if by_other:
        z = OTHER_SENSOR.observe(other_true, robot[None, :2])[0]
    else:
        z = OWN_SENSOR.observe(robot, other_true[None, :2])[0]
    z = z + rng.multivariate_normal(np.zeros(2), NOISE)
    return Meeting(other_estimate, OTHER_COV, z, NOISE, by_other, OTHER_SENSOR)


@pytest.mark.parametrize("by_other", [True, False])
def test_a_meeting_at_the_true_pose_is_chi_square_and_its_draws_are_where_it_says(by_other):
    """Over many simulated meetings the true pose's d² averages the degrees of freedom (2): the covariance carried
    from the other robot's pose and the detection is right. The draws of one meeting lie where it says (d² of 2 on
    average too), and a pose 1 m away is far outside the gate."""
    rng = np.random.default_rng(7)
    robot, other = np.array([1.5, -0.5, 2.0]), np.array([-1.0, 0.8, -0.4])
    d2 = [log_likelihood(robot[None], simulated_meeting(rng, robot, other, by_other), OWN_SENSOR)[1][0]
          for _ in range(3000)]
    assert 1.85 < np.mean(d2) < 2.15
    meeting = simulated_meeting(rng, robot, other, by_other)
    drawn = draw(meeting, OWN_SENSOR, 4000, rng)
    assert 1.8 < np.mean(log_likelihood(drawn, meeting, OWN_SENSOR)[1]) < 2.2
    _, far = log_likelihood((robot + [1.0, 0.0, 0.0])[None], meeting, OWN_SENSOR)
    assert far[0] > GATE
    loglik, d2_robot = log_likelihood(np.stack([robot, robot + [5.0, 0.0, 0.0]]), meeting, OWN_SENSOR)
    assert loglik[0] > loglik[1] and d2_robot[1] > GATE  # capped, yet below the pose that explains it


def robot_path(frame: np.ndarray, steps: int, step: np.ndarray):
    """A robot driving ``step`` per reading from its odometry origin, ``frame`` in the world: (odometry, world) poses."""
    odometry = se2_accumulate(np.tile(step, (steps, 1)))[1:]
    return odometry, se2_compose(frame, odometry)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_robots_meetings_fix_its_pose_once_they_are_enough(seed):
    """Meetings of both kinds with placed robots, each at the robot's dead-reckoned pose then: none with two, then
    the robot's present pose within a few centimetres, with a covariance that covers the error."""
    rng = np.random.default_rng(seed)
    frame = np.array([rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(-math.pi, math.pi)])
    odometry, world = robot_path(frame, 8, np.array([0.25, 0.0, 0.08]))
    log = MeetingLog()
    fixes = []
    for k in range(8):
        log.move(odometry[k])
        other = world[k] + np.array([rng.uniform(-3, 3), rng.uniform(-3, 3), rng.uniform(-3, 3)])
        log.add(simulated_meeting(rng, world[k], other, by_other=k % 2 == 0))
        fixes.append(log.solve(OWN_SENSOR))
    assert fixes[0] is None and fixes[1] is None
    fix = fixes[-1]
    assert fix is not None and fix.meetings == 8
    error = np.append(fix.pose[:2] - world[-1][:2], wrap_angle(fix.pose[2] - world[-1][2]))
    assert np.hypot(*error[:2]) < 0.15 and abs(error[2]) < 0.05
    assert error @ np.linalg.solve(fix.cov, error) < 16.3  # χ²(3) 99.9 %


@pytest.mark.parametrize("shared", [True, False])
def test_the_solves_jacobian_is_scipys_forward_differences_from_one_batched_call(shared):
    """The meetings' residuals of a batch of unknowns are each row's own residuals, and their Jacobian by forward
    differences in one batched call is scipy's ``2-point`` Jacobian (the solves took it from there before)."""
    rng = np.random.default_rng(4)
    frame = np.array([1.0, -2.0, 0.7])
    odometry, world = robot_path(frame, 10, np.array([0.25, 0.0, 0.08]))
    log = MeetingLog()
    for k in range(10):
        log.move(odometry[k])
        other = world[k] + np.array([2.0, 1.0 - 0.2 * k, 0.4])
        meeting = simulated_meeting(rng, world[k], other, by_other=k % 3 == 0)
        log.add(Meeting(meeting.other_pose, meeting.other_cov, meeting.z, meeting.noise_cov, meeting.by_other,
                        meeting.other_sensor, "r2" if k % 2 else "r3"))
    entries = log.usable()
    batch, others = _residual_function(entries, np.array([e.odometry for e in entries]), OWN_SENSOR, shared)
    assert others == (2 if shared else 0)
    unknowns = np.concatenate([frame + [0.05, -0.03, 0.02], rng.normal(0.0, 0.05, 3 * others)])
    unknowns[1] = -1e-3  # a negative unknown: the step takes its sign
    rows = np.vstack([unknowns, unknowns + 0.1, -unknowns])
    together = batch(rows)
    for row, residuals in zip(rows, together):
        np.testing.assert_allclose(batch(row[None])[0], residuals, rtol=1e-12, atol=1e-12)
    one = lambda x: batch(x[None])[0]  # noqa: E731
    np.testing.assert_allclose(_forward_differences(batch)(unknowns), approx_derivative(one, unknowns),
                               rtol=1e-5, atol=1e-5)  # the residuals agree to rounding, over a step of 1e-8
    at_zero = np.array(unknowns)
    at_zero[0] = 0.0
    np.testing.assert_allclose(_forward_differences(batch)(at_zero), approx_derivative(one, at_zero),
                               rtol=1e-5, atol=1e-5)


def test_meetings_with_one_robot_count_its_pose_error_once():
    """Twelve meetings with one placed robot whose estimate is off by one error, drawn from its covariance: the
    fix's covariance covers the fix's error (d² of χ²(3) on average, 3). Counted as twelve independent errors it
    was about four times too small (d² 12 on average over these draws)."""
    cov = np.diag([0.01, 0.01, 0.003])
    d2 = []
    for seed in range(60):
        rng = np.random.default_rng(seed)
        frame = np.array([rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(-math.pi, math.pi)])
        odometry, world = robot_path(frame, 12, np.array([0.25, 0.0, 0.06]))
        error = rng.multivariate_normal(np.zeros(3), cov)  # the placed robot's, in all its meetings
        log = MeetingLog(max_std_xy=10.0, max_std_theta=10.0)
        for k in range(12):
            log.move(odometry[k])
            other = world[0] + np.array([2.0 + 0.1 * k, 1.0, 0.5])
            by_other = k % 2 == 0
            z = (OTHER_SENSOR.observe(other, world[k][None, :2]) if by_other
                 else OWN_SENSOR.observe(world[k], other[None, :2]))[0] + rng.multivariate_normal(np.zeros(2), NOISE)
            log.add(Meeting(other + error, cov, z, NOISE, by_other, OTHER_SENSOR, "r2"))
        fix = log.solve(OWN_SENSOR)
        if fix is not None:
            miss = np.append(fix.pose[:2] - world[-1][:2], wrap_angle(fix.pose[2] - world[-1][2]))
            d2.append(miss @ np.linalg.solve(fix.cov, miss))
    assert len(d2) >= 50
    assert 2.2 < np.mean(d2) < 4.5


def test_meetings_that_do_not_fix_the_heading_or_disagree_fix_nothing():
    """A robot standing still seen by placed robots: its position is known, its heading not — no fix. A meeting
    from a placed robot whose pose is 3 m wrong: inconsistent — no fix either."""
    rng = np.random.default_rng(4)
    robot = np.array([2.0, 1.0, 0.7])
    still = MeetingLog()
    for _ in range(10):
        other = robot + np.array([rng.uniform(-3, 3), rng.uniform(-3, 3), 0.0])
        still.add(simulated_meeting(rng, robot, other, by_other=True))
    assert len(still) == 10 and still.solve(OWN_SENSOR) is None
    odometry, world = robot_path(np.zeros(3), 6, np.array([0.3, 0.0, 0.1]))
    liar = MeetingLog()
    for k in range(6):
        liar.move(odometry[k])
        other = world[k] + np.array([2.0, -1.0, 0.3])
        meeting = simulated_meeting(rng, world[k], other, by_other=k % 2 == 1)
        if k == 5:
            meeting = Meeting(meeting.other_pose + [3.0, 0.0, 0.0], OTHER_COV, meeting.z, NOISE, True, OTHER_SENSOR)
        liar.add(meeting)
    assert liar.solve(OWN_SENSOR) is None
    assert liar.contradicts(world[-1], OWN_SENSOR)
    liar.entries.pop()
    assert liar.solve(OWN_SENSOR) is not None and not liar.contradicts(world[-1], OWN_SENSOR)
    assert liar.contradicts(se2_compose(world[-1], [0.0, 0.0, math.pi]), OWN_SENSOR)  # the twin of a half turn


def test_a_meeting_no_particle_agrees_with_starts_the_localization_from_it():
    """Particles all on the twin of the truth: the meeting restarts the localizer from the poses it allows, and
    its next update is a fresh start; a meeting some particle agrees with changes nothing."""
    data = simulate("arena", robots=1, seed=0, duration=1.0)
    info = data.robots["r1"].info
    truth = data.robots["r1"].truth_pose[0]
    mcl = MonteCarloLocalizer(data.landmarks, info.model_copy(update={"start_pose": None}), MclConfig(seed=0),
                              np.random.default_rng(0))
    twin = np.array([-truth[0], -truth[1], wrap_angle(truth[2] + math.pi)])
    mcl.initialize_at(twin, np.diag([0.01, 0.01, 0.001]))
    rng = np.random.default_rng(1)
    other = truth + np.array([1.5, 0.5, 0.2])
    meeting = simulated_meeting(rng, truth, other, by_other=True)
    assert mcl.meet(meeting) and mcl.meetings == 1
    apart = np.hypot(*(mcl.particles[:, :2] - truth[:2]).T)
    assert np.median(apart) < 0.35 and (apart < 1.0).mean() > 0.95  # the meeting's spread: the other's pose and the detection
    kept = mcl.particles.copy()
    assert not mcl.meet(simulated_meeting(rng, truth, other, by_other=True))
    np.testing.assert_array_equal(mcl.particles, kept)
    scan = data.robots["r1"]
    report = mcl.update(np.stack([scan.det_range[: scan.scan_offsets[1]], scan.det_bearing[: scan.scan_offsets[1]]], -1))
    assert report.particles_after == mcl.config.particles and report.added == 0  # a fresh start: nothing drawn on top


@pytest.mark.parametrize("bearing_std, fixed", [(1.0, False), (0.05, True)])
def test_two_mirror_poses_that_explain_the_meetings_alike_fix_nothing(bearing_std, fixed):
    """A robot standing still sees two placed robots: their ranges allow two positions, mirrored across the line
    between them, which only the bearings tell apart. With bearings as good as useless both explain the meetings
    about as well: ambiguous, no fix (the precision limits are lifted to isolate the check); with good bearings,
    the true one."""
    rng = np.random.default_rng(11)
    robot, first, second = np.array([1.0, 2.0, 0.3]), np.array([-1.0, -1.0, 0.0]), np.array([3.0, -1.5, 1.0])
    noise = np.diag([0.0004, bearing_std**2])
    log = MeetingLog(max_std_xy=100.0, max_std_theta=100.0)
    for other in (first, second, first, second):
        z = OWN_SENSOR.observe(robot, other[None, :2])[0] + rng.multivariate_normal(np.zeros(2), noise)
        log.add(Meeting(other, np.diag([1e-6, 1e-6, 1e-8]), z, noise, False))
    fix = log.solve(OWN_SENSOR)
    assert (fix is not None) == fixed
    if fixed:
        assert np.hypot(*(fix.pose[:2] - robot[:2])) < 0.1


def test_placed_poses_carry_a_lagging_or_early_estimate_to_the_scans_instant():
    """A placed robot's dead reckoning (odometry frame turned and shifted from the world) and estimates of its true
    pose that come late, or ahead of its readings: its pose at any instant of the trail is the truth then; an
    estimate ahead waits for the reading it belongs to; instants outside the trail have no pose."""
    frame = np.array([2.0, -1.0, 0.7])
    odometry, world = robot_path(frame, 50, np.array([0.1, 0.0, 0.05]))
    stamps = 0.1 * np.arange(1, 51)
    placed = PlacedPoses(trail=40, ahead_s=0.25)
    cov = np.diag([0.01, 0.01, 0.001])
    for k in range(30):
        placed.move("r1", stamps[k], odometry[k])
    assert "r1" not in placed and placed.pose_at("r1", stamps[20]) is None
    placed.estimate("r1", stamps[40], world[40], cov)  # ahead of the readings: kept until they reach it
    assert "r1" not in placed
    placed.estimate("r1", stamps[12], world[12], cov)  # late: taken at once
    for k in (5, 20, 29):
        pose, got_cov = placed.pose_at("r1", stamps[k])
        np.testing.assert_allclose(pose, world[k], atol=1e-9)
        np.testing.assert_array_equal(got_cov, cov)
    assert placed.pose_at("r1", stamps[29] + 0.2) is not None and placed.pose_at("r1", stamps[29] + 0.3) is None
    wrong = se2_compose(world[40], [0.5, 0.0, 0.0])
    placed.estimate("r1", stamps[45], wrong, cov)  # waits behind the one at stamps[40]
    for k in range(30, 42):
        placed.move("r1", stamps[k], odometry[k])
    np.testing.assert_allclose(placed.pose_at("r1", stamps[41])[0], world[41], atol=1e-9)
    for k in range(42, 50):
        placed.move("r1", stamps[k], odometry[k])
    np.testing.assert_allclose(placed.pose_at("r1", stamps[45])[0], wrong, atol=1e-9)  # the later estimate took over
    assert placed.pose_at("r1", stamps[5]) is None  # older than the trail of 40 readings
    placed.forget("r1")
    assert "r1" not in placed and placed.pose_at("r1", stamps[49]) is None


def test_the_desk_finds_meetings_either_way_and_solves_every_few():
    """A scan's detections are meetings only between a robot being localized and a placed one, in either
    direction; the desk keeps them on the robot's dead reckoning and solves its pose every ``solve_every``
    meetings, and a localizer that agrees with the meeting is not started again."""
    data = simulate("arena", robots=2, seed=0, duration=2.0)
    infos = {rid: log.info for rid, log in data.robots.items()}
    desk = MeetingDesk(solve_every=3)
    for info in infos.values():
        desk.add_robot(info)
    scan = ScanEvent("r1", 0, 0.0, np.zeros(0), np.zeros(0), None, np.diag([0.01, 0.001]), ["r2", "r3"],
                     np.array([2.0, 3.0]), np.array([0.1, -0.2]))
    localizing, placed = {"r2"}.__contains__, {"r1", "r3"}.__contains__
    found = desk.sightings(scan, localizing, placed)
    assert [(s.subject, s.other, s.by_other) for s in found] == [("r2", "r1", True)]
    np.testing.assert_array_equal(found[0].z, [2.0, 0.1])
    back = ScanEvent("r2", 0, 0.0, np.zeros(0), np.zeros(0), None, np.diag([0.01, 0.001]), ["r1"], np.array([2.0]),
                     np.array([-0.1]))
    assert [(s.subject, s.other, s.by_other) for s in desk.sightings(back, localizing, placed)] == [("r2", "r1", False)]
    assert desk.sightings(scan, set().__contains__, placed) == []  # between placed robots: no meeting

    truth = data.robots["r2"].truth_pose[0]
    desk.move(OdomEvent("r2", 0, 0.1, 0.1, np.zeros(2), np.eye(2) * 1e-6))
    rng = np.random.default_rng(3)
    mcl = MonteCarloLocalizer(data.landmarks, infos["r2"].model_copy(update={"start_pose": None}), MclConfig(seed=0),
                              np.random.default_rng(0))
    mcl.place(truth, np.diag([0.01, 0.01, 0.001]))
    assert mcl.localized
    fixes = []
    for k in range(6):
        other = truth + np.array([rng.uniform(-3, 3), rng.uniform(-3, 3), rng.uniform(-3, 3)])
        restarted, fix = desk.meet("r2", simulated_meeting(rng, truth, other, by_other=k % 2 == 0), mcl)
        assert not restarted
        fixes.append(fix)
    assert [f is not None for f in fixes] == [False, False, True, False, False, True]
    assert np.hypot(*(fixes[-1].pose[:2] - truth[:2])) < 0.5  # the meetings were simulated with other sensor offsets
    assert desk.meet("r2", simulated_meeting(rng, truth, truth + [2.0, 0, 0], True), mcl, solve=False)[1] is None
    assert not desk.contradicts("r2", truth) and desk.contradicts("r2", truth + np.array([1.0, 0.0, 0.0]))
