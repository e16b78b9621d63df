"""FastSLAM on several workers: the parallel kernels give the serial kernels' numbers bit for bit, on any thread count,
and a whole run gives the same trajectories and map with 1 worker as with 2 (the same seed)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from central.fastslam import association, kernels
from central.fastslam.config import FastSlamConfig, available_cores
from central.fastslam.core import FastSlam
from robots.loaders import data_root, load_dataset
from robots.models import RangeBearingSensor
from robots.simulator import simulate
from schemas.config import CentralSettings, RunSettings
from schemas.contract import OdomEvent, RunOptions, ScanEvent
from services.offline import run_estimator, run_options
from tests.unit.test_fastslam_kernels import gaussians, random_map

REAL_USE_THREADS = kernels.use_threads


@pytest.fixture(params=[1, 2], ids=["parallel-1-thread", "parallel-2-threads"])
def threads(request, monkeypatch):
    """The parallel kernels, run on 1 thread or on 2 (the wrappers take workers=2 and get this many threads)."""
    monkeypatch.setattr(kernels, "use_threads", lambda workers: REAL_USE_THREADS(request.param))
    yield request.param
    REAL_USE_THREADS(kernels.max_threads())


def shared_map(seed: int):
    """:func:`random_map` resampled so that pairs of particles share blocks: the kernels copy on write, and the last
    holder of a block updates it in place."""
    lmap = random_map(seed)
    lmap.select(np.repeat(np.arange(20), 2))
    return lmap


def map_state(lmap) -> list[np.ndarray]:
    """Everything a kernel may change in an :class:`AlignedMap`, its block bookkeeping included."""
    return [*gaussians(lmap), lmap.table.copy(), lmap.refs.copy(), lmap.free_blocks[:lmap.free_count[0]].copy(),
            lmap.free_count.copy(), lmap.exist.copy(), lmap.hits.copy()]


def assert_identical(got: list, expected: list) -> None:
    assert len(got) == len(expected)
    for a, b in zip(got, expected):
        np.testing.assert_array_equal(a, b)


def scan_inputs(seed: int, lmap):
    rng = np.random.default_rng(seed)
    pose = rng.normal([0.5, -0.5, 2.0], [0.3, 0.3, 0.2], (40, 3))
    slots = np.array([3, 7, 0, 11, 5])
    truth = gaussians(lmap)[0][0, slots] + rng.normal(0.0, 0.3, (5, 2))
    z = RangeBearingSensor().observe(pose[0], truth) + rng.normal(0.0, [0.1, 0.05], (5, 2))
    return rng, pose, slots, z, np.array([[0.04, 0.001], [0.001, 0.003]])


@pytest.mark.parametrize("seed", [0, 1])
def test_parallel_known_update_gives_the_serial_numbers_and_the_reference(seed, threads):
    sensor = RangeBearingSensor((0.4, -0.2))
    serial, parallel, reference = shared_map(seed), shared_map(seed), shared_map(seed)
    _, pose, slots, z, r = scan_inputs(seed, serial)
    expected = kernels.known_update(serial, sensor, pose, slots, z, r, 1.0, 6.0, workers=1)
    got = kernels.known_update(parallel, sensor, pose, slots, z, r, 1.0, 6.0, workers=2)
    assert np.ptp(expected) > 1.0  # the particles disagree: agreement is not trivial
    np.testing.assert_array_equal(got, expected)
    assert_identical(map_state(parallel), map_state(serial))
    slam = SimpleNamespace(map=reference, pose=pose[:, None], config=FastSlamConfig(exist_hit=1.0, exist_max=6.0))
    numpy_ll = association.known_update_reference(slam, SimpleNamespace(index=0, sensor=sensor), slots, z, r)
    np.testing.assert_allclose(got, numpy_ll, rtol=1e-10, atol=1e-10)
    for a, b in zip(gaussians(parallel), gaussians(reference)):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("seed", [0, 3])
def test_parallel_proposal_step_gives_the_serial_numbers_blocks_and_tables(seed, threads):
    """The FastSLAM 2.0 step: poses, weights, landmarks, the blocks handed out and the spatial index's boxes."""
    sensor = RangeBearingSensor((0.4, -0.2))
    serial, parallel = shared_map(seed), shared_map(seed)
    rng, pose, slots, z, r = scan_inputs(seed, serial)
    delta, motion_cov = np.array([0.3, 0.02, 0.05]), np.diag([0.02, 0.01, 0.004])
    normals = rng.standard_normal((40, 3))
    poses = {}
    weights = {}
    for workers, lmap in ((1, serial), (2, parallel)):
        poses[workers] = pose.copy()
        weights[workers] = kernels.propose(lmap, sensor, poses[workers], delta, motion_cov, slots, z, r, 4, normals,
                                           1e-12, 1.0, 6.0, workers=workers)
    assert np.ptp(weights[1]) > 1.0 and np.abs(poses[1] - pose).max() > 0.1
    np.testing.assert_array_equal(weights[2], weights[1])
    np.testing.assert_array_equal(poses[2], poses[1])
    assert_identical(map_state(parallel), map_state(serial))
    np.testing.assert_array_equal(parallel.near(np.zeros(2), 50.0), serial.near(np.zeros(2), 50.0))  # the boxes
    assert serial.blocks_in_use() > shared_map(seed).blocks_in_use()  # copies were made


