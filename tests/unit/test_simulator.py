"""Simulator and worlds: same seed same data, the worlds' specifications, the sensor's limits."""

import math

import numpy as np
import pytest

from robots.models import RangeBearingSensor, wrap_angle
from robots.simulator import simulate
from robots.worlds import PAPER000_CLUSTER, WORLDS, make_world


def _arrays(log):
    return [log.odom_control, log.det_range, log.det_bearing, log.det_id, log.truth_pose, log.scan_offsets]


def test_same_seed_same_data_other_seed_other_data():
    a, b, c = (simulate("arena", robots=3, seed=s, duration=5.0) for s in (4, 4, 5))
    for rid in a.robots:
        for x, y in zip(_arrays(a.robots[rid]), _arrays(b.robots[rid])):
            np.testing.assert_array_equal(x, y)
    assert not np.array_equal(a.robots["r1"].odom_control, c.robots["r1"].odom_control)


def test_a_robot_simulated_alone_matches_the_same_robot_in_the_fleet():
    fleet = simulate("random", robots=3, seed=2, duration=4.0)
    alone = simulate("random", seed=2, duration=4.0, robot_ids=["r2"])
    np.testing.assert_array_equal(fleet.robots["r2"].truth_pose, alone.robots["r2"].truth_pose)


def test_without_robot_detections_only_those_go_and_a_fleet_simulates_in_chunks():
    ids = ["s1", "s2", "s3", "s4"]
    seeing = simulate("arena", seed=1, duration=4.0, robot_ids=ids)
    blind = simulate("arena", seed=1, duration=4.0, robot_ids=ids, robot_detections=False)
    chunks = [simulate("arena", seed=1, duration=4.0, robot_ids=part, robot_detections=False)
              for part in (ids[:3], ids[3:])]
    assert sum(len(log.robot_det_ids) for log in seeing.robots.values()) > 0
    for rid in ids:
        assert len(blind.robots[rid].robot_det_ids) == 0
        chunk = next(c for c in chunks if rid in c.robots)
        for x, y, z in zip(_arrays(seeing.robots[rid]), _arrays(blind.robots[rid]), _arrays(chunk.robots[rid])):
            np.testing.assert_array_equal(x, y)
            np.testing.assert_array_equal(y, z)


@pytest.mark.parametrize("name", sorted(WORLDS))
def test_every_world_simulates_with_consistent_arrays(name):
    data = simulate(name, seed=1, duration=3.0, rate=5.0, odom_factor=2)
    log = data.robots["r1"]
    assert len(log.odom_stamp) == 30 and len(log.scan_stamp) == 16 and len(log.truth_stamp) == 31
    assert log.scan_offsets[-1] == log.det_range.size == log.det_id.size
    assert np.all(np.diff(log.odom_stamp) > 0)
    events = list(data.events())
    assert [e.stamp for e in events] == sorted(e.stamp for e in events)


def test_world_specifications():
    paper = make_world("paper000", seed=7)
    assert paper.landmarks.shape == (12, 2)
    np.testing.assert_array_equal(paper.landmarks[:5], PAPER000_CLUSTER)
    assert np.all((paper.landmarks >= 0) & (paper.landmarks <= 20))
    assert paper.turn_rate * (1.0 / paper.extra["rate"]) == pytest.approx(math.radians(1.0))
    assert paper.speed / paper.turn_rate == pytest.approx(5.0)
    grid = make_world("grid196")
    assert grid.landmarks.shape == (196, 2) and np.ptp(grid.landmarks[:, 0]) == pytest.approx(39.0)
    assert np.unique(np.round(np.diff(np.unique(grid.landmarks[:, 0])), 9)).tolist() == [3.0]
    assert grid.sensor.max_range == 5.0 and grid.sensor.fov == pytest.approx(math.pi) and grid.speed == 0.2
    arena = make_world("arena")
    assert arena.landmarks.shape == (15, 2)


def test_cross_world_is_four_fold_symmetric_except_its_room():
    cross = make_world("cross")
    symmetric = cross.landmarks[: cross.extra["symmetric_landmarks"]]
    rotated = symmetric @ np.array([[0.0, 1.0], [-1.0, 0.0]])
    distances = np.linalg.norm(rotated[:, None] - symmetric[None], axis=-1)
    assert np.allclose(distances.min(axis=1), 0.0, atol=1e-9)
    assert cross.landmarks.shape[0] > symmetric.shape[0]


