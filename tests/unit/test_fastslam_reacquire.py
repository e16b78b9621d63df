"""Re-acquisition of a robot blind too long (central/fastslam/reacquire.py): its drift, the search for one rigid
correction of its recent detections, and the filter that holds its scans until the correction is clear."""

from __future__ import annotations

import dataclasses
import math
import pickle

import numpy as np
import pytest

from central.fastslam import kernels, reacquire, robot_detections
from central.fastslam.config import FastSlamConfig
from central.fastslam.core import FastSlam
from robots.models import RangeBearingSensor, se2_compose, wrap_angle
from robots.simulator import simulate
from schemas.contract import OdomEvent, ScanEvent

CONFIG = FastSlamConfig(association="shared")


def test_drift_is_the_covariance_of_dead_reckoning():
    """Monte Carlo: poses composed from noisy relative motions spread as the accumulated drift says, the heading's
    error carried into position along the path; a turn adds the announced slip per radian."""
    rng = np.random.default_rng(0)
    delta, cov = np.array([0.1, 0.0, 0.06]), np.diag([1e-4, 4e-5, 2e-4])
    start, steps, samples = np.array([1.0, -2.0, 0.4]), 25, 20000
    drift, mean = None, start.copy()
    for _ in range(steps):
        drift = reacquire.accumulate(drift, mean[2], delta, cov, 0.0)
        mean = se2_compose(mean, delta)
    poses = np.broadcast_to(start, (samples, 3)).copy()
    for _ in range(steps):
        poses = se2_compose(poses, delta + rng.multivariate_normal(np.zeros(3), cov, samples))
    empirical = np.cov((poses - mean).T)
    np.testing.assert_allclose(empirical, drift, rtol=0.1, atol=2e-4)
    slipped = reacquire.accumulate(None, 0.0, np.array([0.0, 0.0, -0.5]), np.zeros((3, 3)), 0.015)
    assert slipped[2, 2] == pytest.approx(0.015 * 0.5) and not slipped[:2].any()


def test_a_robot_is_lost_once_its_drift_passes_either_threshold():
    assert not reacquire.lost(CONFIG, None)
    assert not reacquire.lost(CONFIG, np.diag([0.3**2, 0.3**2, 0.1**2]))
    assert reacquire.lost(CONFIG, np.diag([0.3**2, 0.3**2, 0.2**2]))
    assert reacquire.lost(CONFIG, np.diag([0.1**2, 0.5**2, 0.01**2]))


