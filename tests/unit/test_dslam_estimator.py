"""The D-SLAM estimator end to end on simulated data: exactness without noise, consistency, several robots, clutter."""

import dataclasses
import pickle

import numpy as np
import pytest
from scipy.stats import chi2

from robots.models import wrap_angle
from robots.simulator import simulate
from robots.worlds import make_world
from schemas.contract import OdomEvent, RunOptions, ScanEvent
from services.dslam.config import DslamConfig
from services.dslam.core import DSlam
from services.estimators import make_estimator


def run(estimator, data):
    for log in data.robots.values():
        if not estimator.has_robot(log.robot_id):
            estimator.add_robot(log.info)
    feed(estimator, data.events())
    return estimator


def feed(estimator, events):
    for event in events:
        if isinstance(event, OdomEvent):
            estimator.on_odometry(event)
        elif isinstance(event, ScanEvent):
            estimator.on_scan(event)


def quiet(world_name: str, seed: int = 0):
    """A world whose sensor and odometry are (almost) noiseless."""
    world = make_world(world_name, seed)
    sensor = world.sensor.model_copy(update={"noise_cov": np.diag([1e-14, 1e-16])})
    return dataclasses.replace(world, sensor=sensor, control_std=(1e-9, 1e-9))


def pose_error(estimator, data, rid):
    pose, cov = estimator.poses()[rid]
    log = data.robots[rid]
    truth = log.truth_at(np.array([log.scan_stamp[-1]]))[0]
    error = pose - truth
    error[2] = (error[2] + np.pi) % (2 * np.pi) - np.pi
    return error, cov


def test_registered_as_dslam():
    data = simulate("arena", robots=1, duration=1.0)
    estimator = make_estimator(RunOptions(estimator="dslam"), [data.robots["r1"].info])
    assert isinstance(estimator, DSlam)


def test_noiseless_data_give_the_exact_map_and_poses():
    data = simulate(quiet("grid196"), robots=1, seed=0, duration=25.0)
    estimator = run(make_estimator(RunOptions(estimator="dslam"), [data.robots["r1"].info]), data)
    view = estimator.landmark_map()
    assert view.means.shape[0] >= 8
    np.testing.assert_allclose(view.means, data.landmarks[view.ids], atol=1e-5)
    error, _ = pose_error(estimator, data, "r1")
    assert np.max(np.abs(error)) < 1e-5


def test_grid_map_is_consistent_and_sparse():
    data = simulate("grid196", robots=1, seed=3, duration=30.0)
    estimator = run(DSlam(DslamConfig()), data)
    view = estimator.landmark_map()
    n = view.means.shape[0]
    nees = estimator.map.normalised_error(data.landmarks[view.ids])
    assert nees < chi2.ppf(0.999, 2 * n)
    pattern = estimator.map.matrix.tocsr().toarray().reshape(n, 2, n, 2).any(axis=(1, 3))
    i, j = np.nonzero(pattern)
    gaps = np.linalg.norm(view.means[i] - view.means[j], axis=1)
    assert gaps.max() <= 2 * data.robots["r1"].info.sensor.max_range  # links only between features seen together
    error, cov = pose_error(estimator, data, "r1")
    assert error @ np.linalg.solve(cov, error) < chi2.ppf(0.999, 3)


def test_robots_feed_one_map_and_an_unknown_start_is_placed():
    data = simulate("grid196", robots=2, seed=1, duration=20.0)
    infos = [data.robots["r1"].info, data.robots["r2"].info.model_copy(update={"start_pose": None, "start_pose_cov": None})]
    estimator = run(make_estimator(RunOptions(estimator="dslam"), infos), data)
    assert estimator.counts["robots_placed"] == 1
    error, _ = pose_error(estimator, data, "r2")
    assert np.hypot(error[0], error[1]) < 0.3
    view = estimator.landmark_map()
    assert np.sqrt(np.mean(np.sum((view.means - data.landmarks[view.ids]) ** 2, axis=1))) < 0.2


