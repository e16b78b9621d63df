"""The timing analysis of ``benchmarks/sensor_timing.py``: it finds a delay put into a simulated robot's stamps."""

from dataclasses import replace

import numpy as np
import pytest

from benchmarks.support.timing import (best_shift, dead_reckoning, detection_scatter, detection_truth_error,
                                      odometry_truth_lag)
from robots.loaders import load_dataset

SHIFTS = np.round(np.arange(-0.3, 0.3001, 0.025), 4)


@pytest.fixture(scope="module")
def log():
    dataset = load_dataset("sim:arena", seed=3, duration=60.0, odom_factor=4)
    return dataset, next(iter(dataset.robots.values()))


def test_best_shift_refines_the_grid_minimum_by_a_parabola():
    shifts = np.arange(-0.2, 0.21, 0.05)
    assert best_shift(shifts, (shifts - 0.07) ** 2) == pytest.approx(0.07)
    assert best_shift(shifts, shifts) == pytest.approx(-0.2)  # at the edge: the grid point


def test_dead_reckoning_keeps_the_heading_continuous_for_interpolation(log):
    _, robot = log
    stamps, poses = dead_reckoning(robot)
    assert np.ptp(poses[:, 2]) > 2 * np.pi  # the robot turns more than once around: a wrapped heading would jump
    assert np.abs(np.diff(poses[:, 2])).max() < 0.5
    assert stamps.shape == (poses.shape[0],)


@pytest.mark.parametrize("delay", [0.0, 0.1, -0.15])
def test_detections_stamped_late_are_found_early_against_odometry(log, delay):
    _, robot = log
    late = replace(robot, scan_stamp=robot.scan_stamp + delay)
    assert best_shift(SHIFTS, detection_scatter(late, SHIFTS, window=2.0, gate=1.0)) == pytest.approx(-delay, abs=0.03)


@pytest.mark.parametrize("delay", [0.0, 0.2])
def test_delays_against_the_truth(log, delay):
    dataset, robot = log
    late = replace(robot, scan_stamp=robot.scan_stamp + delay, odom_stamp=robot.odom_stamp + delay)
    error = detection_truth_error(late, dataset.landmarks, np.asarray(dataset.landmark_ids), SHIFTS)
    assert best_shift(SHIFTS, error) == pytest.approx(-delay, abs=0.03)
    assert best_shift(SHIFTS, odometry_truth_lag(late, SHIFTS)) == pytest.approx(-delay, abs=0.03)