def arena(seed: int = 0) -> np.ndarray:
    """15 landmarks in clusters over 6 m × 10 m, like MR.CLAM's."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform([-1.0, -4.0], [5.0, 4.0], (6, 2))
    return np.concatenate([c + rng.normal(0.0, 0.15, (k, 2)) for c, k in zip(centres, (3, 3, 3, 2, 2, 2))])


def detections_from(truth_points: np.ndarray, correction: reacquire.Correction, seed: int = 1) -> np.ndarray:
    """What a robot that is off by the inverse of ``correction`` would place: the true points moved away."""
    noisy = truth_points + np.random.default_rng(seed).normal(0.0, 0.03, truth_points.shape)
    return reacquire.turned(noisy - correction.shift, correction.centre, -correction.turn)


@pytest.mark.parametrize("turn, shift", [(math.radians(25.0), (0.4, -0.3)), (math.radians(-12.0), (-0.8, 0.5)),
                                         (0.0, (0.0, 0.0))])
def test_search_finds_the_correction_that_puts_the_detections_back_on_the_map(turn, shift):
    landmarks = arena()
    centre = np.array([2.0, 0.0])
    seen = landmarks[np.hypot(*(landmarks - centre).T) < 4.0]
    assert len(seen) >= 4
    truth = reacquire.Correction(turn, np.array(shift), centre, 0.0, 0)
    points = detections_from(np.repeat(seen, 3, axis=0), truth)
    found = reacquire.search(points, landmarks, centre, math.radians(45.0), 2.0, CONFIG.reacquire_rule)
    assert found is not None
    assert abs(found.turn - turn) < math.radians(2.0)
    moved = found.apply(np.column_stack([points, np.zeros(len(points))]))[:, :2]
    assert np.hypot(*(moved - np.repeat(seen, 3, axis=0)).T).max() < 0.2  # a cluster's neighbour may pull a little
    assert np.hypot(*(moved - np.repeat(seen, 3, axis=0)).mean(0)) < 0.05  # the shift fitted, not the vote's cell
    assert found.detections == len(points) and found.landmarks >= 6


def test_search_refuses_what_the_detections_cannot_decide():
    landmarks = arena()
    centre = np.array([2.0, 0.0])
    one = np.repeat(landmarks[:1], 8, axis=0) + 0.01
    assert reacquire.search(one, landmarks, centre, 0.5, 1.0, CONFIG.reacquire_rule) is None  # one landmark: the turn is free
    few = landmarks[:2] + 0.01
    assert reacquire.search(few, landmarks, centre, 0.5, 1.0, CONFIG.reacquire_rule) is None  # fewer than min_detections
    pair = np.array([[0.0, 0.0], [0.5, 0.0], [3.0, 3.0]])  # only two landmarks 0.5 m apart seen: the turn is loose
    points = np.repeat(pair[:2], 5, axis=0) + 0.1
    assert reacquire.search(points, pair, np.zeros(2), 0.0, 0.3, CONFIG.reacquire_rule) is None
    loose_span = CONFIG.model_copy(update={"reacquire_span_m": 0.4}).reacquire_rule
    assert reacquire.search(points, pair, np.zeros(2), 0.0, 0.3, loose_span)
    three = dataclasses.replace(loose_span, min_landmarks=3)  # two landmarks reached, three wanted
    assert reacquire.search(points, pair, np.zeros(2), 0.0, 0.3, three) is None
    grid = np.array([(x, y) for x in range(6) for y in range(6)], float)  # a lattice 1 m apart: shifts by 1 m tie
    points = np.repeat(grid[[7, 8, 13, 14]], 3, axis=0) + 0.3
    assert reacquire.search(points, grid, np.array([1.5, 1.5]), 0.0, 2.0, CONFIG.reacquire_rule) is None
    inside = reacquire.search(points, grid, np.array([1.5, 1.5]), 0.0, 0.5, CONFIG.reacquire_rule)  # a window of one cell decides
    assert inside is not None and np.allclose(inside.shift, [-0.3, -0.3], atol=0.02)


def test_confirm_takes_the_dead_reckoning_when_one_landmark_cannot_pin_the_turn():
    """A robot counted as lost whose dead reckoning held sees one landmark at a time: the rigid search cannot fix
    its turn, but a correction within the drift's σ that explains every detection is taken (the smallest); one
    beyond it, or one that a distinct correction out-explains, is not."""
    landmarks = np.array([[3.0, 0.0], [0.0, 5.0], [-4.0, -4.0]])
    centre, sigmas = np.zeros(2), (0.1, 0.2)  # σ heading (rad), σ position (m)
    rule = CONFIG.reacquire_rule
    assert rule.confirm_sigmas > 0.0  # on by default
    rng = np.random.default_rng(3)
    seen = landmarks[0] + np.array([0.06, -0.04]) + rng.normal(0.0, 0.02, (8, 2))  # 7 cm off: within the drift
    found = reacquire.search(seen, landmarks, centre, 0.5, 1.0, rule, sigmas)
    assert found is not None and abs(found.turn) <= 0.1 and np.hypot(*found.shift) <= 0.2
    moved = found.apply(np.column_stack([seen, np.zeros(len(seen))]))[:, :2]
    assert np.hypot(*(moved.mean(0) - landmarks[0])) < 0.03
    off = dataclasses.replace(rule, confirm_sigmas=0.0)
    assert reacquire.search(seen, landmarks, centre, 0.5, 1.0, off, sigmas) is None  # the rigid rule alone refuses
    assert reacquire.search(seen, landmarks, centre, 0.5, 1.0, rule) is None  # no drift given: nothing to confirm
    far = landmarks[0] + np.array([0.0, 1.0]) + rng.normal(0.0, 0.02, (8, 2))  # 1 m off: beyond 1σ
    assert reacquire.search(far, landmarks, centre, 0.5, 1.0, rule, sigmas) is None
    wider = dataclasses.replace(rule, confirm_sigmas=4.0, confirm_max_turn=0.4, confirm_max_shift=0.8, prior_weight=0.0)
    assert reacquire.search(far, landmarks, centre, 0.5, 1.0, wider, sigmas) is not None
    other = landmarks[1] + np.array([0.6, 0.0]) + rng.normal(0.0, 0.02, (10, 2))  # a 0.6 m shift explains these 10
    both = np.concatenate([seen[:6], other])
    counted = dataclasses.replace(rule, prior_weight=0.0)  # corrections by their detections alone
    assert reacquire.search(both, landmarks, centre, 0.0, 1.0, counted, sigmas) is None  # out-explained: 4 > margin 3
    taken = reacquire.search(both, landmarks, centre, 0.0, 1.0, rule, sigmas)  # the prior: 10 at 3σ against 6 at 0.4σ
    assert taken is not None and np.hypot(*taken.shift) <= 0.2


def test_confirm_tolerance_takes_the_nearest_of_the_corrections_that_explain_about_as_much():
    """One landmark leaves the turn free: the turns of a window all explain about as many detections, and the best
    of them by a fraction (the prior's, a point at the inlier's edge) can be the edge of the window. With a tolerance
    the confirmation takes, of those within it of the best, the one nearest the dead reckoning."""
    landmarks = np.array([[3.0, 0.0], [0.0, 5.0], [-4.0, -4.0]])
    centre, sigmas = np.zeros(2), (0.2, 0.2)
    rng = np.random.default_rng(5)
    seen = landmarks[0] + rng.normal(0.0, 0.03, (8, 2))
    plain = dataclasses.replace(CONFIG.reacquire_rule, confirm_max_turn=0.2, confirm_max_shift=0.5, prior_weight=0.0)
    scored = [(8.0, 0.18, np.array([0.02, 0.1]), np.zeros(8, int)), (7.5, 0.0, np.array([0.01, 0.0]), np.zeros(8, int))]
    assert reacquire.confirm(scored, plain, sigmas)[1] == 0.18  # the best by half a detection, 0.9σ of turn away
    tolerant = dataclasses.replace(plain, confirm_tolerance=1.0)
    assert reacquire.confirm(scored, tolerant, sigmas)[1] == 0.0  # within a detection of it: the dead reckoning
    assert reacquire.confirm([(8.0, 0.18, scored[0][2], scored[0][3]), (6.5, 0.0, scored[1][2], scored[1][3])],
                             tolerant, sigmas)[1] == 0.18  # 1.5 detections fewer: not within the tolerance
    found = reacquire.search(seen, landmarks, centre, 0.2, 0.5, tolerant, sigmas)
    assert found is not None and abs(found.turn) < 0.02  # the whole search: no turn where none is needed


def test_a_match_conditions_the_drift_on_what_its_landmarks_pin():
    """``condition``: the Kalman update of the drift by matched detections equals the information form
    (D⁻¹ + Hᵀ Q⁻¹ H)⁻¹; one landmark leaves most of the heading's variance (the turn about it is free), two
    landmarks far apart pin it."""
    info = simulate("arena", robots=1, duration=1.0).robots["r1"].info
    sensor = FastSlam(FastSlamConfig(particles=4, association="shared"), [info]).robots["r1"].sensor
    pose, drift = np.array([1.0, 2.0, 0.3]), np.diag([0.25, 0.25, 0.06])  # σ 0.5 m, 14°
    noise = np.diag([0.01, 0.001])

    def conditioned(points: np.ndarray) -> np.ndarray:
        h_x, _ = sensor.jacobians(np.broadcast_to(pose, (len(points), 3)), points)
        out = reacquire.condition(drift, h_x, np.broadcast_to(noise, (len(points), 2, 2)))
        h = h_x.reshape(-1, 3)
        q_inv = np.kron(np.eye(len(points)), np.linalg.inv(noise))
        np.testing.assert_allclose(out, np.linalg.inv(np.linalg.inv(drift) + h.T @ q_inv @ h), atol=1e-12)
        return out

    one = conditioned(np.array([[2.5, 2.4]]))
    two = conditioned(np.array([[2.5, 2.4], [0.2, 4.0]]))
    assert one[2, 2] > 0.5 * drift[2, 2]  # the turn about one landmark stays mostly free
    assert two[2, 2] < 0.05 * one[2, 2]  # two landmarks 2.8 m apart pin it
    assert max(one[0, 0], one[1, 1]) < 0.5 * drift[0, 0]  # the position along the landmark is pinned


def test_the_drift_prior_decides_between_corrections_that_explain_as_much():
    """Two copies of a landmark pattern 1.2 m apart: two corrections explain every detection, and the rigid rule
    refuses; weighed by the drift's Gaussian, the one near the dead reckoning wins by more than the margin."""
    pattern = np.array([[1.0, 0.0], [0.0, 1.2], [-1.0, 0.3], [0.4, -1.0]])
    landmarks = np.concatenate([pattern, pattern + [1.0, 0.6]])
    points = np.repeat(pattern, 3, axis=0) + [0.1, -0.05] + np.random.default_rng(5).normal(0.0, 0.01, (12, 2))
    centre, sigmas = np.zeros(2), (0.05, 0.2)
    rule = dataclasses.replace(CONFIG.reacquire_rule, confirm_sigmas=0.0)  # the prior alone
    assert rule.prior_weight > 0.0  # on by default
    found = reacquire.search(points, landmarks, centre, 0.0, 2.0, rule, sigmas)
    assert found is not None and np.allclose(found.shift, [-0.1, 0.05], atol=0.02)
    flat = dataclasses.replace(rule, prior_weight=0.0)
    assert reacquire.search(points, landmarks, centre, 0.0, 2.0, flat, sigmas) is None
    assert reacquire.search(points, landmarks, centre, 0.0, 2.0, rule) is None  # no drift given: no prior
    wide = (0.05, 5.0)  # a drift this wide cannot tell the two apart by the margin
    assert reacquire.search(points, landmarks, centre, 0.0, 2.0, rule, wide) is None


