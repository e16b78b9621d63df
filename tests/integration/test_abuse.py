"""The standing abuse suite (issue 16): schema-valid lies and unbounded cost against every stream service, live.

Two fleets, each played once for the module by :class:`benchmarks.support.abuse.Fleet`: one router and two copies
of the fleet under two key prefixes, ``ref`` untouched and ``hit`` attacked, with the same simulated robots and
seeds and the same services (central FastSLAM, D-SLAM, MCL tracking every robot):

- **lies** (robots r1, r2, r3): an attacker's own session sends 10 RobotInfo for r3 before r3 starts and 10 for
  r1 after it joined (start pose 70 m off), odometry and scans with seq 2^62 and then stamped 1e12 on r1's keys,
  r2's next odometry claiming dt = 10 s at 2 m/s, then a plausible odometry stream continuing r2's seqs and
  running ahead of it for 2 s, and last a second robot process with r3's id and seed (a twin: its own session,
  seq 0 again) for 2 robot seconds.
- **floods** (robots r1 and r2, plus the association service; D-SLAM associates through it): r2 itself tells the
  same lies from its own session (a buggy robot: seq 2^62, stamp 1e12, dt = 10 s, 5 m/s), then the attacker sends
  20 scans of 10^6 detections with a long-past seq on r1's key, 200 robot ids that never announce themselves, 20
  scans of 10^6 detections from such an id, and at once a dense JCBB query (200 × 200) and a LocalizeRequest of
  1,000 detections × 20,000 particles. (The floods are smaller than the issue's 200 scans, to stay fast: 320 MB each,
  still three times the memory bound they test; benchmarks/abuse.py sends the issue's sizes. Messages of robot
  ids that no session holds go after 2 s here, not the default 30 s.)

Asserted, against the issue's Targets: every service of the attacked copy still runs, exits cleanly, logged no
traceback and counted no ``handler_error``; no counter in its stats is absurd (``missing`` < 1e6), no estimate
is stamped past the robots' clock and every output decodes; every forged message is counted by each stream
service under one of the reasons that fit it (a forgery from another session may be ``not_owner`` or
``no_source``, or what its content is; a lie of the robot itself counted from where the service took in the lie
before it to where it published a pose past this one, however far it lags), and no real message is refused
meanwhile (no other reason counted beyond the untouched copy's); for every robot and every service, the median
error against the truth after the last probe aimed at that robot (over the whole run, the attacks on the others
included, for a robot none aims at) is within 10 % of the untouched copy's plus 0.01 m, and the estimate caught
up with the robot's last message (the median after the attack; the copies handle events in the same order, and
differed by at most 2 mm in four runs: see TOLERANCE in benchmarks/support/abuse.py); a flood grows no service's
RSS by 100 MB or more; and neither a flood nor a heavy query silences a service (its stats,
its poses of each robot) for more than 1 s longer than the untouched copy's longest silence in the same
window, while each query is answered.

The figures of each fleet are printed as one ``ABUSE {json}`` line (``-s`` shows them).
"""

from __future__ import annotations

import json
from dataclasses import replace

import pytest

from benchmarks.support.abuse import BLOCK_LIMIT_S, PROBES, RSS_LIMIT_MB, Fleet, Plan, Scene, Step, estimates_off

pytestmark = pytest.mark.integration

SCENE = Scene(big_scans=20, localize_observations=1000, localize_particles=20_000, forged_stream_s=2.0, twin_s=2.0)
SEEDS = {"lies": 0, "floods": 1}  # the two fleets on two seeds: more of the robots' paths covered
UNANNOUNCED = (("FLEETSLAM_UNANNOUNCED_S", "2"),)  # unannounced ids' messages go after 2 s (default 30 s), to be fast
PLANS = {
    # 80 robot seconds (40 s at speed-up 2): on two cores shared with a benchmark the steps took 31 s of wall time
    # (the services slow to count, the twin a process of its own), 62 robot seconds; 40 once left 0.3 s after the attack
    "lies": Plan(robots=("r1", "r2", "r3"), duration=80.0, steps=(
        Step(PROBES["info_before_start"], ("r3",)),
        Step(PROBES["info_joined"], ("r1",), 2.0),
        Step(PROBES["seq_jump"], ("r1",), 4.0),
        Step(PROBES["stamp_jump"], ("r1",), 7.0),
        Step(PROBES["dt_lie"], ("r2",), 10.0),
        Step(PROBES["forged_stream"], ("r2",), 13.0),
        Step(PROBES["twin_robot"], ("r3",)),
    )),
    # the buggy robot's lies 4 robot seconds apart: each is counted in each service's own time (a window closes when
    # the service published a pose past the lie), so a service that lags the robot by more than the spacing (D-SLAM
    # here, 15 robot seconds behind through the association service; more on a loaded machine) still counts each
    # lie in its own window; the attacker's probes wait until every service is past the lies
    "floods": Plan(robots=("r1", "r2"), duration=72.0, assoc=True, service_env=UNANNOUNCED, steps=(
        Step(PROBES["buggy_seq_jump"], ("r2",), 3.0),
        Step(PROBES["buggy_stamp_jump"], ("r2",), 7.0),
        Step(PROBES["buggy_dt_lie"], ("r2",), 11.0),
        Step(PROBES["buggy_control_lie"], ("r2",), 15.0),
        Step(PROBES["stale_big_scans"], ("r1",)),  # the attacker's probes, one right after the other
        Step(PROBES["ghosts"]),
        Step(PROBES["ghost_big_scans"]),
        Step(PROBES["heavy_queries"]),
    )),
}
STEPS = [(fleet, step.probe.name) for fleet, plan in PLANS.items() for step in plan.steps]
COUNTED = [(fleet, name) for fleet, name in STEPS if not PROBES[name].query]
FLOODS = [(fleet, name) for fleet, name in STEPS if PROBES[name].flood]