def test_clutter_stays_out_of_the_map_with_association():
    data = simulate("arena", robots=1, seed=2, duration=25.0, clutter_rate=1.0)
    config = DslamConfig(association="auto", confirm_hits=3, tentative_misses=2)
    estimator = run(DSlam(config), data)
    view = estimator.landmark_map()
    distance = np.linalg.norm(view.means[:, None] - data.landmarks[None], axis=-1).min(axis=1)
    assert view.means.shape[0] >= 10
    assert np.sum(distance > 0.5) <= 1
    assert estimator.counts["tentative_dropped"] > 5


def test_bad_input_is_counted_not_fatal():
    data = simulate("arena", robots=1, duration=2.0)
    estimator = DSlam()
    estimator.add_robot(data.robots["r1"].info)
    scan = data.robots["r1"].scan(0)
    scan.ranges = np.concatenate([scan.ranges, [np.nan, -1.0]])
    scan.bearings = np.concatenate([scan.bearings, [0.0, 0.0]])
    scan.landmark_ids = np.concatenate([scan.landmark_ids, [1, 2]])
    estimator.on_scan(scan)
    stranger = data.robots["r1"].odom(0)
    stranger.robot_id = "r9"
    estimator.on_odometry(stranger)
    assert estimator.counts["bad_observations"] == 2 and estimator.counts["unknown_robot"] == 1


def test_a_robot_whose_start_was_missed_has_no_pose():
    data = simulate("arena", robots=1, duration=2.0)
    estimator = DSlam()
    estimator.add_robot(data.robots["r1"].info)
    estimator.on_odometry(data.robots["r1"].odom(5))
    assert "r1" not in estimator.poses() and estimator.counts["missed_start"] == 1


def test_two_measurements_of_one_feature_are_set_aside():
    data = simulate("grid196", robots=1, duration=1.0)
    estimator = DSlam()
    estimator.add_robot(data.robots["r1"].info)
    scan = data.robots["r1"].scan(0)
    scan.ranges = np.concatenate([scan.ranges, scan.ranges[:1] + 0.5])
    scan.bearings = np.concatenate([scan.bearings, scan.bearings[:1]])
    scan.landmark_ids = np.concatenate([scan.landmark_ids, scan.landmark_ids[:1]])
    estimator.on_scan(scan)
    assert estimator.counts["assoc_shared_landmark"] == 2
    assert estimator.map.n == len(set(scan.landmark_ids.tolist())) - 1



def test_the_turn_slip_a_robot_announces_widens_the_association_gate_until_the_heading_is_observed():
    """A robot announcing turn_slip_var gets that much heading variance per radian turned added to the pose covariance
    its detections are gated with, not to its pose; ``turn_slip=False`` or a robot announcing none adds nothing, and
    a full-rank localization starts the sum again."""
    data = simulate("arena", robots=1, duration=1.0)
    info = data.robots["r1"].info.model_copy(update={"turn_slip_var": 0.02})
    cov = np.diag([1e-4, 1e-4])
    events = [OdomEvent("r1", k, 0.1 * (k + 1), 0.1, np.array([0.5, -0.4]), cov) for k in range(10)]

    def gate_and_pose(config: DslamConfig, robot_info) -> tuple[float, float]:
        estimator = DSlam(config)
        estimator.add_robot(robot_info)
        for event in events:
            estimator.on_odometry(event)
        robot = estimator.robots["r1"]
        _, _, request = estimator.association_request(robot, np.array([[2.0, 0.1]]), np.diag([0.01, 0.001]))
        return float(request.pose_cov[2, 2]), float(robot.cov[2, 2])

    plain_gate, plain_pose = gate_and_pose(DslamConfig(turn_slip=False), info)
    gate, pose = gate_and_pose(DslamConfig(), info)
    assert gate - plain_gate == pytest.approx(0.02 * 0.4, rel=1e-9)
    assert pose == pytest.approx(plain_pose, rel=1e-12)
    assert gate_and_pose(DslamConfig(), data.robots["r1"].info)[0] == pytest.approx(plain_gate, rel=1e-12)

    mapped = simulate("grid196", robots=1, seed=0, duration=20.0)
    slipping = mapped.robots["r1"].info.model_copy(update={"turn_slip_var": 0.02})
    estimator = DSlam(DslamConfig(association="jcbb"))
    estimator.add_robot(slipping)
    turned = 0.0
    for event in mapped.events():
        if isinstance(event, OdomEvent):
            estimator.on_odometry(event)
            turned += abs(float(event.control[1])) * event.dt
        elif isinstance(event, ScanEvent):
            estimator.on_scan(event)
    assert turned > 1.0
    assert estimator.robots["r1"].turn_slip < 0.02 * 0.5 * turned