def thrown_off_run(data, slam: FastSlam, drift: np.ndarray | None, turn_deg: float = 25.0) -> tuple[float, float]:
    """Feed ``data`` to ``slam``; 30 s after r1's first scan throw its estimate ``turn_deg`` and 0.5 m off (a blind
    turn on slipping wheels, or a wrong correction) with ``drift`` as its drift. (r1's final position error, heading
    error)."""
    log = data.robots["r1"]
    thrown = False
    for event in data.events():
        if not thrown and event.stamp - log.scan_stamp[0] >= 30.0:
            pose, _ = slam.poses()["r1"]
            error = reacquire.Correction(math.radians(turn_deg), np.array([0.4, -0.3]), pose[:2], 0.0, 0)
            column = slam.robots["r1"].index
            slam.pose[:, column] = error.apply(slam.pose[:, column])
            slam.robots["r1"].drift = drift
            thrown = True
        if isinstance(event, OdomEvent):
            slam.on_odometry(event)
        elif isinstance(event, ScanEvent):
            slam.on_scan(event)
    pose, _ = slam.poses()["r1"]
    return float(np.hypot(*(pose[:2] - log.truth_pose[-1, :2]))), abs(wrap_angle(pose[2] - log.truth_pose[-1, 2]))


def lost_robot_run(seed: int, reacquire_on: bool) -> tuple[float, float, int, FastSlam]:
    """One robot maps the MR.CLAM-like arena for 30 s; then its estimate is thrown off by 25° and 0.5 m, as a
    blind turn on slipping wheels would, with a drift that says so; it drives on for 30 s. (final position error,
    heading error, landmarks mapped, the filter)."""
    data = simulate("arena", robots=1, seed=seed, duration=60.0)
    slam = FastSlam(FastSlamConfig(particles=30, association="shared", seed=seed, reacquire=reacquire_on),
                    [data.robots["r1"].info])
    error, heading = thrown_off_run(data, slam, np.diag([0.3**2, 0.3**2, math.radians(25.0) ** 2]))
    return error, heading, len(slam.landmark_map().means), slam


