"""The compiled MCL kernels (likelihood, cluster merging) against their numpy and scipy references on seeded scenes."""

import dataclasses
import math

import numpy as np
import pytest

from robots.models import RangeBearingSensor
from schemas.messages import SensorSpec
from services.compiled import warm_up
from services.mcl import kernels
from services.mcl.config import MclConfig
from services.mcl.clustering import grid_labels
from services.mcl.likelihood import LandmarkMap, ScanModel, scan_log_likelihood


def scene(seed: int, fov: float, offset: tuple[float, float], clutter: int):
    """200 landmarks in a 40 m square, a noisy scan from near the middle with ``clutter`` false detections,
    and 1000 poses scattered around the truth."""
    rng = np.random.default_rng(seed)
    landmarks = rng.uniform(0.0, 40.0, (200, 2))
    spec = SensorSpec(max_range=6.0, min_range=0.2, fov=fov, noise_cov=np.diag([0.05**2, math.radians(2.0) ** 2]),
                      offset=np.array(offset), detection_probability=0.9)
    config = MclConfig()
    model = ScanModel.from_spec(spec, config.noise_scale, config.clutter_weight, config.miss_floor,
                                config.view_margin_range, config.view_margin_bearing, config.match_sigmas)
    lmap = LandmarkMap(landmarks, model, config.lookup_cell, config.match_candidates)
    truth = np.array([20.0, 20.0, rng.uniform(-math.pi, math.pi)])
    z = RangeBearingSensor(offset).observe(truth, landmarks)
    keep = (z[:, 0] < 6.0) & (z[:, 0] > 0.2) & (np.abs(z[:, 1]) < 0.5 * fov)
    z = z[keep] + rng.normal(0.0, [0.05, math.radians(2.0)], (int(keep.sum()), 2))
    false = np.stack([rng.uniform(0.2, 6.0, clutter), rng.uniform(-0.5 * fov, 0.5 * fov, clutter)], -1)
    poses = truth + rng.normal(0.0, [1.0, 1.0, 0.3], (1000, 3))
    return poses, np.vstack([z, false]), lmap, model


@pytest.mark.parametrize("seed, fov, offset, clutter", [
    (0, math.radians(120.0), (0.0, 0.0), 0),
    (1, 2 * math.pi, (0.0, 0.0), 2),
    (2, math.radians(180.0), (0.3, -0.1), 1),
    (3, math.radians(60.0), (0.5, 0.0), 3),
])
def test_kernel_gives_the_reference_log_likelihood(seed, fov, offset, clutter):
    assert kernels.AVAILABLE  # numba is a declared dependency
    poses, z, lmap, model = scene(seed, fov, offset, clutter)
    reference, reference_quality = scan_log_likelihood(poses, z, lmap, model, compiled=False)
    compiled, compiled_quality = scan_log_likelihood(poses, z, lmap, model, compiled=True)
    assert len(z) >= 2
    assert np.ptp(reference) > 10.0  # the scene tells poses apart: agreement is not trivial
    np.testing.assert_allclose(compiled, reference, atol=2e-3, rtol=1e-5)  # double against single precision
    np.testing.assert_allclose(compiled_quality, reference_quality, rtol=1e-2)


def test_kernel_counts_missed_landmarks_like_the_reference():
    poses, z, lmap, model = scene(4, math.radians(120.0), (0.0, 0.0), 0)
    no_miss = dataclasses.replace(model, miss_probability=1.0)
    # one observation left: the other landmarks the poses predict in view are missed, and cost log p_miss each
    penalty = {}
    for compiled in (False, True):
        with_misses, _ = scan_log_likelihood(poses, z[:1], lmap, model, compiled=compiled)
        without, _ = scan_log_likelihood(poses, z[:1], lmap, no_miss, compiled=compiled)
        penalty[compiled] = (with_misses - without) / math.log(model.miss_probability)
    np.testing.assert_allclose(penalty[True], penalty[False], atol=1e-3)
    assert np.all(np.abs(penalty[True] - np.round(penalty[True])) < 1e-3)  # whole landmarks
    assert penalty[True].max() >= 2 and len(np.unique(np.round(penalty[True]))) >= 3


def test_warm_up_compiles_within_seconds():
    assert 0.0 <= warm_up() < 120.0


@pytest.mark.parametrize("seed", range(4))
def test_cluster_kernel_gives_the_reference_labels(seed):
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-10.0, 10.0, (6, 3))
    poses = np.concatenate([c + rng.normal(0.0, [0.8, 0.8, 0.4], (300, 3)) for c in centres])
    poses[:, 2] = (poses[:, 2] + np.pi) % (2 * np.pi) - np.pi  # some clusters straddle ±π
    args = (2.0, math.radians(45.0), 2.0, math.radians(45.0))
    reference = grid_labels(poses, *args, compiled=False)
    compiled = grid_labels(poses, *args, compiled=True)
    np.testing.assert_array_equal(compiled, reference)
    assert 2 <= len(np.unique(reference)) < len(np.unique(np.floor(poses[:, :2] / 2.0), axis=0))  # cells do merge


@pytest.mark.parametrize("seed, fov, observations, draws", [
    (5, math.radians(120.0), None, 8),  # a whole scan, the one-point check ranking the draws
    (6, 2 * math.pi, None, 1),
    (7, math.radians(180.0), 2, 8),  # two observations: pairs, no check
    (8, math.radians(120.0), 1, 8),  # one: circles round random landmarks
])
def test_resetting_kernels_draw_the_reference_poses(seed, fov, observations, draws):
    """Sensor resetting by the kernels takes the same random draws in the same order as the numpy reference, so the
    candidate poses agree to rounding (atan2, sin and cos of libm against numpy's), and so does the generator after."""
    from services.mcl.resetting import poses_from_scan

    _, z, lmap, model = scene(seed, fov, (0.2, 0.0), 1)
    z = z[:observations]
    got = {}
    for compiled in (False, True):
        rng = np.random.default_rng(seed)
        poses = poses_from_scan(z, lmap, model, 1500, 3.0, 0.05, 0.02, 2.0, rng, draws, compiled=compiled)
        got[compiled] = (poses, rng.random())
    assert len(z) == (observations or len(z)) and len(z) >= 1
    assert np.ptp(got[False][0][:, 0]) > 1.0  # candidates spread over the map: agreement is not trivial
    np.testing.assert_allclose(got[True][0], got[False][0], atol=1e-9)
    assert got[True][1] == got[False][1]
