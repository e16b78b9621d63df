"""The laser point-landmark extractor on constructed scans, the simulated laser, and the car park's real laser."""

import dataclasses
import math

import numpy as np
import pytest

from robots.features import ExtractorConfig, extract_point_landmarks
from robots.loaders import data_root, load_dataset, resolve_path
from robots.loaders.common import find_file, read_table
from robots.models import RangeBearingSensor, dead_reckon, robot_models, se2_compose
from robots.simulator import LaserConfig, simulate, simulate_laser
from robots.worlds import make_world, world_walls

BEAMS, ANGLE_MIN = 361, -math.pi / 2
STEP = math.pi / (BEAMS - 1)  # 0.5°
ANGLES = ANGLE_MIN + STEP * np.arange(BEAMS)


def scan_of(poles: list[tuple[float, float, float]], wall: float = 10.0) -> np.ndarray:
    """Ranges of a scan from the origin: a wall across x = ``wall`` (nothing beyond ±80° of it) and poles given as
    (centre range, centre bearing, radius), each beam stopping at the nearest surface."""
    ranges = np.where(np.abs(ANGLES) < math.radians(80), wall / np.cos(ANGLES), np.inf)
    for distance, bearing, radius in poles:
        offset = distance * np.sin(ANGLES - bearing)  # how far the beam passes from the centre
        along = distance * np.cos(ANGLES - bearing)
        hit = (np.abs(offset) <= radius) & (along > 0)
        entry = along - np.sqrt(np.maximum(radius**2 - offset**2, 0.0))
        ranges = np.where(hit & (entry < ranges), entry, ranges)
    return ranges


def test_a_pole_in_front_of_a_wall_is_one_detection_at_its_place():
    radius = 0.1
    found = extract_point_landmarks(scan_of([(5.0, 0.3, radius)]), ANGLE_MIN, STEP)
    assert found.range.size == 1
    assert found.bearing[0] == pytest.approx(0.3, abs=STEP / 2)
    # the mean of the front surface: about radius·π/4 in front of the centre
    assert found.range[0] == pytest.approx(5.0 - radius * math.pi / 4, abs=0.02)
    assert found.beams[0] >= 4 and found.width[0] <= 2 * radius
    assert found.scan[0] == 0 and found.cov.shape == (1, 2, 2)


def test_the_covariance_is_the_floor_plus_the_spread_of_the_cluster():
    config = ExtractorConfig(range_std=0.05, bearing_std=0.01)
    ranges = np.full(BEAMS, np.inf)
    ranges[100] = 7.0  # one beam: the floor and a beam's angular footprint
    ranges[200:203] = [4.0, 4.1, 4.2]
    found = extract_point_landmarks(ranges, ANGLE_MIN, STEP, config=config)
    np.testing.assert_allclose(found.cov[:, 0, 0], [0.05**2, 0.05**2 + np.var([4.0, 4.1, 4.2])])
    np.testing.assert_allclose(found.cov[:, 1, 1], [0.01**2 + STEP**2 / 12, 0.01**2 + (3 * STEP) ** 2 / 12])
    np.testing.assert_array_equal(found.cov[:, 0, 1], [0.0, 0.0])


def test_two_poles_side_by_side_are_two_detections():
    found = extract_point_landmarks(scan_of([(6.0, 0.10, 0.1), (6.1, 0.20, 0.1)]), ANGLE_MIN, STEP)
    assert found.range.size == 2
    np.testing.assert_allclose(found.bearing, [0.10, 0.20], atol=STEP)


def test_a_pole_half_hidden_behind_another_splits_off_and_fails_the_occlusion_test():
    """The poles overlap in angle, 0.6 m apart in range (more than the 0.3 m jump): two clusters. The far one has
    the near one beside it, so only the near one stands in front of both its neighbours."""
    poles = [(5.0, 0.0, 0.15), (5.6, 0.045, 0.15)]
    found = extract_point_landmarks(scan_of(poles), ANGLE_MIN, STEP)
    assert found.range.size == 1 and found.bearing[0] == pytest.approx(0.0, abs=STEP)
    both = extract_point_landmarks(scan_of(poles), ANGLE_MIN, STEP, config=ExtractorConfig(require_discontinuity=False))
    poles_only = both.range < 8.0  # not the wall, cut up where it grazes
    pole_ranges, pole_bearings = both.range[poles_only], both.bearing[poles_only]
    assert pole_ranges.size == 2 and pole_ranges[1] - pole_ranges[0] > 0.3 and pole_bearings[1] > pole_bearings[0]