def test_a_lost_robot_is_put_back_on_the_map_instead_of_mapping_a_copy():
    """Without re-acquisition the robot's next detections are paired from the wrong pose: it ends metres off and
    maps spurious landmarks (seeds 0 and 2); with it, its scans are held until one correction explains them."""
    for seed in (0, 2):
        error, heading, landmarks, slam = lost_robot_run(seed, True)
        assert slam.counts["reacquire_started"] == 1 and slam.counts["reacquired"] == 1
        assert slam.counts["detections_blind"] > 0
        assert error < 0.3 and heading < math.radians(4.0)
        plain_error, _, plain_landmarks, plain = lost_robot_run(seed, False)
        assert plain.counts["reacquired"] == 0 and plain_error > 1.0 and plain_landmarks > landmarks
    assert slam.robots["r1"].blind is None


def test_detections_of_other_robots_contradict_a_robot_only_when_most_are_unexplained_and_of_two_robots():
    """The last window's detections of robots decide; older ones are dropped. One robot seen wrongly is not enough (it
    may be the one that is off), nor a few unexplained among many explained ones."""
    robot = FastSlam(FastSlamConfig(association="shared"), [simulate("arena", robots=1, seed=0, duration=1.0)
                                                            .robots["r1"].info]).robots["r1"]
    robot.robot_checks = [(t, "r2" if t % 2 else "r3", False) for t in range(6)]
    assert reacquire.contradicted(robot, 5.0, 10.0, 6)
    assert not reacquire.contradicted(robot, 12.0, 10.0, 6) and len(robot.robot_checks) == 4  # two fell out
    robot.robot_checks = [(t, "r2", False) for t in range(8)]
    assert not reacquire.contradicted(robot, 8.0, 10.0, 6)  # one robot: either of the two may be off
    robot.robot_checks = [(t, "r2" if t % 2 else "r3", t < 6) for t in range(12)]
    assert not reacquire.contradicted(robot, 12.0, 20.0, 6)  # 6 unexplained of 12
    config = FastSlamConfig(association="shared")
    wide = reacquire.widened(None, config.reacquire_max_shift_m, config.reacquire_max_turn)
    assert reacquire.lost(config, wide) and math.sqrt(wide[2, 2]) * reacquire.SIGMAS == pytest.approx(config.reacquire_max_turn)


def test_robot_detections_in_the_window_decide_between_corrections_the_landmarks_cannot():
    """Three landmarks in a row 1.2 m apart, two of them seen from a pose 1.2 m along the row: no shift and one of
    −1.2 m explain every detection alike, so the search refuses; four detections of a robot, each with where that
    robot was, decide it."""
    landmarks = np.array([[3.0, 0.0], [3.0, 1.2], [3.0, 2.4]])
    rng = np.random.default_rng(1)
    points = np.repeat(landmarks[:2] + [0.0, 1.2], 5, axis=0) + rng.normal(0.0, 0.02, (10, 2))
    centre, rule = np.zeros(2), CONFIG.reacquire_rule
    assert reacquire.search(points, landmarks, centre, 0.0, 2.0, rule) is None
    robot_at = np.array([[1.0, -1.0], [1.2, -0.8], [1.4, -0.6], [1.6, -0.4]])
    pairs = np.column_stack([robot_at + [0.0, 1.2] + rng.normal(0.0, 0.05, (4, 2)), robot_at])
    found = reacquire.search(points, landmarks, centre, 0.0, 2.0, rule, robot_pairs=pairs)
    assert found is not None and np.allclose(found.shift, [0.0, -1.2], atol=0.05)
    window = reacquire.BlindWindow(robots=[(0.0, pair) for pair in pairs])
    restored = pickle.loads(pickle.dumps(window))
    del restored.__dict__["robots"]  # a window pickled before it kept robot detections
    restored.__setstate__(dict(restored.__dict__))
    assert restored.robot_pairs() is None and window.robot_pairs().shape == (4, 4)


