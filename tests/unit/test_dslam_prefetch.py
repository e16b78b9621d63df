"""Covariance columns solved between scans: :meth:`DSlam.column_prefetch` picks the columns a placed robot will
soon need, and the D-SLAM service solves them in a worker thread, then caches them under its map lock."""

import asyncio

import numpy as np

from schemas.config import DslamSettings
from schemas.messages import RobotInfo, SensorSpec
from services.dslam.config import DslamConfig
from services.dslam.core import DSlam
from services.dslam.service import DslamService

SENSOR = SensorSpec(max_range=5.0, fov=np.pi, noise_cov=np.diag([0.05**2, 0.02**2]))


def grid_map(core: DSlam, side: int = 12, spacing: float = 3.0) -> np.ndarray:
    """A map of side² landmarks (ids 0..side²−1) as prior information, factored as a scan's solve would, with its
    columns evicted down to ``column_cache`` (loading them in chunks had grown the cache to hold them all)."""
    axis = spacing * np.arange(side)
    means = np.stack(np.meshgrid(axis, axis), -1).reshape(-1, 2)
    core.load_landmarks(np.arange(means.shape[0]), means, np.tile(np.diag([0.04, 0.04]), (means.shape[0], 1, 1)))
    core.map.factorise()
    core.map.cache.capacity = core.config.column_cache
    core.map._evict([])
    assert len(core.map.cache) == core.config.column_cache
    return means


def robot_at(core: DSlam, pose) -> None:
    core.add_robot(RobotInfo(robot_id="r1", stamp=0.0, motion_model="unicycle", sensor=SENSOR, start_pose=pose,
                             odom_rate_hz=10.0, scan_rate_hz=10.0))


def test_column_prefetch_takes_the_nearest_uncached_landmarks_within_reach():
    core = DSlam(DslamConfig(association="known", column_cache=4, column_prefetch_batch=5))
    means = grid_map(core)
    assert core.column_prefetch() is None  # no placed robot
    robot_at(core, [16.5, 16.5, 0.0])
    job = core.column_prefetch()
    reach = SENSOR.max_range + core.config.candidate_margin + core.config.column_prefetch_margin
    distance = np.hypot(*(means[job.landmarks] - [16.5, 16.5]).T)
    assert len(job.landmarks) == 5 and np.all(distance <= reach) and np.all(np.diff(distance) >= 0)
    within = np.hypot(*(means - [16.5, 16.5]).T) <= reach
    assert np.all(distance <= np.sort(np.hypot(*(means[within] - [16.5, 16.5]).T))[4] + 1e-12)
    assert core.take_prefetched(job, job.run()) == 5
    assert all(core.index_of[k] in core.map.cache for k in job.landmarks)
    off = DSlam(DslamConfig(association="known", column_prefetch_margin=0.0))
    grid_map(off)
    robot_at(off, [16.5, 16.5, 0.0])
    assert off.column_prefetch() is None


def test_the_service_solves_columns_between_scans_and_caches_them_exactly():
    service = DslamService(DslamSettings(association="known", column_cache=4, column_prefetch_batch=6))
    grid_map(service.core)
    robot_at(service.core, [16.5, 16.5, 0.0])

    async def between_scans():
        async with service._lock:
            service._start_prefetch()
        await service._prefetch

    asyncio.run(between_scans())
    cached = [i for i in range(service.core.map.n) if i in service.core.map.cache]
    assert service.core.map.columns_prefetched == 6 and len(cached) >= 6
    solves = service.core.map.column_solves
    reference = np.linalg.inv(service.core.map.matrix.tocsr().toarray())  # the test's reference only
    for i in cached:
        np.testing.assert_allclose(service.core.map.marginals(np.array([i]))[0],
                                   reference[2 * i:2 * i + 2, 2 * i:2 * i + 2], atol=1e-12)
    assert service.core.map.column_solves == solves


def test_a_robot_without_a_pose_waits_for_the_columns_of_what_it_saw_and_loses_no_scan():
    """With ``prefetching`` (the service), the scan of a robot without a pose that sees mapped landmarks whose
    columns are not cached is kept (counted), their columns are solved between scans, and the next scan places the
    robot, after the kept one, without a solve of its own; without it (offline) the first scan solves them and
    places the robot at once."""
    from schemas.contract import ScanEvent

    pose = np.array([16.5, 16.5, 0.3])
    noise = np.asarray(SENSOR.noise_cov, float)

    def scan(seq, means):
        seen = [k for k in range(means.shape[0]) if 0.5 < np.hypot(*(means[k] - pose[:2])) < 4.5
                and abs(np.arctan2(*(means[k] - pose[:2])[::-1]) - pose[2]) < 1.2]
        d = means[seen] - pose[:2]
        bearing = np.arctan2(d[:, 1], d[:, 0]) - pose[2]
        return ScanEvent("r1", seq, 1.0 + seq, np.hypot(d[:, 0], d[:, 1]), bearing, np.array(seen, np.int64), noise)

    for prefetching in (True, False):
        core = DSlam(DslamConfig(association="known", column_cache=4))
        means = grid_map(core)
        core.add_robot(RobotInfo(robot_id="r1", stamp=0.0, motion_model="unicycle", sensor=SENSOR,
                                 odom_rate_hz=10.0, scan_rate_hz=10.0))
        core.prefetching = prefetching
        first = scan(0, means)
        assert len(first.landmark_ids) >= 2 and not any(core.index_of[k] in core.map.cache for k in first.landmark_ids)
        solves = core.map.column_solves
        core.on_scan(first)
        if not prefetching:
            assert core.robot_pose("r1") is not None and core.map.column_solves > solves
            continue
        assert core.robot_pose("r1") is None and core.counts["scans_deferred"] == 1 and core.counts["scans"] == 0
        job = core.column_prefetch()
        assert sorted(job.landmarks) == sorted(core.index_of[k] for k in first.landmark_ids)
        core.take_prefetched(job, job.run())
        core.on_scan(scan(1, means))
        placed = core.robot_pose("r1")
        assert placed is not None and core.map.column_solves == solves and core.counts["scans"] == 2
        assert np.hypot(*(placed[0][:2] - pose[:2])) < 0.05 and not core.robots["r1"].deferred