def test_invalid_beams_never_form_a_detection():
    ranges = np.full(BEAMS, np.nan)
    ranges[10], ranges[20], ranges[30], ranges[40] = np.inf, -np.inf, 0.0, -3.0
    ranges[50], ranges[60] = 0.2, 45.0  # below min_range, beyond max_range
    ranges[70:73] = [np.nan, np.inf, np.nan]
    loose = ExtractorConfig(require_discontinuity=False)
    assert extract_point_landmarks(ranges, ANGLE_MIN, STEP, config=loose).range.size == 0
    ranges[100:105] = [5.0, 5.0, np.nan, 5.0, 5.0]  # a gap in a pole: two clusters, the NaN in neither
    found = extract_point_landmarks(ranges, ANGLE_MIN, STEP, config=loose)
    np.testing.assert_array_equal(found.beams, [2, 2])
    np.testing.assert_allclose(found.range, [5.0, 5.0])


def test_a_wide_wall_segment_is_not_a_point():
    ranges = scan_of([])
    ranges[150:211] = 4.0  # 30° of a free-standing board at 4 m: about 2 m wide
    assert extract_point_landmarks(ranges, ANGLE_MIN, STEP).range.size == 0
    wide = extract_point_landmarks(ranges, ANGLE_MIN, STEP, config=ExtractorConfig(max_width_m=3.0))
    assert wide.range.size == 1 and wide.width[0] == pytest.approx(2 * 4.0 * math.sin(math.radians(15)), rel=1e-6)


def test_intensity_mode_takes_only_the_reflective_beams():
    ranges, intensity = scan_of([]), np.zeros(BEAMS)
    intensity[240:242] = 8192  # tape on the flat wall
    reflectors = ExtractorConfig(min_intensity=1.0, require_discontinuity=False)
    found = extract_point_landmarks(ranges, ANGLE_MIN, STEP, intensity, reflectors)
    assert found.beams.tolist() == [2]
    assert found.bearing[0] == pytest.approx(ANGLES[240] + STEP / 2)
    assert extract_point_landmarks(ranges, ANGLE_MIN, STEP, intensity).range.size == 0  # geometry: a flat wall
    assert extract_point_landmarks(ranges, ANGLE_MIN, STEP, None, reflectors).range.size > 0  # no intensities given


def test_a_stack_of_scans_gives_what_each_scan_gives():
    data = simulate("random", seed=3, duration=3.0)
    log = data.robots["r1"]
    scans = simulate_laser(make_world("random", 3), log.truth_at(log.scan_stamp), seed=3)
    stack = extract_point_landmarks(scans.ranges, scans.angle_min, scans.angle_increment)
    assert stack.range.size > 5 * scans.ranges.shape[0]
    for s, ranges in enumerate(scans.ranges):
        one = extract_point_landmarks(ranges, scans.angle_min, scans.angle_increment)
        mine = stack.scan == s
        assert np.all(one.scan == 0)
        for field in ("range", "bearing", "cov", "beams", "width"):
            np.testing.assert_array_equal(getattr(one, field), getattr(stack, field)[mine])


def lone_pole_world(position=(5.0, 0.0)):
    return dataclasses.replace(make_world("arena", 0), landmarks=np.array([position], float))