def test_a_held_robots_detection_of_a_robot_is_placed_from_its_weighted_mean_pose():
    """Particles straddling ±π average to heading π, not 0 (the arithmetic mean would put the point behind the
    robot), and the weights decide between them: a particle of weight zero moves neither end."""
    sensor = RangeBearingSensor()
    pose = np.array([[1.0, 2.0, math.pi - 0.01], [1.0, 2.0, -math.pi + 0.01], [9.0, 9.0, 0.0]])
    target = np.array([[-1.0, 2.0], [-1.0, 2.0], [5.0, 5.0]])
    point = robot_detections.window_point(sensor, pose, target, np.array([0.5, 0.5, 0.0]), np.array([2.0, 0.0]))
    assert np.allclose(point, [-1.0, 2.0, -1.0, 2.0], atol=1e-9)


def test_a_held_window_moves_with_the_robots_estimate_but_not_with_its_odometry():
    """Points placed from one pose stay put while the estimate moves by the odometry, applied between scans or
    buffered at the scan; when the estimate jumps (the shared particles resampled), every point and every robot
    detection's point jumps with it, the seen robots' positions do not."""
    sensor, z = RangeBearingSensor(), np.array([[2.0, 0.3], [4.0, -1.0]])
    before, step = np.array([1.0, 2.0, 0.4]), np.array([0.5, 0.1, 0.2])
    window = reacquire.BlindWindow()
    window.follow(before, None)
    window.add(0.0, sensor.inverse(before, z), 30.0)
    window.robots.append((0.0, np.r_[sensor.inverse(before, z[:1])[0], 7.0, 8.0]))
    window.moved(step)  # applied between two scans (an empty scan, a full buffer)
    window.follow(se2_compose(se2_compose(before, step), step), step)  # the next scan, one step buffered
    assert np.allclose(window.points[0], sensor.inverse(before, z))
    window.moved(step)
    after = np.array([1.3, 1.6, -0.3])  # the pose the points were seen from, as the resampled estimate has it
    window.follow(se2_compose(se2_compose(se2_compose(after, step), step), step), step)
    assert np.allclose(window.points[0], sensor.inverse(after, z))
    assert np.allclose(window.robots[0][1], np.r_[sensor.inverse(after, z[:1])[0], 7.0, 8.0])
    restored = reacquire.BlindWindow(robots=[])
    del restored.__dict__["reckoned"], restored.__dict__["odometry"]  # a window pickled before it kept its pose
    del restored.__dict__["contradicted"]  # ... or why it was held
    restored.__setstate__(dict(restored.__dict__))
    assert restored.reckoned is None and np.array_equal(restored.odometry, np.zeros(3))
    assert restored.contradicted is False


def robots_seen_run(on: bool, turn_deg: float = 25.0, **settings) -> tuple[float, float, FastSlam]:
    """Three robots that see each other map the arena for 30 s; then r1's estimate is thrown ``turn_deg`` and 0.5 m
    off with a drift that says all is well (a wrong correction). (r1's final position error, heading error, the
    filter)."""
    data = simulate("arena", robots=3, seed=2, duration=60.0)
    slam = FastSlam(FastSlamConfig(particles=30, association="shared", seed=2, reacquire_by_robots=on, **settings),
                    [robot.info for robot in data.robots.values()])
    return (*thrown_off_run(data, slam, None, turn_deg), slam)


def test_a_robot_sure_of_a_wrong_pose_is_put_back_when_the_robots_it_sees_contradict_it():
    """Its drift says nothing is wrong, so only its detections of the other two robots can: with
    ``reacquire_by_robots`` (the default) they count it as lost and one correction puts it back; without, it stays
    off."""
    assert FastSlamConfig(association="shared").reacquires_by_robots
    assert not FastSlamConfig(association="known").reacquires_by_robots  # re-acquisition is the shared association's
    error, heading, slam = robots_seen_run(True)
    assert slam.counts["reacquire_contradicted"] >= 1 and slam.counts["reacquired"] >= 1
    assert error < 0.2 and heading < math.radians(4.0)
    plain_error, plain_heading, plain = robots_seen_run(False)
    assert plain.counts["reacquire_started"] == 0 and plain_error > 0.5 and plain_heading > math.radians(8.0)


def test_a_robot_half_a_turn_off_is_put_back_by_the_robots_it_sees():
    """With the landmarks' search capped at 45° (``reacquire_max_turn``), 160° is beyond it. With
    ``reacquire_robots_veto`` (off by default in FastSLAM, on in D-SLAM) the corrections within it that the landmarks
    offer are refused while they leave most of its robot detections off their robots, until the rigid fit of those
    detections onto the robots puts it back; without the fit it stays off. Uncapped (the default), the landmarks'
    search finds the half turn itself."""
    capped = {"reacquire_robots_veto": 3, "reacquire_max_turn": math.radians(45.0)}
    error, heading, slam = robots_seen_run(True, 160.0, **capped)
    assert slam.counts["reacquired_by_robots"] >= 1
    assert error < 0.2 and heading < math.radians(4.0)
    plain_error, plain_heading, plain = robots_seen_run(True, 160.0, **capped, reacquire_robots_fit_min=10**6)
    assert plain.counts["reacquired_by_robots"] == 0 and plain_error > 1.0 and plain_heading > math.radians(45.0)
    error, heading, uncapped = robots_seen_run(True, 160.0, reacquire_robots_veto=3)
    assert uncapped.counts["reacquired"] >= 1 and error < 0.2 and heading < math.radians(4.0)


