"""kill -9 of the stateful services and of the router, with the defaults: nothing lost, the same result.

Two copies of one fleet run side by side through one router, each under its own key prefix: the same two
simulated robots (same seeds, so the same data) with central FastSLAM, D-SLAM and MCL. Copy A runs untouched.
In copy B each service keeps checkpoints (``--state-dir``) and is killed with SIGKILL once, at a seeded random
moment (``--crash-seed``), and started again at once with the same folder; the router is killed and started
again too, earlier (a service restarting while the router is down is a double fault this does not cover). Every
process runs with the default transport settings (publisher caches and subscriber recovery on).

At the end every service of B holds every robot message (no seq missing, the last scan's pose published) and
its estimates agree with A's, each within the stated tolerance of A's error against the truth: a restarted service
resumes from its checkpoint and recovers the rest from the robots' caches, it does not start afresh. The services
handle the robots' events in stamp order, ties by robot id, wait for every robot that announced itself and for
every stream after a router restart, and draw from the checkpointed random generators, so both copies compute the
same numbers: the tolerance is the issue's 5 % (plus 5 mm for rounding), and ``exact`` in the printed figures says
whether B ended bit for bit where A did. MCL localizes against the true map (``--source truth``): a live map
(D-SLAM's or the central estimate) arrives at wall-clock moments, so MCL on it differs between any two runs.
The figures (kill times, first estimate after each restart, errors) are printed as JSON (``-s`` shows them).
With ``--crash-kills none`` nothing is killed: B against A then measures how far two untouched live runs differ.
"""

from __future__ import annotations

import json
import random
import re
import signal
import time

import numpy as np
import pytest

from robots.simulator import simulate
from schemas.codec import decode
from schemas.keys import Keys
from schemas.messages import Estimate, MapEstimate, MclPose, PoseEstimate, ServiceStats
from tests.helpers import Collector, wait_for_port, wait_until
from tests.integration.test_central import map_rmse

pytestmark = pytest.mark.integration

ROBOTS = ("r1", "r2")
DURATION = 50.0  # robot time (s)
SPEEDUP = 2.0
TOLERANCE = (0.05, 0.005)  # B's error ≤ A's error × (1 + 5 %) + 5 mm
# the robots keep their caches this long after their last message: a service killed near the end of their run and
# restarted on a loaded machine (5.5 s to load its kernels) still finds them, where the default 2 s had them gone
LINGER_S = 10.0
START_DELAY_S = 2.0  # robots wait this long after declaring their token: each sees the other's before any data
# services wait this long for a robot that announced itself to send, and for a silent stream (0.1 s by default: on
# a loaded machine a robot's process now and then stalls longer, and the other's events would go first; with two
# busy loops beside the fleets stalls of 0.5 s reordered one copy's events in 1 of 4 runs. A stall of the service
# itself is not counted as silence)
ORDERING = ("--join-wait-s", "4", "--reorder-window-s", "2")
SERVICES = {
    "central": ("central", "--association", "known", "--particles", "50", "--estimate-rate-hz", "4", *ORDERING),
    "dslam": ("dslam", "--association", "known", *ORDERING),
    "mcl": ("mcl", "--all-robots", "--particles", "500", "--source", "truth", *ORDERING),
}


def robot_args(rid: str) -> tuple[str, ...]:
    return ("robot", "--id", rid, "--world", "arena", "--seed", "0", "--rate", "10", "--duration", str(DURATION),
            "--speedup", str(SPEEDUP), "--start-delay", str(START_DELAY_S), "--linger-s", str(LINGER_S))


def within(error_b: float, error_a: float) -> bool:
    return error_b <= error_a * (1 + TOLERANCE[0]) + TOLERANCE[1]