def test_a_robot_placed_at_a_stamp_skips_its_older_events_and_the_first_placed_starts_the_map():
    """Features seen by ids before any robot has a pose do not make the map non-empty: the first robot placed
    starts it as from a known start pose (phase I); a robot placed with MCL's pose at a stamp skips its older events,
    counted, and moves with the later ones."""
    data = simulate("arena", robots=2, seed=0, duration=3.0, unknown_start=True)
    estimator = DSlam(DslamConfig(association="known"))
    for log in data.robots.values():
        estimator.add_robot(log.info)
    first_scan = next(e for e in data.events() if isinstance(e, ScanEvent) and e.robot_id == "r1" and len(e.observations))
    estimator.on_scan(first_scan)
    assert estimator.tentative and estimator.map_is_empty()  # seen by a robot without a pose: nowhere yet
    assert estimator.place_robot("r1", np.zeros(3), np.zeros((3, 3)))
    assert estimator.robots["r1"].info.start_pose is not None  # phase I, as from a start pose
    r2 = data.robots["r2"]
    stamp = float(r2.odom_stamp[10])
    truth = r2.truth_at(np.array([stamp]))[0]
    assert estimator.place_robot("r2", truth, np.diag([1e-4, 1e-4, 1e-5]), stamp=stamp)
    estimator.on_odometry(r2.odom(5))
    assert estimator.counts["before_placement_pose"] == 1
    np.testing.assert_allclose(estimator.poses()["r2"][0], truth)
    estimator.on_odometry(r2.odom(11))
    assert not np.allclose(estimator.poses()["r2"][0], truth) and estimator.counts["before_placement_pose"] == 1



def test_a_robot_placed_against_the_map_maps_from_its_placed_pose_until_localized():
    """``placement_bootstrap``: r2, placed while r1's map holds A and B, sees only C and D: it maps them from its
    placed pose (phase I, as from a start pose), where they are; placed as localized instead (the former behaviour),
    a scan without two mapped features maps nothing."""
    data = simulate("arena", robots=2, seed=0, duration=1.0, unknown_start=[False, True])
    r1 = data.robots["r1"].info.model_copy(update={"start_pose": np.zeros(3), "start_pose_cov": None})
    r2 = data.robots["r2"].info
    landmarks = {1: (2.0, 0.0), 2: (2.0, 1.0), 3: (10.0, 0.0), 4: (10.0, 1.0)}
    placed = np.array([8.0, 0.5, 0.1])
    noise = np.diag([1e-4, 1e-6])

    def scan(rid: str, pose: np.ndarray, ids: list[int], seq: int) -> ScanEvent:
        offset = np.array([landmarks[i] for i in ids]) - pose[:2]
        bearings = np.arctan2(offset[:, 1], offset[:, 0]) - pose[2]
        return ScanEvent(rid, seq, float(seq), np.hypot(*offset.T), bearings, np.array(ids), noise)

    for bootstrap in (True, False):
        estimator = DSlam(DslamConfig(association="known", placement_bootstrap=bootstrap))
        estimator.add_robot(r1)
        estimator.add_robot(r2)
        estimator.on_scan(scan("r1", np.zeros(3), [1, 2], 0))
        assert sorted(estimator.ids) == [1, 2]
        assert estimator.place_robot("r2", placed, np.diag([1e-4, 1e-4, 1e-6]), stamp=1.0)
        estimator.on_scan(scan("r2", placed, [3, 4], 1))
        if bootstrap:
            assert sorted(estimator.ids) == [1, 2, 3, 4] and not estimator.robots["r2"].localized
            means = dict(zip(estimator.ids, estimator.landmark_map().means))
            for i in (3, 4):
                np.testing.assert_allclose(means[i], landmarks[i], atol=0.05)
        else:
            assert sorted(estimator.ids) == [1, 2] and estimator.robots["r2"].localized