def test_the_robots_fit_takes_any_turn_and_refuses_what_the_pairs_cannot_fix():
    """Detections of robots seen from a pose 150° and 1 m off: the least-squares fit gives the correction back. Too
    few pairs, pairs bunched in one spot (the turn is free) or a pair the fit leaves far from its robot: no fit.
    :func:`reacquire.beyond_caps` takes it only for a window the robots contradicted, beyond the search's caps,
    and when the pose as it is leaves most pairs off their robots."""
    rng = np.random.default_rng(4)
    robots_at = rng.uniform(-3.0, 3.0, (8, 2))
    centre = np.array([0.5, -0.5])
    truth = reacquire.Correction(math.radians(150.0), np.array([1.0, 0.3]), centre, 0.0, 0)
    undo = math.radians(-150.0)
    seen = reacquire.turned(robots_at - truth.shift, centre, undo) + rng.normal(0.0, 0.03, (8, 2))
    pairs = np.column_stack([seen, robots_at])
    fit = reacquire.robots_fit(pairs, centre, 6, 0.5, 0.4)
    assert fit is not None and abs(wrap_angle(fit.turn - truth.turn)) < math.radians(2.0)
    assert np.allclose(fit.apply(np.r_[seen[0], 0.0])[:2], robots_at[0], atol=0.1)
    assert reacquire.robots_fit(pairs[:5], centre, 6, 0.5, 0.4) is None
    bunched = np.column_stack([seen[:1].repeat(8, 0) + rng.normal(0.0, 0.05, (8, 2)), robots_at[:1].repeat(8, 0)])
    assert reacquire.robots_fit(bunched, centre, 6, 0.5, 0.4) is None
    wrong = pairs.copy()
    wrong[0, 2:] += [2.0, 0.0]
    assert reacquire.robots_fit(wrong, centre, 6, 0.5, 0.4) is None
    window = reacquire.BlindWindow(contradicted=True, robots=[(0.0, pair) for pair in pairs])
    assert reacquire.beyond_caps(window, centre, math.radians(45.0), 2.0, 6, 0.5, 0.4) is not None
    assert reacquire.beyond_caps(window, centre, math.pi, 5.0, 6, 0.5, 0.4) is None  # within the caps
    held_for_drift = reacquire.BlindWindow(robots=window.robots)
    assert reacquire.beyond_caps(held_for_drift, centre, math.radians(45.0), 2.0, 6, 0.5, 0.4) is None

    def about_centre(near: int, far: int) -> reacquire.BlindWindow:
        """Robots seen from a pose turned 150° about its own position: those seen near it are explained either way."""
        at = np.vstack([centre + rng.normal(0.0, 0.04, (near, 2)), rng.uniform(-3.0, 3.0, (far, 2))])
        seen_from = reacquire.turned(at, centre, undo)
        return reacquire.BlindWindow(contradicted=True, robots=[(0.0, np.r_[p, q]) for p, q in zip(seen_from, at)])

    assert reacquire.beyond_caps(about_centre(3, 6), centre, math.radians(45.0), 2.0, 6, 0.5, 0.25) is not None
    assert reacquire.beyond_caps(about_centre(5, 4), centre, math.radians(45.0), 2.0, 6, 0.5, 0.25) is None


def test_a_correction_that_leaves_the_robots_off_is_refused():
    """Landmarks alone take the shift of 1.2 m; four robot detections that the shift leaves off their robots veto
    it once the window holds ``robots_veto`` of them."""
    landmarks = np.array([[3.0, 0.0], [3.0, 1.2], [6.0, 0.5]])
    rng = np.random.default_rng(2)
    points = np.repeat(landmarks + [0.0, 1.2], 4, axis=0) + rng.normal(0.0, 0.02, (12, 2))
    centre = np.zeros(2)
    robot_at = np.array([[1.0, -1.0], [1.2, -0.8], [1.4, -0.6], [1.6, -0.4]])
    pairs = np.column_stack([robot_at + rng.normal(0.0, 0.05, (4, 2)), robot_at])  # the robots say: no shift
    rule = CONFIG.reacquire_rule
    assert reacquire.search(points, landmarks, centre, 0.0, 2.0, dataclasses.replace(rule, robots_veto=0),
                            robot_pairs=pairs) is not None
    assert reacquire.search(points, landmarks, centre, 0.0, 2.0, dataclasses.replace(rule, robots_veto=3),
                            robot_pairs=pairs) is None
    assert reacquire.search(points, landmarks, centre, 0.0, 2.0, dataclasses.replace(rule, robots_veto=5),
                            robot_pairs=pairs) is not None