def test_the_simulated_laser_sees_a_pole_at_its_range():
    world = lone_pole_world()
    config = LaserConfig(range_std=0.0, pole_radius=0.15)
    poses = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, math.pi / 4], [0.0, 0.0, math.pi / 2]])
    scans = simulate_laser(world, poses, config)
    assert scans.angle_min == pytest.approx(-math.pi / 2) and scans.angle_increment == pytest.approx(math.radians(0.5))
    assert scans.ranges[0, 180] == pytest.approx(4.85) and scans.pole[0, 180] == 0  # beam 180 looks ahead
    assert scans.ranges[1, 90] == pytest.approx(4.85) and scans.pole[1, 90] == 0  # turned left: the pole 45° right
    assert scans.pole[2, 0] == 0  # turned further: the pole on the first beam, cut by the scan's edge
    found = extract_point_landmarks(scans.ranges, scans.angle_min, scans.angle_increment)
    np.testing.assert_array_equal(found.scan, [0, 1])  # no occlusion edge beyond the scan's first beam
    np.testing.assert_allclose(found.bearing, [0.0, -math.pi / 4], atol=1e-9)
    np.testing.assert_allclose(found.range, 5.0 - 0.15 * math.pi / 4, atol=0.02)


def test_the_simulated_laser_sees_the_walls_around_the_world():
    world = lone_pole_world((0.0, 3.0))  # off the beams checked
    walls = world_walls(world, margin=2.0)
    xmax = walls[:, :, 0].max()
    scans = simulate_laser(world, np.array([[0.0, 0.0, 0.0]]), LaserConfig(range_std=0.0, wall_margin=2.0))
    assert scans.ranges[0, 180] == pytest.approx(xmax) and scans.pole[0, 180] == -1
    assert scans.ranges[0, 120] == pytest.approx(xmax / math.cos(math.radians(30)))
    far = simulate_laser(world, np.array([[0.0, 0.0, 0.0]]), LaserConfig(range_std=0.0, max_range=xmax - 1.0))
    assert np.isinf(far.ranges[0, 180])  # beyond max_range: no return


def test_the_simulated_laser_noise_comes_from_the_seed():
    world, poses = make_world("random", 1), np.array([[0.0, 0.0, 0.3], [1.0, 2.0, -1.0]])
    a, b, c = (simulate_laser(world, poses, seed=s).ranges for s in (7, 7, 8))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    exact = simulate_laser(world, poses, LaserConfig(range_std=0.0)).ranges
    returned = np.isfinite(exact) & np.isfinite(a)
    assert 0.015 < np.std(a[returned] - exact[returned]) < 0.025  # range_std 0.02 by default


ROOT = data_root()


@pytest.mark.data
@pytest.mark.skipif(ROOT is None, reason="real data sets not found (set FLEETSLAM_DATA or add ../shared/data)")
def test_car_park_laser_detections_land_on_the_surveyed_beacons():
    """Over the first 15 s (dead reckoning from the GPS-fitted start is good there), the reflective detections of
    the raw laser all lie within 0.5 m of a surveyed beacon, and geometry alone finds most of the beacons passed."""
    data = load_dataset("car-park:")
    log = data.robots["r1"]
    text = resolve_path("car-park", "") / "text_export"
    ranges = read_table(find_file(text, "laser_range.txt"))[:, 1:]
    intensity = read_table(find_file(text, "laser_intensity.txt"))[:, 1:]
    model, _ = robot_models(log.info)
    path = se2_compose(log.info.start_pose, dead_reckon(model, log.odom_control, log.odom_dt))
    path_stamps = np.concatenate([[log.odom_stamp[0] - log.odom_dt[0]], log.odom_stamp])
    early = np.flatnonzero(log.scan_stamp < log.scan_stamp[0] + 15.0)
    poses = np.column_stack([np.interp(log.scan_stamp[early], path_stamps, column)
                             for column in (path[:, 0], path[:, 1], np.unwrap(path[:, 2]))])
    sensor = RangeBearingSensor(tuple(log.info.sensor.offset))

    def beacons_hit(config):
        found = extract_point_landmarks(ranges[early], -math.pi / 2, math.radians(0.5), intensity[early], config)
        placed = sensor.inverse(poses[found.scan], np.column_stack([found.range, found.bearing]))
        distance = np.linalg.norm(placed[:, None] - data.landmarks[None], axis=-1)
        near = distance.min(axis=1) < 0.5
        return near, set(distance.argmin(axis=1)[near].tolist())

    near, reflective = beacons_hit(ExtractorConfig(min_range=1.0, min_intensity=1.0, require_discontinuity=False))
    assert near.size > 60 and near.all() and len(reflective) >= 7
    _, geometric = beacons_hit(ExtractorConfig(min_range=1.0))
    assert len(geometric) >= 9