def kidnapped(world: str, seed: int, duration: float, shift, reacquire: bool):
    """D-SLAM without ids over a simulated run whose robot, halfway, is moved by ``shift`` (x, y, θ) in the filter
    with its position std set beyond 3 m: (estimator, map means before, scans after, the true pose at the end)."""
    data = simulate(world, robots=1, seed=seed, duration=duration)
    events = list(data.events())
    half = len(events) // 2
    estimator = DSlam(DslamConfig(association="jcbb", reacquire=reacquire))
    estimator.add_robot(data.robots["r1"].info)
    feed(estimator, events[:half])
    before = estimator.map.means.copy()
    robot = estimator.robots["r1"]
    robot.pose = robot.pose + np.asarray(shift, float)
    robot.cov = robot.cov + np.diag([9.0, 9.0, 0.0])
    feed(estimator, events[half:])
    scans = sum(isinstance(event, ScanEvent) for event in events[half:])
    log = data.robots["r1"]
    return estimator, before, scans, log.truth_at(np.array([log.scan_stamp[-1]]))[0]


def test_a_lost_robot_leaves_the_map_alone_until_one_correction_puts_it_back():
    """Re-acquisition: a robot whose position std is beyond ``reacquire_position_sd`` neither maps nor localizes
    from its scans; its held detections are searched for one rigid correction, which puts it back on the map."""
    estimator, before, scans, truth = kidnapped("arena", 2, 40.0, (1.2, -0.8, 0.15), reacquire=True)
    assert before.shape[0] >= 8
    assert estimator.counts["reacquire_started"] == 1 and estimator.counts["reacquired"] == 1
    assert 0 < estimator.counts["detections_blind"]
    pose, _ = estimator.poses()["r1"]
    assert np.hypot(*(pose[:2] - truth[:2])) < 0.2 and abs(wrap_angle(pose[2] - truth[2])) < 0.15
    held, before, scans, truth = kidnapped("arena", 2, 40.0, (30.0, 0.0, 0.0), reacquire=True)  # far off: none
    np.testing.assert_array_equal(held.map.means, before)
    assert held.counts["reacquired"] == 0 and held.counts["scans"] > scans > 20
    assert held.robots["r1"].blind is not None
    scan = simulate("arena", robots=1, seed=2, duration=40.0).robots["r1"].scan(-1)
    scan.seq, scan.stamp = scan.seq + 1, scan.stamp + 1.0
    scan.noise_cov = np.zeros((2, 2))  # schema-valid, yet no inlier radius: held, not searched, nothing breaks
    held.robots["r1"].pose = truth.copy()  # among the landmarks again, still lost
    blind = held.counts["detections_blind"]
    held.on_scan(scan)
    assert held.counts["detections_blind"] == blind + len(scan.ranges) and held.counts["reacquired"] == 0


def test_without_re_acquisition_the_kidnapped_robot_maps_from_where_it_wrongly_is():
    estimator, before, _, truth = kidnapped("arena", 2, 40.0, (1.2, -0.8, 0.15), reacquire=False)
    assert estimator.counts["reacquire_started"] == 0 and estimator.counts["detections_blind"] == 0
    pose, _ = estimator.poses()["r1"]
    assert np.hypot(*(pose[:2] - truth[:2])) > 1.0


def thrown_off(by_robots: bool, turn_deg: float = 25.0, **settings) -> tuple[float, float, DSlam]:
    """Three robots that see each other map the arena without ids; halfway r1's estimate is thrown ``turn_deg`` and
    0.5 m off with its covariance unchanged (sure of a wrong pose). (r1's final position error, heading error, the
    estimator)."""
    data = simulate("arena", robots=3, seed=2, duration=60.0)
    estimator = DSlam(DslamConfig(association="jcbb", reacquire_by_robots=by_robots, **settings))
    for log in data.robots.values():
        estimator.add_robot(log.info)
    events = list(data.events())
    half = len(events) // 2
    feed(estimator, events[:half])
    robot = estimator.robots["r1"]
    robot.pose = np.r_[robot.pose[:2] + [0.4, -0.3], wrap_angle(robot.pose[2] + np.deg2rad(turn_deg))]
    feed(estimator, events[half:])
    log = data.robots["r1"]
    truth = log.truth_at(np.array([log.scan_stamp[-1]]))[0]
    pose, _ = estimator.poses()["r1"]
    return float(np.hypot(*(pose[:2] - truth[:2]))), abs(wrap_angle(pose[2] - truth[2])), estimator