def test_drift_grows_while_blind_and_levels_off_while_matching():
    """A robot that sees nothing accumulates drift scan after scan. One that matches landmarks has its drift
    conditioned on them at every match (the default), so it levels off far below the blind one's; with
    ``reacquire_drift_update`` off it starts again from zero at every match (then the proposal adds that scan's
    motion)."""
    data = simulate("arena", robots=1, seed=0, duration=8.0)
    info = data.robots["r1"].info
    drifts = {}
    for blind, update in ((True, True), (False, True), (False, False)):
        config = FastSlamConfig(particles=10, association="shared", seed=0, confirm_hits=1, reacquire_drift_update=update,
                                motion_noise_scale=1.0)
        slam = FastSlam(config, [info])
        robot, seen = slam.robots["r1"], []
        for event in data.events():
            if isinstance(event, OdomEvent):
                slam.on_odometry(event)
            elif isinstance(event, ScanEvent):
                if blind:
                    event = dataclasses.replace(event, ranges=np.zeros(0), bearings=np.zeros(0), landmark_ids=None)
                slam.on_scan(event)
                seen.append(0.0 if robot.drift is None else robot.drift[2, 2])
        drifts[blind, update] = np.array(seen)
        assert (slam.counts["detections_matched"] > 0) != blind
    grown = drifts[True, True][drifts[True, True] > 0]
    assert len(grown) > 5 and np.all(np.diff(grown) > 0)
    conditioned, reset = drifts[False, True], drifts[False, False]
    assert conditioned.max() < 0.1 * grown[-1] and conditioned[-1] > 0.0
    assert conditioned[-1] <= conditioned[-10] and np.ptp(conditioned[-10:]) < 0.1 * conditioned[-1]  # level
    assert reset.max() < 0.05 * grown[-1]  # at most the motion since the last matched scan


def vote_inputs(layout: str, seed: int) -> tuple:
    """The Hough vote's inputs as :func:`reacquire.search` makes them: ``clusters`` of landmarks (a point's pairs
    with two close landmarks fall in one bin), a ``lattice`` 1 m apart (equal votes: the order of ties decides),
    or ``far`` (no pair within the shift limit)."""
    rng = np.random.default_rng(seed)
    if layout == "lattice":
        landmarks = np.array([(x, y) for x in range(6) for y in range(6)], float)
        points = np.repeat(landmarks[rng.choice(36, 6, replace=False)], 3, axis=0) + rng.normal(0.3, 0.02, (18, 2))
    else:
        landmarks = arena(seed)
        points = rng.uniform([-1.0, -4.0], [5.0, 4.0], (30, 2))
        points = np.concatenate([points, points[:10] + rng.normal(0.0, 0.01, (10, 2))])
    if layout == "far":
        points += 50.0
    cells, weights = np.unique(np.round(points / reacquire.POINT_QUANTUM) * reacquire.POINT_QUANTUM, axis=0,
                               return_counts=True)
    turns = np.arange(-0.4, 0.4 + 1e-12, reacquire.TURN_STEP)
    centre = rng.uniform(0.0, 3.0, 2)
    return cells, weights, landmarks, centre, turns, 1.5, CONFIG.reacquire_inlier_m, reacquire.SHIFTS_PER_TURN


@pytest.mark.parametrize("layout, seed", [("clusters", 0), ("clusters", 1), ("clusters", 2), ("lattice", 0),
                                          ("lattice", 1), ("lattice", 2), ("far", 0)])
def test_vote_kernel_scores_the_same_shifts_in_the_same_order_as_the_reference(layout, seed):
    """Entry for entry: the later sort is stable, so among equal scores the order of the entries picks the
    correction."""
    inputs = vote_inputs(layout, seed)
    reference = reacquire.vote_reference(*inputs)
    compiled = kernels.vote(*inputs)
    assert len(compiled) == len(reference)
    assert (len(reference) == 0) == (layout == "far")
    for (score, turn, shift, reached), (score_ref, turn_ref, shift_ref, reached_ref) in zip(compiled, reference):
        assert score == score_ref and turn == turn_ref
        np.testing.assert_allclose(shift, shift_ref, rtol=0.0, atol=1e-9)
        np.testing.assert_array_equal(reached, reached_ref)


@pytest.mark.parametrize("layout, seed", [("clusters", 0), ("lattice", 1), ("lattice", 3), ("far", 1)])
def test_search_gives_the_same_correction_with_the_kernel(layout, seed):
    cells, weights, landmarks, centre, turns, shift_limit, _, _ = vote_inputs(layout, seed)
    points = np.repeat(cells, weights, axis=0)
    found = {}
    for compiled in (True, False):
        rule = CONFIG.model_copy(update={"compiled": compiled}).reacquire_rule
        found[compiled] = reacquire.search(points, landmarks, centre, turns[-1], shift_limit, rule)
    assert (found[True] is None) == (found[False] is None)
    if found[True] is not None:
        assert found[True].turn == found[False].turn
        np.testing.assert_allclose(found[True].shift, found[False].shift, rtol=0.0, atol=1e-9)
        assert (found[True].detections, found[True].landmarks) == (found[False].detections, found[False].landmarks)


