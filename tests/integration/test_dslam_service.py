"""``fleetslam dslam`` over a real router: three robots, the association queryable, one shared map."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

from robots.simulator import simulate
from schemas.keys import Keys
from schemas.messages import MapEstimate, PoseEstimate, ServiceStats
from services.mapfeed import assemble
from tests.helpers import Collector, wait_until

pytestmark = pytest.mark.integration

ROBOTS = ("r1", "r2", "r3")
DURATION = 12.0


def robot_args(rid: str) -> tuple[str, ...]:
    return ("robot", "--id", rid, "--world", "arena", "--seed", "0", "--rate", "10", "--duration", str(DURATION),
            "--speedup", "6", "--start-delay", "1.0", "--no-publish-ids")


def latest(collector: Collector, model):
    decoded = collector.decoded(model)
    return decoded[-1] if decoded else None


def start_dslam(processes, *extra: str):
    return processes.start("dslam", "dslam", "--association", "nn", "--map-period-s", "0.3", "--stats-period-s", "0.3",
                           "--assoc-timeout-s", "1.0", *extra)


def wait_all_scans(stats: Collector, expected: int, processes) -> ServiceStats:
    try:
        wait_until(lambda: (s := latest(stats, ServiceStats)) is not None and s.extra.get("scans", 0) >= expected,
                   120, what=f"dslam to process {expected} scans")
        return latest(stats, ServiceStats)
    except AssertionError as exc:
        last = latest(stats, ServiceStats)
        raise AssertionError(f"{exc}; last stats {last}; log: {processes.log('dslam')[-3000:]}") from None


def test_three_robots_association_service_one_map(router, processes, zsession, prefix):
    keys = Keys(prefix)
    stats = Collector(zsession, keys.stats("dslam"))
    maps = Collector(zsession, keys.dslam_map)
    poses = Collector(zsession, f"{prefix}/dslam/pose/*")
    assoc_stats = Collector(zsession, keys.stats("assoc"))
    processes.start("assoc", "assoc", "--stats-period-s", "0.3")
    wait_until(lambda: assoc_stats.count() > 0, 60, what="the association service")
    start_dslam(processes)
    wait_until(lambda: stats.count() > 0, 60, what="the dslam service")
    for rid in ROBOTS:
        processes.start(rid, *robot_args(rid))
    data = simulate("arena", robots=3, seed=0, duration=DURATION, rate=10.0)
    expected = sum(len(log.scan_stamp) for log in data.robots.values())
    last = wait_all_scans(stats, expected, processes)
    assert last.extra.get("assoc_remote", 0) > 0, last.extra
    assert last.extra.get("assoc_in_process", 0) == 0, last.extra
    assert not {k: v for k, v in last.rejected.items() if k != "unknown_robot"}, last.rejected

    wait_until(lambda: maps.count() > 0 and (m := assemble(maps.decoded(MapEstimate))) is not None
               and m.landmarks.shape[0] >= 10, 10, what="a map")
    final = assemble(maps.decoded(MapEstimate))
    dist = np.linalg.norm(final.landmarks[:, None] - data.landmarks[None], axis=-1)
    rows, cols = linear_sum_assignment(dist)
    assert np.sqrt(np.mean(dist[rows, cols] ** 2)) < 0.3
    assert final.info_nnz > 0 and final.covariances.shape[0] == final.covariance_ids.shape[0]

    for rid in ROBOTS:
        estimates = poses.decoded(PoseEstimate, lambda k, r=rid: k.endswith(f"/{r}"))
        assert len(estimates) > 50
        assert [e.seq for e in estimates] == list(range(len(estimates)))
        end = estimates[-1]
        truth = data.robots[rid].truth_at(np.array([end.stamp]))[0]
        assert np.hypot(*(end.pose[:2] - truth[:2])) < 0.5


def test_unreachable_association_service_falls_back_and_bad_input_is_counted(router, processes, zsession, prefix):
    keys = Keys(prefix)
    stats = Collector(zsession, keys.stats("dslam"))
    start_dslam(processes, "--assoc-retry-s", "0.5")
    wait_until(lambda: stats.count() > 0, 60, what="the dslam service")
    zsession.put(keys.scan("r1"), b"\x00garbage")
    processes.start("r1", *robot_args("r1"))
    data = simulate("arena", robots=1, seed=0, duration=DURATION, rate=10.0)
    last = wait_all_scans(stats, len(data.robots["r1"].scan_stamp), processes)
    assert last.extra.get("assoc_unreachable", 0) >= 1, last.extra
    assert last.extra.get("assoc_in_process", 0) > 10, last.extra
    assert last.extra.get("landmarks", 0) >= 8, last.extra
    assert last.rejected.get("malformed", 0) >= 1, last.rejected


def test_a_robot_that_leaves_and_runs_again_rejoins_from_its_start(router, processes, zsession, prefix):
    """The same robot id twice in a row: the second run's seq 0 after the token went away is a new run, not
    duplicates; its pose starts again from its RobotInfo and every scan of both runs is used."""
    keys = Keys(prefix)
    stats = Collector(zsession, keys.stats("dslam"))
    poses = Collector(zsession, keys.dslam_pose("r1"))
    start_dslam(processes, "--association", "known")
    wait_until(lambda: stats.count() > 0, 60, what="the dslam service")
    run = ("robot", "--id", "r1", "--world", "arena", "--seed", "0", "--rate", "10", "--duration", "4",
           "--speedup", "4", "--start-delay", "0.5")
    scans = len(simulate("arena", robots=1, seed=0, duration=4.0, rate=10.0).robots["r1"].scan_stamp)
    for turn in (1, 2):
        assert processes.start(f"r1-run{turn}", *run).wait(timeout=60) == 0
        wait_all_scans(stats, turn * scans, processes)
    last = latest(stats, ServiceStats)
    assert last.extra.get("robot_restarts") == 1.0, last.extra
    assert last.extra.get("scans") == 2 * scans and not last.rejected, (last.extra, last.rejected)
    truth = simulate("arena", robots=1, seed=0, duration=4.0, rate=10.0).robots["r1"]
    wait_until(lambda: len(poses.decoded(PoseEstimate)) >= 2 * scans - 2, 10, what="every pose estimate")
    end = poses.decoded(PoseEstimate)[-1]
    assert np.hypot(*(end.pose[:2] - truth.truth_at(np.array([end.stamp]))[0, :2])) < 0.3
