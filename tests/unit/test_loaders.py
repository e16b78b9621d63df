"""Loaders: spec parsing, odometry intervals, MR.CLAM barcode mapping, the beacon detector,
and the counts the data sets' SOURCE.md files state (skipped when the data folder is absent)."""

import lzma
import math

import numpy as np
import pytest

from robots.gaussian import turn_slip
from robots.loaders import data_root, detect_beacons, load_dataset
from robots.loaders.common import gps_spikes, group_by_stamp, odometry_intervals, read_table
from robots.models import AckermannModel, RangeBearingSensor

ROOT = data_root()
needs_data = pytest.mark.skipif(ROOT is None, reason="real data sets not found (set FLEETSLAM_DATA or add ../shared/data)")

HEADER = "# a\n# b\n# c\n# d\n"


def _write(path, rows, packed=False):
    text = HEADER + "".join("\t".join(str(v) for v in row) + "\n" for row in rows)
    if packed:
        with lzma.open(f"{path}.xz", "wt") as handle:
            handle.write(text)
    else:
        path.write_text(text)


@pytest.fixture
def tiny_mrclam(tmp_path):
    """Two robots, two landmarks; barcodes 5, 14 are robots 1, 2; 90, 61 landmarks 6, 7; 43 unknown."""
    _write(tmp_path / "Barcodes.dat", [(1, 5), (2, 14), (6, 90), (7, 61)], packed=True)
    _write(tmp_path / "Landmark_Groundtruth.dat", [(6, 1.0, 2.0, 0.0, 0.0), (7, -1.0, 3.0, 0.0, 0.0)])
    for n in (1, 2):
        _write(tmp_path / f"Robot{n}_Odometry.dat",
               [(100.0, 0.1, 0.0), (100.5, 0.1, 0.0), (100.5, 0.2, 0.1), (101.0, 0.2, 0.1), (102.0, 0.0, 0.0)],
               packed=n == 1)
        _write(tmp_path / f"Robot{n}_Measurement.dat",
               [(100.2, 90, 2.0, 0.1), (100.2, 14 if n == 1 else 5, 3.0, -0.2), (100.7, 43, 1.0, 0.0),
                (101.5, 61, 4.0, 0.3)])
        _write(tmp_path / f"Robot{n}_Groundtruth.dat", [(99.0, 0.0, 0.0, 0.0), (101.0, 2.0, 0.0, 0.2)])
    return tmp_path


def test_odometry_intervals_drop_readings_overtaken_at_the_same_stamp():
    stamps = np.array([0.0, 0.5, 0.5, 1.0])
    controls = np.array([[1.0, 0.0], [2.0, 0.0], [3.0, 0.0], [4.0, 0.0]])
    end, dt, used, dropped = odometry_intervals(stamps, controls)
    assert dropped == 1
    np.testing.assert_allclose(end, [0.5, 1.0])
    np.testing.assert_allclose(dt, [0.5, 0.5])
    np.testing.assert_allclose(used[:, 0], [1.0, 3.0])


