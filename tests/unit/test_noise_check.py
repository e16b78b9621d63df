"""The noise-model check of ``benchmarks/odometry_noise.py``: on a simulated robot whose odometry noise is known it
predicts the scatter measured, and more when the model claims a looser odometry."""

from dataclasses import replace

import numpy as np
import pytest

from benchmarks.support.noise_check import pair_scatter, within_gate_second_moment
from robots.loaders import data_root, load_dataset

BINS = np.array([0.0, 1.0, 2.0, 4.0, 8.0])


@pytest.fixture(scope="module")
def noisy():
    """A simulated robot whose controls carry 0.1 (m/s, rad/s) more noise per reading, which its covariance says."""
    log = next(iter(load_dataset("sim:arena", seed=3, duration=60.0, odom_factor=4).robots.values()))
    rng = np.random.default_rng(5)
    return replace(log, odom_control=log.odom_control + 0.1 * rng.standard_normal(log.odom_control.shape),
                   odom_cov=log.odom_cov + np.diag([0.1**2, 0.1**2]))


def test_a_model_that_fits_predicts_the_measured_scatter(noisy):
    rows = pair_scatter(noisy, BINS, draws=20)
    assert all(row["pairs"] > 1000 for row in rows)
    for row in rows:
        assert row["predicted_m"] == pytest.approx(row["measured_m"], rel=0.1)
        assert row["predicted_m"] ** 2 == pytest.approx(row["odometry_m"] ** 2 + row["sensor_m"] ** 2)
    assert rows[-1]["odometry_m"] > 2.0 * rows[0]["odometry_m"]  # dead reckoning drifts with the time between scans


def test_a_model_too_loose_predicts_more_than_is_measured(noisy):
    rows = pair_scatter(noisy, BINS, draws=20, odom_scale=4.0)
    assert rows[-1]["predicted_m"] > 1.3 * rows[-1]["measured_m"]
    assert all(row["predicted_m"] > row["measured_m"] for row in rows)


def test_the_gated_second_moment_matches_draws_cut_at_the_gate():
    rng = np.random.default_rng(11)
    for variance, gate in ((0.04, 1.0), (1.0, 1.0), (9.0, 0.5)):
        d = rng.standard_normal((200_000, 2)) * np.sqrt(variance / 2)
        r2 = np.sum(d**2, axis=1)
        assert within_gate_second_moment(np.array([variance]), gate)[0] == pytest.approx(
            r2[r2 < gate**2].mean(), rel=0.02)


def test_the_gated_second_moment_has_its_limits():
    assert within_gate_second_moment(np.array([0.01]), 10.0)[0] == pytest.approx(0.01)  # the gate cuts nothing
    assert within_gate_second_moment(np.array([1e6]), 1.0)[0] == pytest.approx(0.5, rel=1e-3)  # an even disc
    assert np.all(np.diff(within_gate_second_moment(np.array([0.1, 0.5, 2.0, 8.0]), 1.0)) > 0)


def test_a_tight_gate_cuts_the_prediction_as_it_cuts_the_measured_scatter(noisy):
    rows = pair_scatter(noisy, BINS, gate=0.3, draws=10)
    for row in rows:
        assert row["gated_m"] == pytest.approx(row["measured_m"], rel=0.1)
    assert rows[-1]["predicted_m"] > 1.25 * rows[-1]["measured_m"]  # uncut, the model that fits seems too loose


def test_within_the_gate_a_model_too_loose_still_predicts_more(noisy):
    fits = pair_scatter(noisy, BINS, gate=0.3, draws=10)
    loose = pair_scatter(noisy, BINS, gate=0.3, draws=10, odom_scale=4.0, sensor_scale=25.0)
    for tight, wide in zip(fits, loose):
        assert tight["gated_m"] <= tight["predicted_m"] and tight["gated_m"] < 0.3
        assert wide["gated_m"] > tight["gated_m"]
    assert loose[-1]["gated_m"] > 1.2 * loose[-1]["measured_m"]


@pytest.mark.skipif(data_root() is None, reason="real data sets not found (set FLEETSLAM_DATA or add ../shared/data)")
def test_victoria_parks_odometry_model_is_looser_than_its_scatter():
    """Within a 0.5 m gate, the sensor at the detections' scan-to-scan repeatability (its covariance / 100): the
    loader's odometry (the ACFR example's) predicts more than the scatter in every interval, σ/√2 still no less."""
    log = load_dataset("victoria-park:victoria_park").robots["r1"]
    assert np.allclose(np.sqrt(np.diag(log.odom_cov)), [0.7, np.radians(7.0)])
    bins = np.array([0.0, 1.0, 4.0, 16.0])
    example = pair_scatter(log, bins, gate=0.5, draws=5, sensor_scale=0.01)
    tighter = pair_scatter(log, bins, gate=0.5, draws=5, sensor_scale=0.01, odom_scale=0.5)
    for theirs, ours in zip(example, tighter):
        assert theirs["pairs"] > 10_000
        assert ours["gated_m"] >= ours["measured_m"]
        assert theirs["gated_m"] > 1.1 * theirs["measured_m"] and theirs["gated_m"] > ours["gated_m"]