def test_a_robot_sure_of_a_wrong_pose_is_put_back_when_the_robots_it_sees_contradict_it():
    """Its covariance says nothing is wrong, so only its detections of the other two robots can: with
    ``reacquire_by_robots`` (the default) they count it as lost and one correction of its held detections puts it
    back; without, it stays off."""
    error, heading, estimator = thrown_off(True)
    assert estimator.counts["reacquire_contradicted"] >= 1 and estimator.counts["reacquired"] >= 1
    assert error < 0.2 and heading < np.deg2rad(5.0)
    plain_error, _, plain = thrown_off(False)
    assert plain.counts["reacquire_started"] == 0 and plain_error > 0.5


def test_a_robot_half_a_turn_off_is_put_back_by_the_robots_it_sees():
    """160° is beyond any search of the landmarks (``reacquire_max_turn``): the rigid fit of its detections of the
    other robots onto them puts it back; without that fit (a minimum of pairs never reached) it stays off."""
    error, heading, estimator = thrown_off(True, 160.0)
    assert estimator.counts["reacquired_by_robots"] >= 1
    assert error < 0.2 and heading < np.deg2rad(5.0)
    plain_error, plain_heading, plain = thrown_off(True, 160.0, reacquire_robots_fit_min=10**6)
    assert plain.counts["reacquired_by_robots"] == 0 and plain_error > 1.0 and plain_heading > np.deg2rad(45.0)


def test_a_robot_checkpointed_before_it_kept_robot_detections_restores():
    """A checkpoint written before ``reacquire_by_robots`` holds robots without their robot detections."""
    estimator = DSlam()
    estimator.add_robot(simulate("arena", robots=1, seed=0, duration=1.0).robots["r1"].info)
    state = dict(pickle.loads(pickle.dumps(estimator.robots["r1"])).__dict__)
    del state["robot_checks"], state["contradicted"]
    restored = object.__new__(type(estimator.robots["r1"]))
    restored.__setstate__(state)
    assert restored.robot_checks == [] and restored.contradicted is False


MAPPED_LANDMARKS = np.array([[3.0, 0.0], [0.0, 3.0], [3.0, 3.0]])


def one_robot_among_three_mapped_landmarks(robot: dict, **config) -> DSlam:
    """D-SLAM with ids (``config`` added) holding :data:`MAPPED_LANDMARKS` (ids 1, 2, 3) as if surveyed, and one
    arena robot r1 whose RobotInfo is updated by ``robot``."""
    estimator = DSlam(DslamConfig(association="known", **config))
    estimator.load_landmarks([1, 2, 3], MAPPED_LANDMARKS, np.repeat(1e-6 * np.eye(2)[None], 3, 0))
    info = simulate("arena", robots=1, duration=1.0).robots["r1"].info
    estimator.add_robot(info.model_copy(update=robot))
    return estimator


def relocalized_after_interleaved_sightings(steps: int) -> tuple[DSlam, np.ndarray]:
    """A robot sure of a pose 0.6 m and 10° off localizes against three mapped landmarks every other scan and
    against one of them in between. (The estimator after ``steps`` such pairs, the true pose.)"""
    estimator = one_robot_among_three_mapped_landmarks({"start_pose": (0.6, -0.3, np.deg2rad(10.0)),
                                                        "start_pose_cov": np.diag([1e-4, 1e-4, 1e-5])})
    robot = estimator.robots["r1"]
    truth = np.array([0.0, 0.0, np.pi / 4])
    robot.pose[2] += truth[2]
    noise = np.diag([1e-4, 1e-5])
    every = np.array([estimator.index_of[key] for key in (1, 2, 3)])
    seen = robot.sensor.observe(truth, estimator.map.means[every])
    for _ in range(steps):
        estimator._localize(robot, seen, noise, every)
        estimator._localize(robot, seen[2:], noise, every[2:])
    return estimator, truth


