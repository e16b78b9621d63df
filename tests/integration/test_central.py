"""The central FastSLAM service over a real router: three simulated robots, every message consumed, a good map."""

from __future__ import annotations

import numpy as np
import pytest
import zenoh

from robots.simulator import simulate
from schemas.codec import decode, encode
from schemas.keys import Keys
from schemas.messages import Estimate, MclPose, ServiceStats
from tests.helpers import Asked, Collector, wait_until

pytestmark = pytest.mark.integration

ROBOTS = ("r1", "r2", "r3")
DURATION = 10.0


def robot_args(rid: str, *extra: str) -> tuple[str, ...]:
    return ("robot", "--id", rid, "--world", "arena", "--seed", "0", "--rate", "10", "--duration", str(DURATION),
            "--speedup", "8", "--start-delay", "0.5", *extra)


def map_rmse(means: np.ndarray, truth: np.ndarray, cutoff: float = 1.0) -> tuple[float, int]:
    from scipy.optimize import linear_sum_assignment

    distance = np.linalg.norm(means[:, None] - truth[None], axis=-1)
    rows, cols = linear_sum_assignment(distance)
    matched = distance[rows, cols][distance[rows, cols] < cutoff]
    return float(np.sqrt(np.mean(matched**2))), int(matched.size)


def latest_stats(collector: Collector) -> ServiceStats | None:
    stats = collector.decoded(ServiceStats)
    return stats[-1] if stats else None


def test_three_robots_one_map(router, processes, zsession, prefix):
    keys = Keys(prefix)
    estimates = Collector(zsession, keys.central_estimate)
    stats = Collector(zsession, keys.stats("central"))
    processes.start("central", "central", "--association", "nn", "--particles", "50", "--estimate-rate-hz", "4",
                    "--max-state-queries", "16")
    wait_until(lambda: stats.count() > 0, 60, what="the central service's first stats")
    robots = [processes.start(rid, *robot_args(rid)) for rid in ROBOTS]
    for process in robots:
        assert process.wait(timeout=60) == 0
    data = {rid: simulate("arena", seed=0, duration=DURATION, robot_ids=[rid]).robots[rid] for rid in ROBOTS}
    expected = sum(len(log.odom_stamp) + len(log.scan_stamp) for log in data.values())

    def consumed():
        s = latest_stats(stats)
        return s is not None and s.extra.get("processed", 0) >= expected and s.extra.get("buffered", 1) == 0

    wait_until(consumed, 30, what=f"the central service to process all {expected} messages")
    final = latest_stats(stats)
    assert final.extra["processed"] == expected
    assert final.extra["missing"] == 0
    assert not final.rejected, final.rejected
    assert final.messages_in["odom"] + final.messages_in["scan"] == expected

    reply = next(iter(zsession.get(keys.central_state, timeout=10.0)))
    state = decode(reply.ok.payload.to_bytes(), Estimate)
    assert {r.robot_id for r in state.robots} == set(ROBOTS)
    truth = simulate("arena", seed=0, duration=1.0).landmarks
    rmse, matched = map_rmse(state.landmarks, truth)
    assert matched >= 8 and rmse < 0.15, (rmse, matched, len(state.landmarks))
    for robot in state.robots:
        error = robot.pose[:2] - data[robot.robot_id].truth_pose[-1, :2]
        assert np.hypot(*error) < 0.3, (robot.robot_id, error)
    # a flood of state queries: each answered once, with the estimate or busy, and one estimate built per turn
    flood = [Asked(zsession, keys.central_state, None) for _ in range(200)]
    outcomes = [asked.one() for asked in flood]
    answered = [decode(payload, Estimate) for ok, payload, _ in outcomes if ok]
    busy = [payload for ok, payload, _ in outcomes if not ok]
    assert answered and all(payload.startswith(b"busy: ") for payload in busy)
    assert all(len(estimate.landmarks) == len(state.landmarks) for estimate in answered)
    flooded = wait_until(lambda: next((s for s in reversed(stats.decoded(ServiceStats))
                                       if s.extra.get("state_answered") == len(answered) + 1), None), 15,
                         what="stats counting the state queries")
    assert flooded.rejected == ({"busy": len(busy)} if busy else {})

    published = estimates.decoded(Estimate)
    assert len(published) >= 3
    seqs = [e.seq for e in published]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
    assert all(e.method == "fastslam-nn" and e.particles == 50 for e in published)