def play(name: str, tmp_path_factory) -> dict:
    result = Fleet(PLANS[name], replace(SCENE, seed=SEEDS[name]), tmp_path_factory.mktemp(name)).run()
    print(f"ABUSE {json.dumps({'fleet': name, **result}, default=str)}")
    return result


@pytest.fixture(scope="module")
def lies(tmp_path_factory) -> dict:
    return play("lies", tmp_path_factory)


@pytest.fixture(scope="module")
def floods(tmp_path_factory) -> dict:
    return play("floods", tmp_path_factory)


@pytest.fixture
def fleet(request):
    """The figures of the fleet named by the test's ``fleet`` parameter (played once per module)."""
    return request.getfixturevalue(request.param)


@pytest.mark.parametrize("fleet", list(PLANS), indirect=True)
def test_services_stay_up_and_their_figures_stay_possible(fleet):
    final = fleet["final"]
    assert all(final["alive"].values()), final["alive"]
    assert all(code == 0 for code in final["exit_codes"].values()), final["exit_codes"]
    assert not any(final["tracebacks"].values()), final["tracebacks"]
    assert not any(rejected.get("handler_error") for rejected in final["rejected"].values()), final["rejected"]
    assert not any(final["absurd"].values()), final["absurd"]
    assert not any(final["undecodable"].values()), f"service outputs that did not decode: {final['undecodable']}"
    duration = fleet["plan"]["duration"]
    assert final["estimate_stamp_max"]["hit"] is not None and final["estimate_stamp_max"]["hit"] <= duration + 1e-6, \
        final["estimate_stamp_max"]


@pytest.mark.parametrize("fleet,probe", COUNTED, indirect=["fleet"])
def test_each_probe_is_refused_and_counted_and_no_real_message_is(fleet, probe):
    record = fleet["steps"][probe]
    sent = record["sent"]
    assert sent.get("messages", 0) > 0 and "error" not in sent, sent
    short = {name: n for name, n in record["counted"].items() if n < sent["messages"]}
    assert not short, (f"{probe}: sent {sent['messages']}, counted under {record['expected']}: {record['counted']}; "
                       f"rejected in the window: {record['rejected']['hit']}")
    assert not record["unexpected"], (f"{probe}: reasons beyond the probe's own (real messages refused?): "
                                      f"{record['unexpected']}")


@pytest.mark.parametrize("fleet", list(PLANS), indirect=True)
def test_every_robot_after_the_attack_is_as_in_the_untouched_run(fleet):
    errors = fleet["final"]["errors"]
    off = estimates_off(errors)
    assert not off, f"estimates off the untouched run (after stamp {errors['_after_stamp']}): {off}"
    lag = {key: lag for key, lag in fleet["final"]["stamp_lag_s"].items() if key.endswith("/hit") and lag > 1e-6}
    assert not lag, f"estimates that never caught up with the robot (seconds behind): {lag}"
    assert errors["_after_window_s"] >= 5.0, f"the attack ended too late to see the fleet after it: {errors}"


@pytest.mark.parametrize("fleet,probe", FLOODS, indirect=["fleet"])
def test_a_flood_bounds_memory_and_starves_nothing(fleet, probe):
    record = fleet["steps"][probe]
    grown = {name: mb for name, mb in record["rss_growth_mb"].items() if mb >= RSS_LIMIT_MB}
    assert not grown, f"{probe}: RSS growth (MB) {record['rss_growth_mb']}, sent {record['sent']}"
    blocked = {name: {k: v for k, v in gaps.items() if v > BLOCK_LIMIT_S} for name, gaps in record["blocked_s"].items()}
    assert not any(blocked.values()), f"{probe}: silent longer than the untouched copy by (s) {blocked}"


@pytest.mark.parametrize("fleet", ["floods"], indirect=True)
def test_heavy_queries_are_answered_and_block_no_service(fleet):
    record = fleet["steps"]["heavy_queries"]
    queries = record["sent"].get("queries", {})
    assert set(queries) == {"assoc", "localize"}, record["sent"]
    assert all(q["answer_s"] is not None for q in queries.values()), queries
    blocked = {name: {k: v for k, v in gaps.items() if v > BLOCK_LIMIT_S} for name, gaps in record["blocked_s"].items()}
    assert not any(blocked.values()), f"silent longer than the untouched copy by (s) {blocked}; queries {queries}"
