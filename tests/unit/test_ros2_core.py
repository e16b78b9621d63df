"""ROS 2 fleet file and conversions (services/ros2): validation errors, round trips, every rejection reason."""

import math

import numpy as np
import pytest

from robots.dataset import RobotLog
from robots.models import AckermannModel
from schemas.messages import RobotInfo, SensorSpec
from services.ros2.core import (RobotInput, fleet_entry_for, make_header, new_message, reject_reason,
                                robot_log_messages, stamp_to_ns, type_hash, typestore_for)
from services.ros2.fleet import FleetFileError, RobotEntry, load_fleet, parse_fleet

JAZZY = typestore_for("jazzy")


def _log(motion_model: str = "unicycle", stamp0: float = 1_248_272_263.0) -> RobotLog:
    """A small robot log: 60 controls at ≈ 40 Hz (some standing still), three scans."""
    rng = np.random.default_rng(3)
    stamps = stamp0 + np.cumsum(rng.uniform(0.02, 0.03, 61))
    controls = np.column_stack([rng.uniform(-1.0, 4.0, 60), rng.uniform(-0.4, 0.4, 60)])
    ackermann = motion_model == "ackermann"
    sensor = SensorSpec(max_range=20.0, fov=math.pi, noise_cov=np.diag([0.04, 0.001]), offset=np.array([0.5, 0.2]))
    info = RobotInfo(robot_id="r1", stamp=stamp0, motion_model=motion_model, wheelbase=2.83 if ackermann else 0.0,
                     encoder_offset=0.76 if ackermann else 0.0, sensor=sensor, odom_rate_hz=40.0, scan_rate_hz=5.0,
                     start_pose=np.array([1.0, 2.0, 0.5]), start_pose_cov=np.diag([1e-6, 1e-6, 1e-6]))
    return RobotLog(info=info, odom_stamp=stamps[1:], odom_dt=np.diff(stamps), odom_control=controls,
                    odom_cov=np.diag([0.04, 0.01]), scan_stamp=stamps[[10, 30, 50]], scan_offsets=np.array([0, 2, 2, 5]),
                    det_range=np.array([3.0, 4.5, 1.0, 7.0, 12.0]),
                    det_bearing=np.array([0.1, -3.1, 1.5, -1.5, 3.1]), det_id=None, scan_cov=np.diag([0.04, 0.001]))


def _replay(log: RobotLog, entry: RobotEntry | None = None, distro: str = "jazzy"):
    """Export ``log``, pass every message through CDR, import it back: (odometry events, scan events)."""
    entry = entry or fleet_entry_for(log)
    typestore = typestore_for(distro)
    robot = RobotInput(entry)
    odometry, scans = [], []
    for topic, msgtype, _, msg in robot_log_messages(log, entry, typestore):
        msg = typestore.deserialize_cdr(typestore.serialize_cdr(msg, msgtype), msgtype)
        if topic == entry.topic(entry.odometry_topic):
            event = robot.odometry(msg)
            if event is not None:
                odometry.append(event)
        elif topic == entry.topic(entry.landmarks_topic):
            scans.append(robot.landmarks(msg))
    return odometry, scans


def _odometry(stamp: float, speed: float = 1.0, turn: float = 0.1, covariance=None, frame: str = "r1/odom",
              child: str = "r1/base_link"):
    vector = "geometry_msgs/msg/Vector3"
    twist = new_message(JAZZY, "geometry_msgs/msg/Twist", linear=new_message(JAZZY, vector, x=speed),
                        angular=new_message(JAZZY, vector, z=turn))
    cov = np.zeros(36) if covariance is None else np.asarray(covariance, float)
    return new_message(JAZZY, "nav_msgs/msg/Odometry", header=make_header(JAZZY, stamp_to_ns(stamp), frame),
                       child_frame_id=child,
                       twist=new_message(JAZZY, "geometry_msgs/msg/TwistWithCovariance", twist=twist, covariance=cov))


def _pose_array(stamp: float, points, frame: str = "r1/sensor"):
    poses = [new_message(JAZZY, "geometry_msgs/msg/Pose", position=new_message(JAZZY, "geometry_msgs/msg/Point", x=x, y=y))
             for x, y in points]
    return new_message(JAZZY, "geometry_msgs/msg/PoseArray", header=make_header(JAZZY, stamp_to_ns(stamp), frame),
                       poses=poses)


