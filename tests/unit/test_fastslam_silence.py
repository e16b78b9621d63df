"""Silences of confirmed landmarks (central/fastslam/silence.py): a copy no robot sees again is deleted, the null
learned from the map, the kernel against its numpy reference."""

from __future__ import annotations

import math

import numpy as np
import pytest

from central.fastslam import kernels, silence
from central.fastslam.config import FastSlamConfig
from central.fastslam.core import FastSlam
from robots.simulator import simulate
from robots.worlds import make_world
from schemas.contract import OdomEvent, ScanEvent


def test_the_threshold_is_the_level_an_exponential_tail_passes_with_probability_alpha():
    rng = np.random.default_rng(0)
    ended = rng.exponential(5.0, 20_000)
    threshold = silence.tail_threshold(ended, np.zeros(0), 0.95, 0.05)
    u = np.quantile(ended, 0.95)
    # above u the excess is exponential with scale 5: P(any of the ~1000 above u passes) = 1000 e^(-(t-u)/5) = 0.05
    assert threshold == pytest.approx(u + 5.0 * math.log(1000 / 0.05), rel=0.05)
    trials = [(rng.exponential(5.0, 20_000) > threshold).any() for _ in range(200)]
    assert 0.01 < np.mean(trials) < 0.12


def test_ongoing_silences_count_as_censored_and_raise_the_threshold():
    """Early in a run only short silences have ended: the silences still going on say the tail is longer."""
    ended = np.random.default_rng(1).exponential(2.0, 400)
    alone = silence.tail_threshold(ended, np.zeros(0), 0.95, 0.05)
    ongoing = np.array([30.0, 40.0, 1.0])
    assert silence.tail_threshold(ended, ongoing, 0.95, 0.05) > 1.5 * alone
    assert silence.tail_threshold(np.zeros(0), ongoing, 0.95, 0.05) == math.inf


def scan_inputs(seed: int, count: int = 12, slots_total: int = 20) -> tuple:
    rng = np.random.default_rng(seed)
    slots = rng.choice(slots_total, count, replace=False).astype(np.int64)
    confirmed = rng.random(count) < 0.8
    hit = rng.random(count) < 0.4
    zhat = np.stack([rng.uniform(0.2, 7.0, count), rng.uniform(-1.2, 1.2, count)], -1)
    h_x = rng.normal(size=(count, 2, 3))
    own = np.array([np.diag(rng.uniform(0.001, 0.05, 2)) for _ in range(count)])
    pose_cov = np.diag([0.04, 0.04, 0.01])
    r = np.diag([0.15**2, 0.025**2])
    silences = rng.uniform(0.0, 5.0, slots_total) * (rng.random(slots_total) < 0.7)
    views = np.where(rng.random((slots_total, 1)) < 0.5, np.nan, 0.0) + rng.uniform(0.2, 7.0, (slots_total, 2))
    views[:3] = np.nan
    views[slots[:2]] = zhat[:2] + 1e-3  # two views from (nearly) the same viewpoint
    counts = np.abs(rng.normal(5.0, 2.0, (2, silence.RANGE_BINS)))
    counts[0] = np.minimum(counts[0], counts[1])
    return slots, confirmed, hit, zhat, h_x, own, pose_cov, r, 0.1, 6.0, 0.9, silences, views, counts


def copies(args: tuple) -> list:
    return [a.copy() if isinstance(a, np.ndarray) else a for a in args]


@pytest.mark.parametrize("seed", range(6))
def test_the_kernel_counts_and_deletes_as_the_reference(seed):
    args = scan_inputs(seed)
    probe = copies(args)
    silence.silence_reference(*probe, 9.21, math.inf)
    grown = probe[11][args[0]] > args[11][args[0]]
    assert grown.any()  # some landmark missed from a new viewpoint
    threshold = float(np.median(probe[11][args[0]][grown])) - 1e-9  # deletes some of them, not all
    expected, got = copies(args), copies(args)
    ended_ref, deleted_ref = silence.silence_reference(*expected, 9.21, threshold)
    ended, deleted = kernels.silence_kernel(*got, 9.21, threshold)
    np.testing.assert_allclose(ended, ended_ref)
    np.testing.assert_array_equal(deleted, deleted_ref)
    for index in (11, 12, 13):  # silences, views, counts
        np.testing.assert_allclose(got[index], expected[index], equal_nan=True)
    assert deleted_ref.any() and ended_ref.size > 0
    assert not np.isnan(got[12][args[0][args[2] & args[1]]]).any()  # an association sets the last view


def ghost_run(on: bool, seed: int = 0) -> tuple[FastSlam, int, np.ndarray]:
    """One robot maps the arena for 90 s, its scans missing a landmark now and then (P_D 0.8), with a confirmed
    landmark loaded where nothing stands: the copy a robot leaves after mapping from a wrong pose. (the filter, the
    copy's id, the true landmarks)."""
    world = make_world("arena", seed)
    data = simulate(world, robots=1, seed=seed, duration=90.0, detection_probability=0.8)
    log = data.robots["r1"]
    xs = np.linspace(log.truth_pose[:, 0].min(), log.truth_pose[:, 0].max(), 25)
    ys = np.linspace(log.truth_pose[:, 1].min(), log.truth_pose[:, 1].max(), 25)
    grid = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)
    ghost = grid[np.linalg.norm(grid[:, None] - world.landmarks[None], axis=-1).min(1).argmax()]
    slam = FastSlam(FastSlamConfig(particles=30, association="shared", seed=seed, silence=on, silence_min_ended=50,
                                   reacquire=False), [log.info])
    ghost_id = 10_000
    slam.load_landmarks([ghost_id], [ghost], [np.eye(2) * 0.01])
    for event in data.events():
        if isinstance(event, OdomEvent):
            slam.on_odometry(event)
        elif isinstance(event, ScanEvent):
            slam.on_scan(event)
    return slam, ghost_id, world.landmarks


def test_a_landmark_no_robot_sees_again_is_deleted_and_the_true_ones_stay():
    slam, ghost, truth = ghost_run(True)
    assert ghost not in slam.known_slots
    assert slam.counts["landmarks_silenced"] == 1
    means = slam.landmark_map().means
    assert np.linalg.norm(means[:, None] - truth[None], axis=-1).min(1).max() < 0.5  # what is left is true
    assert slam.silences.ended_total >= 50 and math.isfinite(slam.silences.threshold)
    kept, ghost, _ = ghost_run(False)
    assert ghost in kept.known_slots and kept.counts["landmarks_silenced"] == 0