def test_killed_services_and_router_resume_and_lose_nothing(router, processes, zsession, prefix, tmp_path, crash_seed,
                                                            crash_kills):
    rng = random.Random(crash_seed)
    prefixes = {"A": f"{prefix}a", "B": f"{prefix}b"}
    keys = {copy: Keys(p) for copy, p in prefixes.items()}
    state_dirs = {name: tmp_path / "state" / name for name in SERVICES}
    stats = {(copy, name): Collector(zsession, keys[copy].stats(name)) for copy in prefixes for name in SERVICES}
    arrivals: dict = {("B", name): [] for name in SERVICES} | {"estimate": []}  # wall times of copy B's output

    def arrival_times(key: str, into: list):
        return zsession.declare_subscriber(key, lambda _sample: into.append(time.monotonic()))

    timers = [arrival_times(keys["B"].stats(name), arrivals[("B", name)]) for name in SERVICES]
    timers.append(arrival_times(keys["B"].central_estimate, arrivals["estimate"]))
    dslam_maps = {copy: Collector(zsession, keys[copy].dslam_map) for copy in prefixes}
    dslam_poses = {copy: Collector(zsession, f"{p}/dslam/pose/*") for copy, p in prefixes.items()}
    mcl_poses = {copy: Collector(zsession, f"{p}/mcl/*/pose") for copy, p in prefixes.items()}

    def start(copy: str, name: str, label: str | None = None):
        extra = ("--state-dir", str(state_dirs[name])) if copy == "B" else ()
        return processes.start(label or f"{name}-{copy}", *SERVICES[name], *extra,
                               env={"FLEETSLAM_PREFIX": prefixes[copy]})

    services = {(copy, name): start(copy, name) for copy in prefixes for name in SERVICES}
    for (copy, name), collector in stats.items():
        wait_until(lambda: collector.count() > 0, 90, what=f"the first stats of {name} in copy {copy}")
    robots = {(copy, rid): processes.start(f"{rid}-{copy}", *robot_args(rid), env={"FLEETSLAM_PREFIX": prefixes[copy]})
              for copy in prefixes for rid in ROBOTS}
    # the kills' moments count from the robots' start, not from when their logs were read: on a loaded machine that
    # came 11 s late, central B was killed after its robots had finished and gone, and nothing could refill it
    t0 = time.monotonic() + START_DELAY_S
    wait_until(lambda: all("publishing" in processes.log(f"{rid}-{copy}") for copy, rid in robots), 60,
               what="every robot to start publishing")
    run_wall_s = DURATION / SPEEDUP
    # the router early, the services later, so that no service restarts while the router is down: a service that
    # subscribes then gets no history from the caches (zenoh-ext fetches it once, at declaration)
    plan = sorted([(rng.uniform(0.1, 0.2) * run_wall_s, "router")]
                  + [(rng.uniform(0.35, 0.65) * run_wall_s, name) for name in SERVICES]) if crash_kills else []
    figures: dict = {"seed": crash_seed, "plan_s": [[round(t, 2), name] for t, name in plan], "restarts": {}}
    restarted_at: dict[str, float] = {}
    for at_s, name in plan:  # kills at their seeded moments: a restart is not waited for before the next kill
        time.sleep(max(0.0, t0 + at_s - time.monotonic()))
        if name == "router":
            process = next(p for n, p in processes.started if n == "router")
            process.send_signal(signal.SIGKILL)
            process.wait(timeout=10)
            processes.started.remove(("router", process))
            processes.start("router", "router", "--listen", router.endpoint)
            wait_for_port(router.port)
            continue
        victim = services[("B", name)]
        victim.send_signal(signal.SIGKILL)
        victim.wait(timeout=10)
        restarted_at[name] = time.monotonic()
        services[("B", name)] = start("B", name, f"{name}-B-restarted")
        figures["restarts"][name] = {"killed_at_s": round(at_s, 2)}
    for name, at in restarted_at.items():
        first_stats = wait_until(lambda: next((t for t in arrivals[("B", name)] if t > at), None), 60,
                                 what=f"{name} of copy B back after its kill")
        figures["restarts"][name]["first_stats_after_s"] = round(first_stats - at, 2)
        if name == "central":
            first = wait_until(lambda: next((t for t in arrivals["estimate"] if t > at), None), 60,
                               what="central B's first estimate after its restart")
            figures["restarts"][name]["first_estimate_after_s"] = round(first - at, 2)

    sent = {}
    for (copy, rid), process in robots.items():
        assert process.wait(timeout=120) == 0, processes.log(f"{rid}-{copy}")[-2000:]
        done = re.search(r"done: odom (\d+), scan (\d+)", processes.log(f"{rid}-{copy}"))
        sent[(copy, rid)] = (int(done.group(1)), int(done.group(2)))
    truth = {rid: simulate("arena", seed=0, duration=DURATION, robot_ids=[rid]).robots[rid] for rid in ROBOTS}
    world = simulate("arena", seed=0, duration=1.0).landmarks
    assert all(sent[(copy, rid)] == (truth[rid].odom_stamp.size, truth[rid].scan_stamp.size)
               for copy in prefixes for rid in ROBOTS), sent

    def final_stats(copy: str, name: str) -> ServiceStats:
        return stats[(copy, name)].decoded(ServiceStats)[-1]

    def central_logs(copy: str) -> str:
        return processes.log(f"central-{copy}") + processes.log(f"central-{copy}-restarted")

    expected = sum(sum(sent[("A", rid)]) for rid in ROBOTS)
    for copy in prefixes:
        try:
            wait_until(lambda: final_stats(copy, "central").extra.get("processed", 0) >= expected
                       and final_stats(copy, "central").extra.get("buffered", 1) == 0, 60,
                       what=f"central {copy} to process all {expected} messages")
        except AssertionError as exc:  # say where the messages went: its counters and the end of its log
            raise AssertionError(f"{exc}; its last stats: {final_stats(copy, 'central').extra}; its log ends: "
                                 f"{central_logs(copy)[-3000:]}") from None

    def last_by_robot(collector: Collector, model) -> dict:
        return {message.robot_id: message for message in collector.decoded(model)}

    errors: dict = {}
    for copy in prefixes:
        central = decode(next(iter(zsession.get(keys[copy].central_state, timeout=10.0))).ok.payload.to_bytes(), Estimate)
        last_scan = {rid: truth[rid].scan_stamp[-1] for rid in ROBOTS}

        def at_the_end(model, collector) -> bool:
            poses = last_by_robot(collector, model)
            return all(rid in poses and abs(poses[rid].stamp - last_scan[rid]) < 1e-6 for rid in ROBOTS)

        wait_until(lambda: at_the_end(PoseEstimate, dslam_poses[copy]) and at_the_end(MclPose, mcl_poses[copy])
                   and dslam_maps[copy].count(), 90,
                   what=f"D-SLAM's and MCL's poses of every robot's last scan in copy {copy} (every scan handled)")
        dslam_map = decode(next(iter(zsession.get(keys[copy].dslam_state, timeout=10.0))).ok.payload.to_bytes(),
                           MapEstimate)
        dslam_pose = last_by_robot(dslam_poses[copy], PoseEstimate)
        mcl_pose = last_by_robot(mcl_poses[copy], MclPose)
        final = {rid: truth[rid].truth_pose[-1, :2] for rid in ROBOTS}
        errors[copy] = {
            "central_pose_m": max(float(np.hypot(*(r.pose[:2] - final[r.robot_id]))) for r in central.robots),
            "central_map_m": map_rmse(central.landmarks, world)[0],
            "dslam_pose_m": max(float(np.hypot(*(p.pose[:2] - final[rid]))) for rid, p in dslam_pose.items()),
            "dslam_map_m": map_rmse(dslam_map.landmarks, world)[0],
            "mcl_pose_m": max(float(np.hypot(*(p.best_pose[:2] - final[rid]))) for rid, p in mcl_pose.items()),
        }
        figures[f"errors_{copy}"] = {k: round(v, 4) for k, v in errors[copy].items()}
        assert {r.robot_id for r in central.robots} == set(ROBOTS)
    for name in SERVICES:  # a gap filled after the stats last published goes in the next: wait for one without
        try:
            wait_until(lambda: final_stats("B", name).extra.get("missing", -1) == 0, 15,
                       what=f"stats of {name} B with nothing missing")
        except AssertionError:
            pass  # said below, with the stats
        after = final_stats("B", name)
        figures.setdefault("already_held", {})[name] = after.extra.get("already_held", 0)
        figures.setdefault("checkpoint", {})[name] = {"bytes": after.extra.get("checkpoint_bytes"),
                                                      "write_ms": after.extra.get("checkpoint_write_ms")}
        assert after.extra.get("missing", -1) == 0, (name, after.extra)
        if crash_kills:
            assert "resumed from" in processes.log(f"{name}-B-restarted"), processes.log(f"{name}-B-restarted")[-2000:]
    assert final_stats("A", "central").extra.get("missing", -1) == 0  # the router restart lost nothing either
    scans_sent = sum(sent[("A", rid)][1] for rid in ROBOTS)  # D-SLAM counts each scan it fused, checkpointed with it:
    for copy in prefixes:  # one released but not yet fused when a checkpoint was taken would be lost to a restart
        assert final_stats(copy, "dslam").extra.get("scans") == scans_sent, (copy, final_stats(copy, "dslam").extra)
    for copy in prefixes:  # the filter's own view: controls that came late, or across a gap
        extra = final_stats(copy, "central").extra
        figures[f"central_{copy}_core"] = {k: v for k, v in extra.items()
                                           if k.startswith("rejected_") or k in ("odometry_gaps", "controls_late", "already_held",
                                                                         "hold_ms_p99")}
    figures["kills"] = crash_kills
    figures["exact"] = {measure: errors["B"][measure] == error_a for measure, error_a in errors["A"].items()}
    print("CRASH-RESTART " + json.dumps(figures))
    for measure, error_a in errors["A"].items():
        assert within(errors["B"][measure], error_a), (measure, errors)