def test_detections_respect_range_fov_noise_and_ids():
    data = simulate("grid196", seed=3, duration=30.0)
    log = data.robots["r1"]
    world = make_world("grid196")
    sensor = RangeBearingSensor()
    assert np.all(log.det_range <= world.sensor.max_range + 0.5)
    assert np.all(np.abs(log.det_bearing) <= world.sensor.fov / 2 + 0.2)
    errors = []
    for s in range(len(log.scan_stamp)):
        scan = log.scan(s)
        truth = sensor.observe(log.truth_at(np.array([scan.stamp]))[0], world.landmarks[scan.landmark_ids])
        errors.append(scan.observations - truth)
    errors = np.vstack(errors)
    errors[:, 1] = wrap_angle(errors[:, 1])
    np.testing.assert_allclose(np.std(errors, axis=0), np.sqrt(np.diag(world.sensor.noise_cov)), rtol=0.15)


def test_clutter_and_missed_detections():
    clean = simulate("random", seed=1, duration=20.0, detection_probability=1.0, clutter_rate=0.0).robots["r1"]
    noisy = simulate("random", seed=1, duration=20.0, detection_probability=0.5, clutter_rate=3.0).robots["r1"]
    assert np.all(clean.det_id >= 0)
    n_scans = len(noisy.scan_stamp)
    assert np.sum(noisy.det_id == -1) / n_scans == pytest.approx(3.0, rel=0.2)
    assert np.sum(noisy.det_id >= 0) < 0.65 * np.sum(clean.det_id >= 0)


def test_unknown_start_hides_the_start_pose_but_keeps_truth():
    log = simulate("cross", seed=0, duration=1.0, unknown_start=True).robots["r1"]
    assert log.info.start_pose is None and log.truth_pose.shape[0] > 0


def test_a_robot_announces_motion_limits_that_its_own_odometry_keeps():
    from robots.process import load_robot
    from schemas.config import RobotSettings

    robot, _ = load_robot(RobotSettings(world="arena", duration=20.0, seed=3))
    info = robot.info
    assert info.max_speed is not None and info.max_turn_rate is not None and info.max_steering is None
    assert np.abs(robot.odom_control[:, 0]).max() <= info.max_speed < 2 * np.abs(robot.odom_control[:, 0]).max()
    assert np.abs(robot.odom_control[:, 1]).max() <= info.max_turn_rate


def test_a_robot_in_a_fleet_keeps_its_own_path_and_detects_the_others_as_they_detect_it():
    """``--fleet``: each robot's process simulates the fleet and publishes its own log; the robot's motion and
    landmark detections are those it has alone, and two processes agree on where each robot is (r2 detects r1
    where r1's own truth is)."""
    from robots.process import load_robot
    from schemas.config import RobotSettings

    alone, _ = load_robot(RobotSettings(robot_id="r2", world="arena", duration=10.0, seed=0))
    r2, _ = load_robot(RobotSettings(robot_id="r2", world="arena", duration=10.0, seed=0, fleet="r1,r2"))
    r1, _ = load_robot(RobotSettings(robot_id="r1", world="arena", duration=10.0, seed=0, fleet="r1,r2"))
    np.testing.assert_array_equal(alone.odom_control, r2.odom_control)
    np.testing.assert_array_equal(alone.det_range, r2.det_range)
    assert alone.robot_det_ids == [] and set(r2.robot_det_ids) == {"r1"}
    sensor = RangeBearingSensor(tuple(r2.info.sensor.offset))
    for k in range(len(r2.scan_stamp)):
        lo, hi = r2.robot_det_offsets[k], r2.robot_det_offsets[k + 1]
        for j in range(lo, hi):
            truth = r1.truth_pose[np.argmin(np.abs(r1.truth_stamp - r2.scan_stamp[k]))]
            pose = r2.truth_pose[np.argmin(np.abs(r2.truth_stamp - r2.scan_stamp[k]))]
            z = sensor.observe(pose, truth[None, :2])[0]
            assert abs(r2.robot_det_range[j] - z[0]) < 0.5 and abs(wrap_angle(r2.robot_det_bearing[j] - z[1])) < 0.2
    with pytest.raises(ValueError, match="--fleet"):
        load_robot(RobotSettings(robot_id="r1", replay="mrclam:/nonexistent:1", fleet="r1,r2"))