def test_the_kernel_finds_the_correction_of_the_search_test():
    """The compiled vote on the case :func:`test_search_finds_the_correction_that_puts_the_detections_back_on_the_map`
    checks: the same correction as the reference."""
    landmarks = arena()
    centre = np.array([2.0, 0.0])
    seen = landmarks[np.hypot(*(landmarks - centre).T) < 4.0]
    truth = reacquire.Correction(math.radians(25.0), np.array([0.4, -0.3]), centre, 0.0, 0)
    points = detections_from(np.repeat(seen, 3, axis=0), truth)
    found = [reacquire.search(points, landmarks, centre, math.radians(45.0), 2.0,
                              CONFIG.model_copy(update={"compiled": compiled}).reacquire_rule) for compiled in (True, False)]
    assert found[0] is not None and found[1] is not None
    assert found[0].turn == found[1].turn and found[0].detections == found[1].detections
    np.testing.assert_allclose(found[0].shift, found[1].shift, rtol=0.0, atol=1e-9)


def _correction(turn: float, centre, shift) -> reacquire.Correction:
    return reacquire.Correction(turn, np.asarray(shift, float), np.asarray(centre, float), 10.0, 3)


def test_a_correction_is_taken_only_when_the_next_search_with_new_detections_agrees():
    """One window's chance alignment (a turn of 40°) is not confirmed by the next search, which finds the true
    correction; that one needs its own confirmation, with new detections in between; the same detections searched
    again confirm nothing."""
    window = reacquire.BlindWindow()
    position = np.array([1.0, 2.0])
    window.add(0.0, np.zeros((6, 2)), 15.0)
    assert not window.confirms(_correction(math.radians(40.0), position, [0.3, -0.2]), position, 2, 5, 0.4)
    window.add(0.5, np.zeros((6, 2)), 15.0)
    true = _correction(math.radians(5.0), position, [0.1, 0.1])
    assert not window.confirms(true, position, 2, 5, 0.4)  # disagrees with the 40° one: a new candidate
    assert not window.confirms(true, position, 2, 5, 0.4)  # no new detections since: no confirmation yet
    window.add(1.0, np.zeros((6, 2)), 15.0)
    # the same world transform found about another centre (the robot moved on): the same correction
    moved = position + np.array([0.5, 0.0])
    again = reacquire.rigid(true.turn, true.centre, true.shift)
    shift = again[:2, :2] @ moved + again[:2, 2] - moved
    assert window.confirms(_correction(true.turn, moved, shift), moved, 2, 5, 0.4)
    assert reacquire.BlindWindow().confirms(true, position, 1, 5, 0.4)  # one confirmation: at once (the old rule)


def test_a_candidate_correction_follows_the_window_when_the_estimate_jumps():
    """The window's points move with the robot's estimate (resampling by other robots' scans); the candidate moves
    with them, so the same correction of the moved points is recognised as a confirmation."""
    window = reacquire.BlindWindow()
    pose = np.array([0.0, 0.0, 0.0])
    window.follow(pose, None)
    window.add(0.0, np.array([[2.0, 0.0], [3.0, 1.0]]), 15.0)
    first = _correction(0.3, pose[:2], [0.2, 0.0])
    assert not window.confirms(first, pose[:2], 2, 1, 0.4)
    jumped = np.array([0.5, -0.5, 0.3])  # farther than a distinct correction: without following, no confirmation
    window.follow(jumped, None)
    window.add(0.5, np.array([[2.0, 0.5]]), 15.0)
    # the map-frame target of every point is unchanged: the correction of the jumped points is A ∘ jump⁻¹
    expected = reacquire.rigid(0.3, pose[:2], [0.2, 0.0]) @ np.linalg.inv(reacquire.rigid(0.3, pose[:2], [0.5, -0.5]))
    turn = math.atan2(expected[1, 0], expected[0, 0])
    centre = jumped[:2]
    shift = expected[:2, :2] @ centre + expected[:2, 2] - centre
    assert window.confirms(_correction(turn, centre, shift), centre, 2, 1, 0.4)


def test_a_robot_turned_past_the_old_caps_is_searched_as_far_as_its_drift_says():
    """A robot thrown 70° and 0.5 m off, with a drift that says so: the search reaches 3σ of the drift (the caps
    default to half a turn and 8 m, bounds of the work rather than of the answer) and puts it back; with the old caps
    (45°, 2 m, fitted on MR.CLAM 6) the correction it needs lies outside them and the robot stays off."""
    def run(**caps) -> tuple[float, float, FastSlam]:
        data = simulate("arena", robots=1, seed=0, duration=60.0)
        slam = FastSlam(FastSlamConfig(particles=30, association="shared", seed=0, **caps), [data.robots["r1"].info])
        drift = np.diag([0.4**2, 0.4**2, math.radians(40.0) ** 2])
        return (*thrown_off_run(data, slam, drift, turn_deg=70.0), slam)

    assert FastSlamConfig().reacquire_max_turn >= math.pi - 1e-3
    error, heading, slam = run()
    assert slam.counts["reacquired"] >= 1 and error < 0.3 and heading < math.radians(4.0)
    capped_error, capped_heading, capped = run(reacquire_max_turn=0.785, reacquire_max_shift_m=2.0)
    assert capped_error > 1.0 and capped_heading > math.radians(20.0)