def test_group_by_stamp_offsets():
    stamps, offsets = group_by_stamp(np.array([1.0, 1.0, 2.0, 3.0, 3.0, 3.0]))
    np.testing.assert_allclose(stamps, [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(offsets, [0, 2, 3, 6])


def test_read_table_plain_and_xz_alike(tmp_path):
    rows = [(1.0, 2.0), (3.0, 4.5)]
    _write(tmp_path / "a.dat", rows)
    _write(tmp_path / "b.dat", rows, packed=True)
    np.testing.assert_array_equal(read_table(tmp_path / "a.dat", 2), read_table(tmp_path / "b.dat.xz", 2))
    with pytest.raises(ValueError, match="columns"):
        read_table(tmp_path / "a.dat", 3)


def test_mrclam_maps_barcodes_keeps_robot_detections_and_counts_unknown(tiny_mrclam):
    data = load_dataset(f"mrclam:{tiny_mrclam}")
    assert list(data.robots) == ["r1", "r2"]
    np.testing.assert_array_equal(data.landmark_ids, [6, 7])
    r1 = data.robots["r1"]
    np.testing.assert_array_equal(r1.det_id, [6, 7])
    np.testing.assert_allclose(r1.scan_stamp, [100.2, 101.5])  # the unknown barcode's scan disappears
    scan = r1.scan(0)
    assert scan.robot_ids == ["r2"] and scan.robot_ranges[0] == 3.0 and scan.ranges.tolist() == [2.0]
    assert r1.scan(1).robot_ids == [] and r1.scan(1).landmark_ids.tolist() == [7]
    assert data.meta["unknown_barcodes"] == {"r1": 1, "r2": 1}
    assert data.meta["odometry_duplicates"]["r1"] == 1
    np.testing.assert_allclose(r1.odom_dt, [0.5, 0.5, 1.0])
    np.testing.assert_allclose(r1.odom_control[:, 0], [0.1, 0.2, 0.2])
    np.testing.assert_allclose(r1.info.start_pose, [1.0, 0.0, 0.1])  # truth interpolated at t = 100
    assert data.robots["r2"].scan(0).robot_ids == ["r1"]


def test_mrclam_spec_with_a_robot_number_loads_that_robot_only(tiny_mrclam):
    data = load_dataset(f"mrclam:{tiny_mrclam}:2")
    assert list(data.robots) == ["r2"]
    assert data.meta["fleet_start"] == 100.0  # the clock origin every replay process can share
    with pytest.raises(ValueError, match="robots are 1-5"):
        load_dataset(f"mrclam:{tiny_mrclam}:7")


def test_bad_specs_are_refused_with_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match="expected one of"):
        load_dataset("kitti:/nowhere")
    with pytest.raises(FileNotFoundError):
        load_dataset(f"victoria-park:{tmp_path / 'missing'}")


def test_sim_spec_delegates_to_the_simulator():
    data = load_dataset("sim:arena", robots=2, seed=1, duration=2.0)
    assert list(data.robots) == ["r1", "r2"] and data.name == "sim:arena"


def test_beacon_detector_clusters_reflective_beams_inside_the_range_window():
    ranges = np.full((2, 361), 81.9)
    intensity = np.zeros((2, 361), int)
    ranges[0, 10:13], intensity[0, 10:13] = [5.0, 5.2, 5.4], 8192  # beacon: beams 10-12
    ranges[0, 180], intensity[0, 180] = 12.0, 32768  # beacon straight ahead
    ranges[0, 300:302], intensity[0, 300:302] = 40.0, 8192  # too far
    ranges[1, 360], intensity[1, 360] = 2.0, 16384  # last beam: left
    found = detect_beacons(ranges, intensity)
    np.testing.assert_array_equal(found.scan, [0, 0, 1])
    np.testing.assert_allclose(found.range, [5.2, 12.0, 2.0])
    np.testing.assert_allclose(found.bearing, [math.radians(5.5 - 90.0), 0.0, math.radians(90.0)], atol=1e-12)
    np.testing.assert_array_equal(found.beams, [3, 1, 1])
    assert found.rejected == 1


def test_mrclam_robots_announce_their_turn_slip(tiny_mrclam):
    """Every MR.CLAM robot announces the heading variance per radian turned its odometry covariance leaves out
    (0.015 by default, the loader's ``turn_slip_var`` otherwise); the odometry covariance stays one for all controls."""
    data = load_dataset(f"mrclam:{tiny_mrclam}")
    assert {log.info.turn_slip_var for log in data.robots.values()} == {0.015}
    assert data.robots["r1"].odom_cov.shape == (2, 2)
    assert load_dataset(f"mrclam:{tiny_mrclam}", turn_slip_var=0.0).robots["r1"].info.turn_slip_var == 0.0


def test_mrclam_cameras_announce_their_detection_probability(tiny_mrclam):
    """The MR.CLAM sensor announces the share of the landmarks in view its camera detects (0.3 by default)."""
    robots = load_dataset(f"mrclam:{tiny_mrclam}").robots.values()
    assert {log.info.sensor.detection_probability for log in robots} == {0.3}
    other = load_dataset(f"mrclam:{tiny_mrclam}", detection_probability=0.9)
    assert other.robots["r1"].info.sensor.detection_probability == 0.9


@needs_data
def test_mrclam_detection_probability_is_what_the_camera_detects_in_view():
    """Of the landmarks inside the camera's view (0.3 m and 0.05 rad within its limits) at a scan's Vicon pose,
    Dataset 6's robots detect the announced share, within 0.05 (measured 0.297 over the five robots)."""
    data = load_dataset("mrclam:utias_mrclam/MRCLAM_Dataset6")
    in_view = detected = 0
    for log in data.robots.values():
        spec = log.info.sensor
        camera = RangeBearingSensor(tuple(spec.offset))
        poses = log.truth_at(log.scan_stamp)
        for k in np.flatnonzero(np.all(np.isfinite(poses), axis=1)):
            ranges, bearings = camera.observe(poses[k], data.landmarks).T
            view = ((ranges > spec.min_range + 0.3) & (ranges < spec.max_range - 0.3)
                    & (np.abs(bearings) < spec.fov / 2 - 0.05))
            seen = set(log.det_id[log.scan_offsets[k]:log.scan_offsets[k + 1]].tolist())
            in_view += int(view.sum())
            detected += sum(int(i) in seen for i in data.landmark_ids[view].tolist())
    announced = {log.info.sensor.detection_probability for log in data.robots.values()}
    assert announced == {0.3} and in_view > 10_000
    assert abs(detected / in_view - 0.3) <= 0.05


@needs_data
def test_mrclam_turn_slip_covers_the_heading_error_of_turns():
    """Over 4 s windows of Dataset 6, the odometry's heading error against Vicon is within 3σ of the model (σ_ω
    and the announced turn slip, :func:`robots.gaussian.turn_slip` per reading) in at least 99 % of the windows,
    turning or not; with σ_ω alone, in under 80 % of the turns."""
    def within_three_sigma(data, slip: bool) -> tuple[float, float]:
        every, turning = [], []
        for log in data.robots.values():
            covs = np.broadcast_to(log.odom_cov, (log.odom_stamp.size, 2, 2))
            turns = log.odom_control[:, 1] * log.odom_dt
            added = [turn_slip(log.info.turn_slip_var if slip else 0.0, turn) for turn in turns]
            heading = np.concatenate([[0.0], np.cumsum(turns)])
            variance = np.concatenate([[0.0], np.cumsum(covs[:, 1, 1] * log.odom_dt**2 + np.array(added))])
            turned = np.concatenate([[0.0], np.cumsum(np.abs(log.odom_control[:, 1]) * log.odom_dt)])
            ends = np.concatenate([[log.odom_stamp[0] - log.odom_dt[0]], log.odom_stamp])
            valid = np.isfinite(log.truth_pose[:, 2])
            truth = np.unwrap(log.truth_pose[valid, 2])
            starts = np.arange(ends[0] + 5.0, ends[-1] - 10.0, 4.0)
            i0, i1 = np.searchsorted(ends, starts), np.searchsorted(ends, starts + 4.0)
            true_turn = (np.interp(ends[i1], log.truth_stamp[valid], truth)
                         - np.interp(ends[i0], log.truth_stamp[valid], truth))
            inside = np.abs(heading[i1] - heading[i0] - true_turn) <= 3.0 * np.sqrt(variance[i1] - variance[i0])
            every.append(inside)
            turning.append(inside[turned[i1] - turned[i0] > 0.5])
        return float(np.mean(np.concatenate(every))), float(np.mean(np.concatenate(turning)))

    data = load_dataset("mrclam:utias_mrclam/MRCLAM_Dataset6")
    every, turning = within_three_sigma(data, slip=True)
    assert every >= 0.99 and turning >= 0.99
    _, turning_without = within_three_sigma(data, slip=False)
    assert turning_without < 0.8


@needs_data
def test_mrclam_dataset6_counts_match_source_md():
    data = load_dataset("mrclam:utias_mrclam/MRCLAM_Dataset6")
    odometry = {"r1": 61785, "r2": 65005, "r3": 61158, "r4": 52916, "r5": 60567}
    split = {"r1": (1534, 407, 1), "r2": (3239, 792, 0), "r3": (4348, 1277, 2), "r4": (2023, 373, 3),
             "r5": (4239, 1139, 0)}
    truth = {"r1": 49241, "r2": 59705, "r3": 56977, "r4": 61714, "r5": 57467}
    assert data.meta["odometry_rows"] == odometry
    assert data.meta["truth_rows"] == truth
    for rid, (landmark, robot, unknown) in split.items():
        log = data.robots[rid]
        assert (log.det_range.size, len(log.robot_det_ids), data.meta["unknown_barcodes"][rid]) == (landmark, robot, unknown)
        assert log.odom_stamp.size == odometry[rid] - 1 - data.meta["odometry_duplicates"][rid]
        assert np.all(log.odom_dt > 0) and np.all(np.diff(log.scan_stamp) > 0)
        assert set(np.unique(log.det_id)) <= set(range(6, 21))
        assert set(log.robot_det_ids) <= {"r1", "r2", "r3", "r4", "r5"} - {rid}
        assert log.info.start_pose is not None
    assert data.landmarks.shape == (15, 2)
    span = data.robots["r1"].truth_stamp[-1] - data.robots["r2"].truth_stamp[0]
    assert span == pytest.approx(771.9, abs=0.5)  # robot 1's truth stops early


@needs_data
def test_mrclam_observations_agree_with_vicon_truth():
    """Observations predicted from the Vicon poses and the landmark truth match the measured ones."""
    data = load_dataset("mrclam:utias_mrclam/MRCLAM_Dataset6:2")
    log = data.robots["r2"]
    scan_of = np.repeat(np.arange(log.scan_stamp.size), np.diff(log.scan_offsets))
    poses = log.truth_at(log.scan_stamp[scan_of])
    lookup = dict(zip(data.landmark_ids.tolist(), data.landmarks))
    predicted = RangeBearingSensor().observe(poses, np.array([lookup[i] for i in log.det_id.tolist()]))
    ok = np.isfinite(predicted[:, 0])
    assert np.median(np.abs(log.det_range[ok] - predicted[ok, 0])) < 0.2
    assert np.median(np.abs(log.det_bearing[ok] - predicted[ok, 1])) < 0.03


@needs_data
def test_mrclam_dataset1_partial_has_no_robot_truth_and_its_stated_counts():
    data = load_dataset("mrclam:utias_mrclam/MRCLAM_Dataset1_partial")
    rows = [97890, 94826, 97351, 100012, 100726]
    measurements = [5723, 6699, 8742, 3991, 8792]
    for n, rid in enumerate(data.robots):
        log = data.robots[rid]
        assert data.meta["odometry_rows"][rid] == rows[n]
        assert log.det_range.size + len(log.robot_det_ids) + data.meta["unknown_barcodes"][rid] == measurements[n]
        assert log.info.start_pose is None and log.truth_stamp.size == 0


@needs_data
def test_victoria_park_counts_and_vehicle_frame_bearings():
    data = load_dataset("victoria-park:victoria_park")
    log = data.robots["r1"]
    assert data.meta["odometry_rows"] == 61945 and data.meta["detections"] == 52974 and data.meta["gps_fixes"] == 4466
    assert log.scan_stamp.size == 7230 and log.det_range.size == 52974
    assert np.all(np.abs(log.det_bearing) <= math.pi / 2)
    assert math.degrees(log.det_bearing.min()) == pytest.approx(6.5 - 90.0, abs=0.1)
    assert log.info.motion_model == "ackermann" and log.info.wheelbase == 2.83 and log.info.encoder_offset == 0.76
    np.testing.assert_allclose(log.info.sensor.offset, [3.78, 0.50])
    # One fix of the failing receiver jumps 141 m away and back: dropped, counted; the truth is at the antenna.
    assert data.meta["gps_spikes_dropped"] == 1 and log.truth_pose.shape == (4465, 3)
    assert np.all(np.isnan(log.truth_pose[:, 2])) and data.meta["truth_offset"] == [3.78, 0.50]
    assert not np.any(np.isclose(log.truth_stamp, 1223.284)) and np.any(np.isclose(log.truth_stamp, 1227.689))
    assert np.allclose(log.odom_dt, 0.025, atol=2e-3)
    assert data.meta["diameter"].shape == (52974,)


def _car_park_early_detection_distance(data) -> np.ndarray:
    """Over the first 30 s, each detection placed from dead reckoning at its scan's stamp: its distance to the
    nearest surveyed beacon."""
    log = data.robots["r1"]
    model, sensor = AckermannModel(), RangeBearingSensor(tuple(log.info.sensor.offset))
    pose, poses, t = log.info.start_pose, {}, log.odom_stamp[0] - log.odom_dt[0]
    for k in range(log.odom_stamp.size):
        if log.odom_stamp[k] > t + 30.0:
            break
        pose = model.step(pose, log.odom_control[k], log.odom_dt[k])
        poses[k] = pose
    stamps = log.odom_stamp[: len(poses)]
    early = np.flatnonzero(log.scan_stamp < stamps[-1])
    scan_of = np.repeat(early, np.diff(log.scan_offsets)[early])
    nearest = np.searchsorted(stamps, log.scan_stamp[scan_of]).clip(0, len(poses) - 1)
    at = np.array([poses[int(k)] for k in nearest])
    index = np.concatenate([np.arange(log.scan_offsets[s], log.scan_offsets[s + 1]) for s in early])
    placed = sensor.inverse(at, np.column_stack([log.det_range[index], log.det_bearing[index]]))
    return np.min(np.linalg.norm(placed[:, None] - data.landmarks[None], axis=-1), axis=1)


@needs_data
def test_car_park_counts_detector_and_start_pose():
    data = load_dataset("car-park:acfr_car_park")
    log = data.robots["r1"]
    assert data.meta["odometry_rows"] == 5001 and data.meta["gps_fixes"] == 626 and log.scan_stamp.size == 586
    assert data.landmarks.shape == (15, 2)
    assert data.meta["start_fit_rmse_m"] < 0.5
    detector = data.meta["detector"]
    assert detector["detections"] == log.det_range.size > 500
    assert np.all((log.det_range >= 1.0) & (log.det_range <= 30.0))
    # Over the first 30 s dead reckoning is good: every detection lands on a surveyed beacon.
    distance = _car_park_early_detection_distance(data)
    assert distance.size > 100 and np.mean(distance < 1.0) > 0.95


@needs_data
def test_car_park_scans_moved_back_by_the_laser_delay_land_closer_to_the_survey():
    data, stamped = load_dataset("car-park:acfr_car_park"), load_dataset("car-park:acfr_car_park", scan_delay_s=0.0)
    assert data.meta["scan_delay_s"] == 0.047 and stamped.meta["scan_delay_s"] == 0.0
    assert np.allclose(stamped.robots["r1"].scan_stamp - data.robots["r1"].scan_stamp, 0.047)
    assert np.array_equal(stamped.robots["r1"].det_range, data.robots["r1"].det_range)
    # the delay was measured without the survey (benchmarks/sensor_timing.py); the survey agrees with it
    delayed, as_stamped = _car_park_early_detection_distance(data), _car_park_early_detection_distance(stamped)
    assert delayed.size == as_stamped.size
    assert np.median(delayed) < 0.8 * np.median(as_stamped)


def test_gps_spikes_flags_only_a_fix_that_jumps_away_from_both_neighbours():
    stamps = np.arange(8) * 0.2
    xy = np.column_stack([stamps * 5.0, np.zeros(8)])
    xy[3] += [0.0, 40.0]       # an isolated jump: out and back
    xy[6:] += [0.0, 30.0]      # a step that stays: the receiver moved its solution, not a spike
    spikes = gps_spikes(stamps, xy, max_speed=10.0, slack=5.0)
    assert spikes.tolist() == [False, False, False, True, False, False, False, False]
    assert not gps_spikes(stamps[:2], xy[:2], 10.0, 5.0).any()