def feed(slam: FastSlam, data) -> None:
    for event in data.events():
        if isinstance(event, OdomEvent):
            slam.on_odometry(event)
        elif isinstance(event, ScanEvent):
            slam.on_scan(event)


@pytest.mark.parametrize("association_name, proposal_name", [("shared", "auto"), ("known", "fastslam1"),
                                                             ("known", "fastslam2")])
def test_a_simulated_run_gives_the_same_trajectories_and_map_on_1_and_2_workers(association_name, proposal_name):
    data = simulate("arena", robots=3, seed=5, duration=25.0, clutter_rate=0.5)
    infos = [log.info for log in data.robots.values()]
    runs = {}
    for workers in (1, 2):
        runs[workers] = FastSlam(FastSlamConfig(particles=60, association=association_name, proposal=proposal_name,
                                                seed=7, workers=workers), infos)
        assert runs[workers].workers == min(workers, kernels.max_threads())
        feed(runs[workers], data)
    one, two = runs[1], runs[2]
    assert one.counts["resamples"] > 0 and one.counts["detections"] > 100
    np.testing.assert_array_equal(two.pose, one.pose)
    np.testing.assert_array_equal(two.logw, one.logw)
    got, expected = two.landmark_map(), one.landmark_map()
    assert len(expected.means) > 5
    np.testing.assert_array_equal(got.means, expected.means)
    np.testing.assert_array_equal(got.covs, expected.covs)


@pytest.mark.data
@pytest.mark.skipif(data_root() is None, reason="real data sets not found (set FLEETSLAM_DATA or add ../shared/data)")
def test_mrclam_without_barcodes_gives_the_same_trajectories_and_map_on_1_and_2_workers():
    data = load_dataset("mrclam:")
    runs = {workers: run_estimator(data, RunOptions(estimator="fastslam", association="unknown", particles=100, seed=3,
                                                    settings={"workers": workers}), None, 40.0)
            for workers in (1, 2)}
    assert runs[1].events["scan"] > 300
    assert runs[1].trajectories.keys() == runs[2].trajectories.keys()
    for rid, trajectory in runs[1].trajectories.items():
        np.testing.assert_array_equal(runs[2].trajectories[rid].poses, trajectory.poses)
    assert len(runs[1].map_means) > 3
    np.testing.assert_array_equal(runs[2].map_means, runs[1].map_means)


def test_workers_none_means_the_cores_the_process_may_use():
    assert FastSlamConfig().workers == 1  # the measured choice (docs/results.md, issue 54)
    assert FastSlamConfig(workers=None).worker_count == available_cores() >= 1
    assert FastSlamConfig(workers=3).worker_count == 3
    assert FastSlam(FastSlamConfig(workers=1)).workers == 1
    assert FastSlam(FastSlamConfig(workers=64)).workers == kernels.max_threads()  # capped at numba's pool
    assert FastSlam(FastSlamConfig(workers=4, compiled=False)).workers == 1  # the numpy references: one core
    with pytest.raises(ValueError):
        FastSlamConfig(workers=0)


def test_workers_flag_reaches_the_filter_of_run_and_central():
    run = RunSettings(estimator="fastslam", workers=2)
    assert run_options(run, None).settings == {"workers": 2}
    assert run_options(RunSettings(estimator="fastslam", workers=2, estimator_settings="workers=1"),
                       None).settings == {"workers": 1}
    assert run_options(RunSettings(estimator="dslam", workers=2), None).settings == {}
    assert CentralSettings(workers=2).core(FastSlamConfig).workers == 2
    assert CentralSettings().core(FastSlamConfig).workers == 1