def test_robot_with_unknown_start_waits_for_mcl(router, processes, zsession, prefix):
    """A robot announcing no start pose is kept out until an MclPose says it is localized; then it joins."""
    keys = Keys(prefix)
    stats = Collector(zsession, keys.stats("central"))
    processes.start("central", "central", "--association", "known", "--particles", "30", "--estimate-rate-hz", "4")
    wait_until(lambda: stats.count() > 0, 60, what="the central service's first stats")
    processes.start("r1", *robot_args("r1"))
    lost = processes.start("r2", *robot_args("r2", "--unknown-start"))

    def waiting():
        s = latest_stats(stats)
        return s is not None and s.extra.get("robots_waiting", 0) == 1 and s.extra.get("waiting", 0) > 20

    wait_until(waiting, 30, what="r2's messages to wait for a pose")
    truth = simulate("arena", seed=0, duration=DURATION, robot_ids=["r2"]).robots["r2"]
    stamp = 1.0
    pose = truth.truth_at(np.array([stamp]))[0]
    publisher = zsession.declare_publisher(keys.mcl_pose("r2"), congestion_control=zenoh.CongestionControl.BLOCK)
    for localized in (False, True):
        publisher.put(encode(MclPose(robot_id="r2", seq=int(localized), stamp=stamp, best_pose=pose,
                                     best_cov=np.diag([1e-4, 1e-4, 1e-5]), localized=localized)))
    wait_until(lambda: (s := latest_stats(stats)) is not None and s.extra.get("robots", 0) == 2, 20,
               what="r2 to be placed")
    assert lost.wait(timeout=60) == 0

    def settled_state() -> Estimate | None:
        reply = next(iter(zsession.get(keys.central_state, timeout=10.0)))
        state = decode(reply.ok.payload.to_bytes(), Estimate)
        settled = {r.robot_id for r in state.robots} == {"r1", "r2"} and latest_stats(stats).extra.get("buffered", 1) == 0
        return state if settled else None

    state = wait_until(settled_state, 30, interval=0.2, what="both robots in the state and the buffer drained")
    r2 = next(r for r in state.robots if r.robot_id == "r2")
    assert np.hypot(*(r2.pose[:2] - truth.truth_pose[-1, :2])) < 0.3
    final = latest_stats(stats)
    assert final.rejected.get("before_placement", 0) > 0
    publisher.undeclare()