# ---------------------------------------------------------------- the fleet file
def test_fleet_file_errors_name_the_file_and_the_field(tmp_path):
    path = tmp_path / "fleet.yaml"
    path.write_text("robots:\n  - robot_id: r1\n    sensor: {max_range: -2}\n  - robot_id: r2\n    odometry_topci: odom\n")
    with pytest.raises(FleetFileError) as error:
        load_fleet(path)
    text = str(error.value)
    assert str(path) in text and "robots.0.sensor.max_range" in text and "robots.1.odometry_topci" in text
    path.write_text("robots: [\n")
    with pytest.raises(FleetFileError, match="not valid YAML"):
        load_fleet(path)
    with pytest.raises(FleetFileError, match="cannot read"):
        load_fleet(tmp_path / "missing.yaml")
    for robots, problem in [([{"robot_id": "r 1"}], "robot_id"),
                            ([{"robot_id": "r1", "motion_model": "ackermann"}], "wheelbase"),
                            ([{"robot_id": "r1"}, {"robot_id": "r1"}], "robot ids repeat"),
                            ([{"robot_id": "a", "namespace": "/x"}, {"robot_id": "b", "namespace": "/x"}], "topics used twice"),
                            ([{"robot_id": "r1", "namespace": "robot1"}], "namespace"),
                            ([{"robot_id": "r1", "odometry_type": "nav_msgs/msg/Path"}], "odometry_type"),
                            ([{"robot_id": "r1", "extractor": {"min_beams": 2}}], "only for landmarks_type"),
                            ([{"robot_id": "r1", "landmarks_type": "sensor_msgs/msg/LaserScan",
                               "extractor": {"min_beam": 2}}], "unknown field"),
                            ([], "robots")]:
        with pytest.raises(FleetFileError, match=problem):
            parse_fleet({"robots": robots}, "fleet file x.yaml")


def test_fleet_entry_defaults_and_topic_names():
    fleet = parse_fleet({"ros_distro": "humble", "robots": [{"robot_id": "r1"}, {"robot_id": "2-b", "namespace": ""}]})
    first, second = fleet.robots
    assert (fleet.ros_distro, fleet.domain_id, fleet.map_frame) == ("humble", 0, "map")
    assert first.namespace == "/r1" and first.topic(first.odometry_topic) == "/r1/odom"
    assert second.namespace == "/robot_2_b" and second.topic("/tf") == "/tf"
    assert parse_fleet({"robots": [{"robot_id": "r1", "namespace": "/"}]}).robots[0].topic("odom") == "/odom"


# ---------------------------------------------------------------- type hashes
def test_type_hashes_are_rosbags_rihs01_and_not_supported_on_humble():
    assert type_hash(JAZZY, "nav_msgs/msg/Odometry", "jazzy") == (
        "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0")
    for msgtype in ("geometry_msgs/msg/PoseArray", "sensor_msgs/msg/LaserScan", "geometry_msgs/msg/TwistStamped"):
        assert type_hash(JAZZY, msgtype, "jazzy") == JAZZY.hash_rihs01(msgtype)
    assert type_hash(typestore_for("humble"), "nav_msgs/msg/Odometry", "humble") == "TypeHashNotSupported"
    with pytest.raises(ValueError, match="unknown ROS distribution"):
        typestore_for("noetic")


# ---------------------------------------------------------------- round trips
@pytest.mark.parametrize("distro", ["jazzy", "humble"])
def test_unicycle_log_round_trips_through_odometry_and_pose_array(distro):
    log = _log("unicycle")
    odometry, scans = _replay(log, distro=distro)
    assert [e.seq for e in odometry] == list(range(60)) and [s.seq for s in scans] == [0, 1, 2]
    np.testing.assert_array_equal([e.stamp for e in odometry], log.odom_stamp)  # Unix stamps: every bit kept
    np.testing.assert_allclose([e.dt for e in odometry], log.odom_dt, rtol=0, atol=1e-9)
    np.testing.assert_allclose([e.control for e in odometry], log.odom_control, rtol=0, atol=1e-12)
    np.testing.assert_allclose([e.control_cov for e in odometry], np.broadcast_to(log.odom_cov, (60, 2, 2)), atol=1e-15)
    np.testing.assert_allclose(np.concatenate([s.ranges for s in scans]), log.det_range, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.concatenate([s.bearings for s in scans]), log.det_bearing, rtol=0, atol=1e-12)
    assert [len(s.ranges) for s in scans] == [2, 0, 3] and all(s.landmark_ids is None for s in scans)


