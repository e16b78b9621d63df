"""ROS 2 bags: ``fleetslam export rosbag2`` read back by rosbags' Reader and mcap's ROS 2 decoder, the
``rosbag2:`` loader, ``fleetslam run --fleet``, and the MR.CLAM round trip (needs the data)."""

import numpy as np
import pytest
from rosbags.rosbag2 import Reader

from robots.loaders import data_root, load_dataset
from schemas.contract import OdomEvent, RunOptions
from services.cli import main as cli_main
from services.export import export_rosbag2
from services.offline import run_estimator
from services.ros2.fleet import load_fleet

ROOT = data_root()


@pytest.fixture(scope="module")
def sim_data():
    return load_dataset("sim:arena", robots=2, seed=4, duration=8.0)


def _assert_same_events(native, loaded, duration=None, tolerance=1e-9):
    """Same events in the same order: stamps, dt, controls and their covariances, ranges, bearings (to ``tolerance``)."""
    expected, got = list(native.events(duration)), list(loaded.events(duration))
    assert len(expected) == len(got)
    for a, b in zip(expected, got):
        assert (type(a), a.robot_id, a.seq) == (type(b), b.robot_id, b.seq)
        assert abs(a.stamp - b.stamp) <= tolerance  # header stamps are whole nanoseconds
        if isinstance(a, OdomEvent):
            np.testing.assert_allclose([b.dt, *b.control], [a.dt, *a.control], rtol=0, atol=tolerance)
            np.testing.assert_allclose(b.control_cov, a.control_cov, rtol=0, atol=tolerance)
        else:
            np.testing.assert_allclose(b.ranges, a.ranges, rtol=0, atol=tolerance)
            np.testing.assert_allclose(b.bearings, a.bearings, rtol=0, atol=tolerance)


def test_mcap_bag_is_read_by_rosbags_and_by_the_mcap_ros2_decoder(sim_data, tmp_path):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    out = tmp_path / "bag"
    summary = export_rosbag2(sim_data, out, storage="mcap")
    r1 = sim_data.robots["r1"]
    with Reader(out) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        counts = {c.topic: c.msgcount for c in reader.connections}
        stamps = [t for _, t, _ in reader.messages()]
    assert types == {"/world/landmarks_truth": "visualization_msgs/msg/MarkerArray",
                     "/r1/odom": "nav_msgs/msg/Odometry", "/r1/landmarks": "geometry_msgs/msg/PoseArray",
                     "/r1/ground_truth": "geometry_msgs/msg/PoseStamped", "/r2/odom": "nav_msgs/msg/Odometry",
                     "/r2/landmarks": "geometry_msgs/msg/PoseArray", "/r2/ground_truth": "geometry_msgs/msg/PoseStamped"}
    assert counts["/r1/odom"] == r1.odom_stamp.size + 1  # one more: the message that starts the clock
    assert counts["/r1/landmarks"] == r1.scan_stamp.size and counts["/r1/ground_truth"] == r1.truth_stamp.size
    assert counts == summary["messages"] and stamps == sorted(stamps)
    decoded = {}
    with open(next(out.glob("*.mcap")), "rb") as handle:
        for _, channel, _, msg in make_reader(handle, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
                topics=["/r1/odom", "/r1/landmarks"]):
            decoded.setdefault(channel.topic, []).append(msg)
    speeds = [m.twist.twist.linear.x for m in decoded["/r1/odom"][1:]]
    np.testing.assert_allclose(speeds, r1.odom_control[:, 0], atol=1e-12)
    ranges = np.concatenate([np.hypot([p.position.x for p in m.poses], [p.position.y for p in m.poses])
                             for m in decoded["/r1/landmarks"]])
    np.testing.assert_allclose(ranges, r1.det_range, atol=1e-12)
    assert decoded["/r1/odom"][0].header.frame_id == "r1/odom" and decoded["/r1/odom"][0].child_frame_id == "r1/base_link"


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_exported_bag_loads_back_as_the_same_data_set(sim_data, tmp_path, storage):
    out = tmp_path / "bag"
    export_rosbag2(sim_data, out, storage=storage)
    loaded = load_dataset(f"rosbag2:{out}")
    assert list(loaded.robots) == ["r1", "r2"] and loaded.meta["rejected"] == {} and loaded.meta["topics_missing"] == []
    _assert_same_events(sim_data, loaded)
    np.testing.assert_array_equal(loaded.landmarks, sim_data.landmarks)
    np.testing.assert_array_equal(loaded.landmark_ids, sim_data.landmark_ids)
    np.testing.assert_allclose(loaded.robots["r2"].truth_pose, sim_data.robots["r2"].truth_pose, atol=1e-12)
    assert loaded.robots["r1"].det_id is None  # ids are not carried