def test_a_robot_mcl_placed_wrongly_is_placed_again_when_mcl_relocalizes(router, processes, zsession, prefix):
    """MCL's first localized pose puts r2 5 m off; ``replace_after`` localized poses far from the filter's later,
    central takes r2 out (counted ``replaced``) and places it again at the next localized pose."""
    keys = Keys(prefix)
    stats = Collector(zsession, keys.stats("central"))
    processes.start("central", "central", "--association", "known", "--particles", "30", "--estimate-rate-hz", "4",
                    "--replace-after", "5")
    wait_until(lambda: stats.count() > 0, 60, what="the central service's first stats")
    processes.start("r1", *robot_args("r1"))
    lost = processes.start("r2", *robot_args("r2", "--unknown-start"))
    wait_until(lambda: (s := latest_stats(stats)) is not None and s.extra.get("robots_waiting", 0) == 1, 30,
               what="r2 to wait for a pose")
    truth = simulate("arena", seed=0, duration=DURATION, robot_ids=["r2"]).robots["r2"]
    publisher = zsession.declare_publisher(keys.mcl_pose("r2"), congestion_control=zenoh.CongestionControl.BLOCK)
    seq = iter(range(100))

    def mcl_says(stamp: float, offset: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
        pose = truth.truth_at(np.array([stamp]))[0] + np.array([*offset, 0.0])
        publisher.put(encode(MclPose(robot_id="r2", seq=next(seq), stamp=stamp, best_pose=pose,
                                     best_cov=np.diag([1e-4, 1e-4, 1e-5]), localized=True)))
        return pose

    mcl_says(1.0, (5.0, 0.0))  # a wrong hypothesis of the symmetric arena
    wait_until(lambda: (s := latest_stats(stats)) is not None and s.extra.get("robots", 0) == 2, 20,
               what="r2 to be placed, wrongly")
    assert lost.wait(timeout=60) == 0
    wait_until(lambda: latest_stats(stats).extra.get("buffered", 1) == 0, 30, what="central to drain its buffer")
    for k in range(4):
        mcl_says(8.0 + 0.1 * k)
    assert latest_stats(stats).extra.get("replaced", 0) == 0
    mcl_says(8.4)
    wait_until(lambda: latest_stats(stats).extra.get("replaced", 0) == 1 and latest_stats(stats).extra.get(
        "robots_waiting", 0) == 1, 20, what="central to take r2 out after 5 far localized poses")
    right = mcl_says(8.5)
    wait_until(lambda: latest_stats(stats).extra.get("robots", 0) == 2, 20, what="r2 to be placed again")
    reply = next(iter(zsession.get(keys.central_state, timeout=10.0)))
    r2 = next(r for r in decode(reply.ok.payload.to_bytes(), Estimate).robots if r.robot_id == "r2")
    assert np.hypot(*(r2.pose[:2] - right[:2])) < 0.3
    assert latest_stats(stats).extra["replaced"] == 1
    publisher.undeclare()


def test_a_robot_that_leaves_and_runs_again_rejoins_from_its_start(router, processes, zsession, prefix):
    """The same robot id twice in a row: the second run's seq 0 after the token went away is a new run, not
    duplicates; the robot rejoins at its start pose and every message of both runs is used."""
    keys = Keys(prefix)
    estimates = Collector(zsession, keys.central_estimate)
    stats = Collector(zsession, keys.stats("central"))
    processes.start("central", "central", "--association", "known", "--particles", "30", "--estimate-rate-hz", "4")
    wait_until(lambda: stats.count() > 0, 60, what="the central service's first stats")
    log = simulate("arena", seed=0, duration=4.0, robot_ids=["r1"]).robots["r1"]
    per_run = len(log.odom_stamp) + len(log.scan_stamp)
    for turn in (1, 2):
        run = processes.start(f"r1-run{turn}", "robot", "--id", "r1", "--world", "arena", "--seed", "0", "--rate", "10",
                              "--duration", "4", "--speedup", "4", "--start-delay", "0.5")
        assert run.wait(timeout=60) == 0
        wait_until(lambda n=turn: (s := latest_stats(stats)) is not None and s.extra.get("processed", 0) >= n * per_run
                   and s.extra.get("buffered", 1) == 0, 30, what=f"run {turn} processed")
    final = latest_stats(stats)
    assert final.extra["processed"] == 2 * per_run and final.extra.get("robot_restarts") == 1.0, final.extra
    assert not final.rejected, final.rejected
    wait_until(lambda: any(r.stamp >= log.scan_stamp[-1] for e in estimates.decoded(Estimate)[-1:] for r in e.robots),
               10, what="an estimate at the end of the second run")
    r1 = estimates.decoded(Estimate)[-1].robots[0]
    assert np.hypot(*(r1.pose[:2] - log.truth_at(np.array([r1.stamp]))[0, :2])) < 0.3
