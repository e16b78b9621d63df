"""D-SLAM's local maps: one scan's points match the recast of eqs. 3-4, a stretch of scans gives the true
geometry, and features seen only beside one mapped feature at a time still reach the map."""

import numpy as np

from robots.models import RangeBearingSensor, UnicycleModel
from schemas.contract import OdomEvent, ScanEvent
from schemas.messages import RobotInfo, SensorSpec
from services.dslam.config import DslamConfig
from services.dslam.core import DSlam
from services.dslam.local_map import LocalMap
from services.dslam.recast import map_measurement, recast, recast_points

NOISE = np.diag([0.02**2, np.deg2rad(1.0) ** 2])


def test_one_scan_recasts_like_the_paper():
    sensor = RangeBearingSensor()
    observations = np.array([[3.0, 0.2], [5.0, -0.4], [4.0, 0.9]])
    local = LocalMap(sensor)
    local.observe(observations, NOISE, np.array([7, 3, 9]))
    points, cov = local.points([7, 3, 9])
    z_local, r_local = recast_points(points, cov)
    z_scan, r_scan = recast(observations, NOISE)
    np.testing.assert_allclose(z_local, z_scan, atol=1e-12)
    np.testing.assert_allclose(r_local, r_scan, atol=1e-12)


def test_features_over_a_stretch_keep_their_true_geometry_and_a_covariance_that_grows_with_motion():
    sensor = RangeBearingSensor(offset=(0.3, 0.0))
    model = UnicycleModel()
    landmarks = np.array([[4.0, 1.0], [6.0, -2.0], [9.0, 1.5]])
    local = LocalMap(sensor)
    pose = np.zeros(3)
    control, control_cov = np.array([1.0, 0.1]), np.diag([0.05**2, 0.02**2])
    local.observe(sensor.observe(pose, landmarks[:2]), NOISE, np.array([0, 1]))
    for _ in range(20):
        local.predict(model, control, control_cov, 0.1)
        pose = model.step(pose, control, 0.1)
    local.observe(sensor.observe(pose, landmarks[1:]), NOISE, np.array([1, 2]))
    np.testing.assert_allclose(local.x[:3], pose, atol=1e-9)
    points, cov = local.points([0, 1, 2])
    np.testing.assert_allclose(map_measurement(points)[0], map_measurement(landmarks)[0], atol=1e-9)
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    first_seen_late = np.trace(cov[4:, 4:])
    assert first_seen_late > np.trace(cov[:2, :2])  # seen only after the motion: odometry noise adds to it
    assert 0.0 < local.position_std() < 0.2


LANDMARKS = np.array([[3.0, 2.0], [3.0, -2.0], [6.0, 0.0], [9.0, 2.0], [9.0, -2.0]])  # A B C D E


def drive(schedule: list[list[int]]):
    """A robot with a known start pose drives 1 m along x between scans; each scan sees the listed landmarks
    (noiseless, with ids). Returns its RobotInfo and the events."""
    spec = SensorSpec(max_range=20.0, fov=2 * np.pi, noise_cov=NOISE)
    info = RobotInfo(robot_id="r1", stamp=0.0, motion_model="unicycle", sensor=spec, start_pose=np.zeros(3),
                     odom_rate_hz=1.0, scan_rate_hz=1.0)
    sensor, model = RangeBearingSensor(), UnicycleModel()
    pose, events = np.zeros(3), []
    control, control_cov = np.array([1.0, 0.0]), np.diag([1e-8, 1e-10])
    for k, seen in enumerate(schedule):
        if k:
            events.append(OdomEvent("r1", k - 1, float(k), 1.0, control, control_cov))
            pose = model.step(pose, control, 1.0)
        z = sensor.observe(pose, LANDMARKS[seen])
        events.append(ScanEvent("r1", k, float(k), z[:, 0], z[:, 1], np.array(seen), NOISE))
    return info, events


def test_features_seen_beside_one_mapped_feature_at_a_time_reach_the_map_through_a_local_map():
    # A and B are mapped at the start; afterwards no scan sees two mapped features: {A, C}, {B, C}, {C, D}, {D, E}
    info, events = drive([[0, 1], [0, 2], [1, 2], [2, 3], [3, 4]])
    maps = {}
    for std in (0.0, 0.5):
        slam = DSlam(DslamConfig(local_map_max_std=std, bootstrap_std=0.0))
        slam.add_robot(info)
        for event in events:
            (slam.on_odometry if isinstance(event, OdomEvent) else slam.on_scan)(event)
        maps[std] = slam.landmark_map()
    assert sorted(maps[0.0].ids.tolist()) == [0, 1]  # one scan at a time (the paper): C never has two references
    view = maps[0.5]
    assert sorted(view.ids.tolist()) == [0, 1, 2]  # the local map {A, B, C} links C; {C, D, E} has one reference
    np.testing.assert_allclose(view.means[list(view.ids).index(2)], LANDMARKS[2], atol=1e-3)