def test_export_duration_and_a_fleet_file_that_renames_a_robot(sim_data, tmp_path):
    out = tmp_path / "bag"
    export_rosbag2(sim_data, out, duration=3.0)
    fleet = load_fleet(out / "fleet.yaml")
    renamed = fleet.model_copy(update={"robots": [fleet.robots[0].model_copy(update={"robot_id": "scout"})]})
    loaded = load_dataset(f"rosbag2:{out}", fleet=renamed)
    assert list(loaded.robots) == ["scout"]
    assert loaded.robots["scout"].odom_stamp[-1] <= sim_data.start_stamp + 3.0 < sim_data.robots["r1"].odom_stamp[-1]


def test_export_and_run_commands(sim_data, tmp_path, capsys):
    out = tmp_path / "bag"
    args = ["export", "rosbag2", "--dataset", "sim:arena", "--duration", "5", "--out", str(out)]
    assert cli_main(args) == 0 and (out / "fleet.yaml").is_file()
    assert cli_main(args) == 2  # exists: kept
    assert cli_main([*args, "--storage", "sqlite3", "--force"]) == 0
    assert next(out.glob("*.db3"))
    other = tmp_path / "notes"
    other.mkdir()
    (other / "keep.txt").write_text("mine")
    assert cli_main(["export", "rosbag2", "--dataset", "sim:arena", "--out", str(other), "--force"]) == 2
    assert (other / "keep.txt").read_text() == "mine"
    run = ["run", "--dataset", f"rosbag2:{out}", "--fleet", str(out / "fleet.yaml"), "--out", str(tmp_path / "run"),
           "--json", str(tmp_path / "run.json"), "--no-progress"]
    assert cli_main(run) == 0
    assert cli_main(["run", "--dataset", "sim:arena", "--fleet", str(out / "fleet.yaml"), "--no-progress",
                     "--out", str(tmp_path / "run2")]) == 2
    assert "--fleet is for rosbag2" in capsys.readouterr().err


def test_a_bag_without_fleet_file_is_refused_with_the_way_out(sim_data, tmp_path):
    out = tmp_path / "bag"
    export_rosbag2(sim_data, out)
    (out / "fleet.yaml").unlink()
    with pytest.raises(ValueError, match="--fleet"):
        load_dataset(f"rosbag2:{out}")


@pytest.mark.data
@pytest.mark.skipif(ROOT is None, reason="real data sets not found (set FLEETSLAM_DATA or add ../shared/data)")
def test_mrclam_round_trip_gives_the_native_events_and_run(tmp_path):
    """MR.CLAM 6, first 120 s: exported and loaded back, the events equal the native loader's within 1e-9 and a
    FastSLAM run without barcodes gives the same trajectories and map as the native data set without what a
    PoseArray cannot carry (landmark ids, detections of other robots)."""
    native = load_dataset("mrclam:")
    export_rosbag2(native, tmp_path / "bag", duration=120.0)
    loaded = load_dataset(f"rosbag2:{tmp_path / 'bag'}")
    assert loaded.meta["rejected"] == {}
    _assert_same_events(native, loaded, duration=120.0)
    for log in native.robots.values():
        log.det_id, log.robot_det_offsets, log.robot_det_ids = None, None, []
        log.robot_det_range, log.robot_det_bearing = np.zeros(0), np.zeros(0)
    runs = [run_estimator(data, RunOptions("fastslam", "unknown", particles=20, seed=3), duration=120.0)
            for data in (native, loaded)]
    np.testing.assert_allclose(runs[1].map_means, runs[0].map_means, rtol=0, atol=1e-9)
    for rid, trajectory in runs[0].trajectories.items():
        np.testing.assert_allclose(runs[1].trajectories[rid].poses, trajectory.poses, rtol=0, atol=1e-9)