def test_ackermann_log_round_trips_with_the_encoder_offset():
    log = _log("ackermann", stamp0=12.5)
    log.odom_control[7] = [0.0, 0.3]  # standing still: the twist has no steering angle
    odometry, _ = _replay(log)
    controls = np.array([e.control for e in odometry])
    moving = np.arange(60) != 7
    np.testing.assert_allclose(controls[moving], log.odom_control[moving], rtol=0, atol=1e-12)
    np.testing.assert_allclose(controls[7], [0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose([e.dt for e in odometry], log.odom_dt, rtol=0, atol=1e-9)
    covs = np.array([e.control_cov for e in odometry])
    np.testing.assert_allclose(covs, np.broadcast_to(log.odom_cov, (60, 2, 2)), rtol=1e-9, atol=1e-12)
    model = AckermannModel(2.83, 0.76)
    np.testing.assert_allclose(model.to_unicycle(controls)[0], model.to_unicycle(log.odom_control)[0], atol=1e-12)


def test_info_announces_the_entry():
    log = _log("ackermann")
    info = RobotInput(fleet_entry_for(log)).info(5.0)
    assert (info.motion_model, info.wheelbase, info.encoder_offset, info.stamp) == ("ackermann", 2.83, 0.76, 5.0)
    np.testing.assert_allclose(info.sensor.noise_cov, log.info.sensor.noise_cov, rtol=1e-15)  # σ² of σ = √var
    np.testing.assert_array_equal(info.sensor.offset, [0.5, 0.2])
    np.testing.assert_array_equal(info.start_pose, log.info.start_pose)
    np.testing.assert_allclose(info.start_pose_cov, log.info.start_pose_cov, rtol=1e-15)


def test_first_odometry_starts_the_clock_and_zero_covariance_uses_odometry_std():
    robot = RobotInput(RobotEntry(robot_id="r1", odometry_std=(0.2, 0.3)))
    assert robot.odometry(_odometry(10.0)) is None
    event = robot.odometry(_odometry(10.25, speed=0.5, turn=-0.2))
    assert (event.seq, event.stamp, event.dt) == (0, 10.25, 0.25)
    np.testing.assert_array_equal(event.control, [0.5, -0.2])
    np.testing.assert_allclose(event.control_cov, np.diag([0.04, 0.09]))
    covariance = np.zeros((6, 6))
    covariance[0, 0], covariance[5, 5], covariance[0, 5], covariance[5, 0] = 0.01, 0.02, 0.003, 0.003
    covariance[1, 1] = 9.0  # not (v, ω): ignored
    event = robot.odometry(_odometry(10.5, covariance=covariance.reshape(36)))
    np.testing.assert_allclose(event.control_cov, [[0.01, 0.003], [0.003, 0.02]])
    assert event.seq == 1


def test_pose_array_bearings_turn_by_the_sensor_yaw():
    entry = RobotEntry(robot_id="r1", sensor={"yaw": math.pi / 2, "offset": (0.3, 0.0)})
    scan = RobotInput(entry).landmarks(_pose_array(1.0, [(2.0, 0.0), (0.0, -1.0)]))
    np.testing.assert_allclose(scan.ranges, [2.0, 1.0])
    np.testing.assert_allclose(scan.bearings, [math.pi / 2, 0.0], atol=1e-15)


def test_laser_scan_goes_through_the_point_landmark_extractor():
    entry = RobotEntry(robot_id="r1", landmarks_type="sensor_msgs/msg/LaserScan", sensor_frame="laser",
                       sensor={"yaw": 0.25}, extractor={"min_beams": 2})
    ranges = np.full(181, 20.0, np.float32)
    ranges[88:93] = 5.0  # a pole straight ahead of the laser, five beams wide
    scan = new_message(JAZZY, "sensor_msgs/msg/LaserScan", header=make_header(JAZZY, stamp_to_ns(2.0), "laser"),
                       angle_min=-math.pi / 2, angle_max=math.pi / 2, angle_increment=math.pi / 180,
                       range_min=0.1, range_max=30.0, ranges=ranges)
    event = RobotInput(entry).landmarks(scan)
    assert len(event.ranges) == 1
    np.testing.assert_allclose(event.ranges, [5.0], atol=1e-6)
    np.testing.assert_allclose(event.bearings, [0.25], atol=1e-6)
    bad = new_message(JAZZY, "sensor_msgs/msg/LaserScan", header=make_header(JAZZY, stamp_to_ns(3.0), "laser"),
                      angle_min=-1.0, angle_increment=0.01, ranges=ranges, intensities=np.ones(3, np.float32))
    with pytest.raises(ValueError, match="^bad_shape:"):
        RobotInput(entry).landmarks(bad)


# ---------------------------------------------------------------- rejections
def _reason(call, *args) -> str:
    with pytest.raises(ValueError) as error:
        call(*args)
    return reject_reason(error.value)


def test_every_bad_input_is_rejected_with_its_reason():
    robot = RobotInput(RobotEntry(robot_id="r1", max_odom_gap_s=1.0))
    assert _reason(robot.odometry, _pose_array(1.0, [])) == "wrong_type"
    assert _reason(robot.landmarks, _odometry(1.0)) == "wrong_type"
    assert _reason(robot.odometry, _odometry(1.0, frame="map")) == "unknown_frame"
    assert _reason(robot.odometry, _odometry(1.0, child="laser")) == "unknown_frame"
    assert _reason(robot.landmarks, _pose_array(1.0, [(1.0, 0.0)], frame="laser")) == "unknown_frame"
    assert robot.odometry(_odometry(1.0, frame="", child="")) is None  # empty frames are accepted
    assert _reason(robot.odometry, _odometry(1.5, speed=math.nan)) == "non_finite"
    assert _reason(robot.landmarks, _pose_array(1.5, [(math.inf, 0.0)])) == "non_finite"
    assert _reason(robot.odometry, _odometry(1.5, covariance=np.zeros(35))) == "bad_shape"
    skew = np.zeros((6, 6))
    skew[0, 0], skew[5, 5], skew[0, 5] = 0.1, 0.1, 0.05
    assert _reason(robot.odometry, _odometry(1.5, covariance=skew.reshape(36))) == "bad_covariance"
    assert _reason(robot.odometry, _odometry(1.0)) == "time_backwards"
    assert _reason(robot.odometry, _odometry(0.5)) == "time_backwards"
    assert robot.odom_seq == 0  # nothing was accepted yet
    assert robot.odometry(_odometry(1.5)).seq == 0
    assert _reason(robot.odometry, _odometry(4.0)) == "time_gap"
    assert robot.odometry(_odometry(4.5)).dt == 0.5  # the gap restarted the clock
    assert robot.landmarks(_pose_array(3.0, [(1.0, 0.0)])).seq == 0
    assert _reason(robot.landmarks, _pose_array(2.0, [])) == "time_backwards"
    assert robot.landmarks(_pose_array(3.0, [])).seq == 1


def test_frames_default_to_the_namespaces_so_a_fleet_shares_one_tf_tree():
    fleet = parse_fleet({"robots": [{"robot_id": "r1"}, {"robot_id": "r2", "namespace": "/robot2"},
                                    {"robot_id": "r3", "namespace": "/", "odom_frame": "world_odom"}]})
    first, second, third = fleet.robots
    assert (first.base_frame, first.odom_frame, first.sensor_frame) == ("r1/base_link", "r1/odom", "r1/sensor")
    assert (second.odom_frame, third.odom_frame, third.base_frame) == ("robot2/odom", "world_odom", "base_link")
    with pytest.raises(FleetFileError, match="odom_frame"):
        parse_fleet({"robots": [{"robot_id": "r1", "odom_frame": "bad frame"}]})