def test_a_sighting_of_one_landmark_does_not_cancel_the_full_rank_estimates_that_contradict_the_pose():
    """After ``relocalize_after`` scans whose full-rank estimate contradicts the prediction the robot is put where
    they say. One landmark leaves a turn free: such a scan could agree with a wrong pose and, counted as agreement,
    reset the count every other scan (MR.CLAM Dataset 1 without ids: a robot 34° off paired single detections with
    the neighbouring landmarks between its full-rank estimates)."""
    steps = DslamConfig().relocalize_after
    estimator, truth = relocalized_after_interleaved_sightings(steps - 1)
    assert estimator.counts["relocalized"] == 0 and estimator.robots["r1"].disagreements == steps - 1
    estimator, truth = relocalized_after_interleaved_sightings(steps)
    pose, _ = estimator.poses()["r1"]
    assert estimator.counts["relocalized"] == 1
    assert np.hypot(*(pose[:2] - truth[:2])) < 0.05 and abs(wrap_angle(pose[2] - truth[2])) < 0.02


def test_without_ids_each_robots_turn_scale_follows_how_much_its_odometry_over_counts_its_turns():
    """A robot whose odometry says 1 / 0.9 of every turn learns a turn scale near 0.9 from pairs of its detections of
    one mapped landmark (robots/odometry_noise.py) and turns its pose by it (``turn_scale_adapt``); off (the default),
    or with ids, the scale stays 1."""
    data = simulate("arena", robots=1, seed=2, duration=120.0)
    for log in data.robots.values():
        log.odom_control = log.odom_control * (1.0, 1.0 / 0.9)

    def learned(**settings) -> float:
        estimator = run(DSlam(DslamConfig(**settings)), data)
        odometry_noise = estimator.robots["r1"].odometry_noise
        return 1.0 if odometry_noise is None else odometry_noise.turn_scale

    assert 0.86 < learned(association="auto", turn_scale_adapt=True) < 0.94
    assert learned(association="auto") == 1.0  # off by default
    assert learned(association="known", turn_scale_adapt=True) == 1.0


def after_a_slipping_turn(in_gate: bool) -> tuple[DSlam, float]:
    """A robot announcing a turn slip of 0.015 rad² per rad turns a full circle on the spot; its odometry over-counts
    the turn by 20° while its heading σ stays at about 2°. It then sees three mapped landmarks. (The estimator, the
    true heading.)"""
    estimator = one_robot_among_three_mapped_landmarks(
        {"start_pose": (0.0, 0.0, 0.0), "turn_slip_var": 0.015,
         "start_pose_cov": np.diag([1e-4, 1e-4, np.deg2rad(1.0) ** 2])}, turn_slip_in_localization_gate=in_gate)
    steps = 100
    for k in range(steps):
        estimator.on_odometry(OdomEvent("r1", k, 0.1 * k, 0.1, np.array([0.0, 2 * np.pi / (steps * 0.1)]),
                                        np.diag([1e-6, 1e-5])))
    robot = estimator.robots["r1"]
    truth = np.array([0.0, 0.0, robot.pose[2] - np.deg2rad(20.0)])
    z = robot.sensor.observe(truth, MAPPED_LANDMARKS)
    estimator.on_scan(ScanEvent("r1", 0, 10.0, z[:, 0], z[:, 1], np.array([1, 2, 3]), np.diag([1e-4, 1e-5])))
    return estimator, truth[2]


def test_the_turn_slip_widens_the_test_of_a_full_rank_localization_that_contradicts_the_prediction():
    """After turning blind, a robot's heading may be off by far more than its odometry's σ says. The slip it
    announces widens the association's gate; with ``turn_slip_in_localization_gate`` it also widens the test that
    sets aside a full-rank localization beyond doubt, so three landmarks that show the 20° are believed at once."""
    estimator, heading = after_a_slipping_turn(in_gate=True)
    pose, _ = estimator.poses()["r1"]
    assert estimator.counts["localization_rejected"] == 0
    assert abs(wrap_angle(pose[2] - heading)) < np.deg2rad(3.0)
    estimator, heading = after_a_slipping_turn(in_gate=False)
    pose, _ = estimator.poses()["r1"]
    assert estimator.counts["localization_rejected"] == 1
    assert abs(wrap_angle(pose[2] - heading)) > np.deg2rad(15.0)
