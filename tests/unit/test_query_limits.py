"""Bounded queries, the pure parts: time budgets in the solvers (on injected clocks), request sizes, the checks of a
localization query, and the query pool's admission, deadline and answers (with stand-ins for Zenoh's queries)."""

from __future__ import annotations

import math
import os
import threading
from collections import Counter

import numpy as np
import pytest

from benchmarks.support.association_problems import dense_request
from robots.models import RangeBearingSensor
from robots.worlds import make_world
from schemas.association import AssociationRequest
from schemas.codec import encode
from schemas.messages import RobotInfo, SensorSpec
from services.association import solvers
from services.association.core import AssociationError, associate, build_problem, query_cells
from services.mcl.config import MclConfig
from services.mcl.core import MonteCarloLocalizer
from services.mcl.fleet import MclFleet
from services.mcl.service import localize_refusal
from services.query_pool import QueryPool, QueryRefused, Sized, caller_timeout, decode_query, is_wildcard

R = np.diag([0.05**2, math.radians(1.0) ** 2])


class StepClock:
    """A clock that moves ``step`` seconds each time it is read: the budget runs out after a known number of checks."""

    def __init__(self, step: float = 1.0):
        self.now = 0.0
        self.step = step

    def __call__(self) -> float:
        self.now += self.step
        return self.now


def jcbb_args(request: AssociationRequest) -> tuple:
    problem = build_problem(request)
    return (problem.innovations, problem.gated, problem.nis, problem.joint_blocks, problem.noise,
            request.gate_probability)


# --- the association solvers' time budget --------------------------------------------------------


@pytest.mark.parametrize("seed", range(3))
def test_jcbb_kernel_in_slices_searches_like_one_call(seed):
    """A search paused every few multiply-adds and resumed gives the same pairings, joint NIS and node count."""
    rng = np.random.default_rng(700 + seed)
    n = int(rng.integers(6, 14))
    landmarks = rng.uniform([1.0, -1.5], [5.0, 1.5], size=(n, 2))
    z = RangeBearingSensor().observe(np.array([0.05, -0.03, 0.02]), landmarks) + rng.normal(0.0, [0.05, 0.02], (n, 2))
    request = AssociationRequest(measurements=z, noise=R * 4, landmarks=landmarks,
                                 landmark_covs=np.tile(np.eye(2) * 0.01, (n, 1, 1)), pose=np.zeros(3),
                                 pose_cov=np.diag([0.05, 0.05, 0.01]))
    args = jcbb_args(request)
    whole = solvers.solve_jcbb(*args)
    never_spent = solvers.Budget(1.0, clock=lambda: 0.0)
    sliced = solvers.solve_jcbb(*args, budget=never_spent, slice_work=50)
    np.testing.assert_array_equal(sliced.rows, whole.rows)
    np.testing.assert_array_equal(sliced.cols, whole.cols)
    assert (sliced.nodes, sliced.truncated, sliced.joint_nis) == (whole.nodes, whole.truncated, whole.joint_nis)
    assert not never_spent.cut


@pytest.mark.parametrize("compiled", [True, False], ids=["kernel", "reference"])
def test_jcbb_stops_at_its_time_budget_with_the_best_so_far(compiled):
    request = dense_request(40, 40)
    args = jcbb_args(request)
    budget = solvers.Budget(300.0, StepClock())  # spent at the 300th look at the clock: a node, or a slice of work
    result = solvers.solve_jcbb(*args, max_nodes=10**9, compiled=compiled, budget=budget, slice_work=2000)
    assert budget.cut and result.truncated
    assert result.rows.size > 0 and result.joint_nis <= solvers.gate_value(request.gate_probability, 2 * result.rows.size)
    assert len(set(result.cols.tolist())) == result.cols.size


def test_jcbb_with_no_time_at_all_is_a_deadline():
    with pytest.raises(AssociationError) as info:
        associate(dense_request(20, 20), "jcbb", time_budget_s=0.0, clock=StepClock())
    assert info.value.reason == "deadline"


def test_a_budget_that_holds_changes_nothing():
    request = dense_request(15, 15, seed=2)
    for method in ("nn", "greedy", "ihgr", "exact", "jcbb", "auto"):
        plain, budgeted = associate(request, method), associate(request, method, time_budget_s=60.0)
        np.testing.assert_array_equal(plain.assignment, budgeted.assignment)
        assert budgeted.truncated == plain.truncated


def test_greedy_stops_at_its_time_budget_with_a_partial_matching():
    request = dense_request(120, 120)
    problem = build_problem(request)
    budget = solvers.Budget(1.5, StepClock())
    rows, cols = solvers.solve_greedy(problem.nis, problem.cost, budget)
    full_rows, _ = solvers.solve_greedy(problem.nis, problem.cost)
    assert budget.cut and 0 < rows.size < full_rows.size
    assert len(set(rows.tolist())) == rows.size and len(set(cols.tolist())) == cols.size


def test_ihgr_gives_the_lp_its_time_left_and_stops_rounding_when_spent():
    cost = np.array([[-2.0, -2.0, np.inf], [-2.0, -2.0, -1.0], [np.inf, -1.0, -3.0]])
    limits = []

    def half(weights, rows, cols, n_rows, n_cols, time_limit=None):  # a fractional optimum: rounding needs more LPs
        limits.append(time_limit)
        return np.full(weights.size, 0.5), float(weights.sum() * 0.5)

    budget = solvers.Budget(2.5, StepClock())
    result = solvers.solve_ihgr(cost, lp=half, budget=budget, max_tie_pairs=0)
    assert limits[0] == pytest.approx(1.5)  # 2.5 s less the one second the clock moved while asking
    assert result.truncated and budget.cut
    assert result.rows.size < 3


def test_an_lp_out_of_time_is_a_deadline():
    """HiGHS told to stop after a millisecond on a dense LP of 90,000 pairs: no partial answer, an error."""
    with pytest.raises(AssociationError) as info:
        associate(dense_request(300, 300), "ihgr", time_budget_s=0.001)
    assert info.value.reason == "deadline"


def test_query_cells_counts_the_largest_array_of_each_method():
    request = dense_request(30, 50)
    assert query_cells(request, "nn") == query_cells(request, "greedy") == query_cells(request, "ihgr") == 30 * 50
    assert query_cells(request, "exact") == 80**2
    assert query_cells(request, "jcbb") == 30 * 50 + 4 * 50**2 + 4 * 30**2
    assert query_cells(request, "auto") == max(80**2, 30 * 50 + 4 * 50**2 + 4 * 30**2)
    joint = request.model_copy(update={"joint_cov": np.eye(3 + 100), "pose_cov": None})
    assert query_cells(joint, "nn") == 103**2


# --- the localization query's checks and budget --------------------------------------------------


def office_sensor(**changes) -> SensorSpec:
    return make_world("office", 0).sensor.model_copy(update=changes)


@pytest.mark.parametrize("noise", [np.zeros((2, 2)), np.array([[1.0, 1.0], [1.0, 1.0]]), np.diag([0.01, 0.0])])
def test_a_singular_sensor_noise_is_invalid(noise):
    landmarks = make_world("office", 0).landmarks
    reason, detail = localize_refusal(10, 1000, office_sensor(noise_cov=noise), landmarks, MclConfig(), 20_000,
                                      5_000_000, 250_000)
    assert reason == "invalid" and "positive definite" in detail


def test_localization_work_is_sized_before_it_starts():
    landmarks = make_world("office", 0).landmarks
    sensor = office_sensor()

    def refusal(observations=10, particles=1000, spec=sensor, pool=landmarks):
        return localize_refusal(observations, particles, spec, pool, MclConfig(), 20_000, 5_000_000, 250_000)

    assert refusal() is None
    assert refusal(particles=50_000)[0] == "too_large" and "20000" in refusal(particles=50_000)[1]
    assert refusal(observations=3000, particles=2000)[0] == "too_large"
    assert "5000000" in refusal(observations=3000, particles=2000)[1]
    assert refusal(spec=office_sensor(max_range=500.0))[0] == "too_large"  # a lookup grid far beyond the map
    wide_noise = np.diag([0.01, 4.0])  # a gate of 70 m in a 0.25 m grid
    assert refusal(spec=office_sensor(noise_cov=wide_noise))[0] == "too_large"
    many = np.random.default_rng(0).uniform(0.0, 20.0, (3000, 2))  # every landmark pairs with every other
    assert "pairs" in refusal(spec=office_sensor(max_range=40.0), pool=many)[1]


def test_localize_once_in_slices_weighs_like_the_filter_and_stops_at_its_budget():
    world = make_world("office", 0)
    fleet = MclFleet(MclConfig(), world.landmarks)
    rng = np.random.default_rng(4)
    z = np.stack([rng.uniform(0.5, 6.0, 12), rng.uniform(-1.0, 1.0, 12)], -1)
    sliced = fleet.localize_once(z, world.sensor, 500, seed=3, slice_cells=1000)
    info = RobotInfo(robot_id="query", stamp=0.0, motion_model="unicycle", sensor=world.sensor, odom_rate_hz=1.0,
                     scan_rate_hz=1.0)
    whole = MonteCarloLocalizer(world.landmarks, info, MclConfig(), np.random.default_rng(3))
    whole.initialize_global(z, 500)
    whole.weigh(z)
    np.testing.assert_array_equal(sliced.particles, whole.particles)
    np.testing.assert_allclose(sliced.weights, whole.weights)
    with pytest.raises(TimeoutError, match="budget ran out"):
        fleet.localize_once(z, world.sensor, 500, seed=3, time_budget_s=2.5, clock=StepClock(), slice_cells=1000)


# --- the query pool ---------------------------------------------------------------------------------


class Shell:
    """What the pool needs of a service: its name, counters and extra, no loop (counted at once)."""

    name = "test"

    def __init__(self):
        self.messages_in: Counter = Counter()
        self.rejected: Counter = Counter()
        self.extra: dict[str, float] = {}

    def reject(self, reason: str, detail: str = "", count: int = 1) -> None:
        self.rejected[reason] += count

    def call_in_loop(self, work, *args) -> None:
        work(*args)

    def put_timing(self, name: str, values) -> None:
        if values:
            self.extra[f"{name}_median"] = float(np.median(values))


class Query:
    """A stand-in for zenoh.Query: records its one answer."""

    def __init__(self, payload: bytes | None = None, parameters: dict | None = None):
        self.parameters = parameters or {}
        self.answers: list[tuple[str, object]] = []
        self.dropped = threading.Event()
        self.payload = None if payload is None else type("Payload", (), {"to_bytes": lambda _self: payload})()

    def reply(self, key, payload) -> None:
        self.answers.append(("ok", payload))

    def reply_err(self, payload) -> None:
        self.answers.append(("err", bytes(payload).decode()))

    def drop(self) -> None:
        self.dropped.set()


def wait_answered(query: Query) -> tuple[str, object]:
    assert query.dropped.wait(10), "the query was never answered"
    assert len(query.answers) == 1, query.answers
    return query.answers[0]


def test_a_full_pool_answers_busy_at_once_and_the_admitted_are_solved():
    shell, release = Shell(), threading.Event()
    pool = QueryPool(shell, workers=1, queue=1, deadline_s=60.0)

    def slow(_budget):
        assert release.wait(10)
        return "k", b"done"

    queries = [Query() for _ in range(4)]
    for query in queries:
        pool.admit(query, "q", lambda: slow)
    for query in queries[2:]:  # answered inside admit, before anything was solved
        assert query.dropped.is_set() and query.answers[0][0] == "err" and query.answers[0][1].startswith("busy:")
    release.set()
    assert [wait_answered(q) for q in queries[:2]] == [("ok", b"done")] * 2
    pool.close()
    assert shell.rejected == Counter(busy=2) and shell.messages_in["q"] == 4 and pool.replies == 2


class LoopShell(Shell):
    """A shell whose loop runs the work handed to it only when the test says (as a busy service's loop would)."""

    def __init__(self):
        super().__init__()
        self.handed: list = []

    def call_in_loop(self, work, *args) -> None:
        self.handed.append((work, args))

    def run_loop(self) -> None:
        handed, self.handed = self.handed, []
        for work, args in handed:
            work(*args)


def test_a_burst_of_refused_queries_is_counted_in_one_call_into_the_loop():
    """500 queries at a full pool: each answered busy at once, and the service's loop (where the robots' streams are
    handled) gets one call for all their counts, not two per query; counts that come after it get the next call."""
    shell, release = LoopShell(), threading.Event()
    pool = QueryPool(shell, workers=1, queue=0, deadline_s=60.0)
    pool.admit(Query(), "q", lambda: (lambda _budget: (release.wait(10), ("k", b"done"))[1]))
    burst = [Query() for _ in range(500)]
    for query in burst:
        pool.admit(query, "q", lambda: pytest.fail("a busy query is never prepared"))
    assert all(query.answers[0][1].startswith("busy:") for query in burst)
    assert len(shell.handed) == 1
    shell.run_loop()
    assert shell.rejected == Counter(busy=500) and shell.messages_in["q"] == 501 and pool.replies == 0
    release.set()
    pool.close()
    pool._executor.shutdown(wait=True)
    shell.run_loop()  # the solved query's reply, counted after the burst was taken, and its timing
    assert pool.replies == 1 and shell.rejected == Counter(busy=500)


def test_a_query_that_waited_past_the_deadline_is_dropped_unsolved():
    shell, release, clock = Shell(), threading.Event(), StepClock(0.0)
    pool = QueryPool(shell, workers=1, queue=4, deadline_s=5.0, clock=clock)
    solved = []

    def first(budget):
        assert release.wait(10)
        return "k", b"first"

    def second(budget):
        solved.append(budget)
        return "k", b"second"

    blocker, late = Query(), Query()
    pool.admit(blocker, "q", lambda: first)
    pool.admit(late, "q", lambda: second)
    clock.now += 6.0  # the caller of the second gave up meanwhile
    release.set()
    assert wait_answered(blocker) == ("ok", b"first")
    kind, text = wait_answered(late)
    pool.close()
    assert kind == "err" and text.startswith("expired:") and not solved
    assert shell.rejected == Counter(expired=1)


def test_a_query_whose_caller_gave_up_is_dropped_and_a_solve_gets_the_callers_time():
    shell, release, clock = Shell(), threading.Event(), StepClock(0.0)
    pool = QueryPool(shell, workers=1, queue=4, deadline_s=60.0, clock=clock)
    budgets = []

    def first(budget):
        assert release.wait(10)
        return "k", b"first"

    def noted(budget):
        budgets.append(budget)
        return "k", b"solved"

    blocker, abandoned, patient, hurried = Query(), Query(None, {"timeout_s": "1"}), Query(), Query(None, {"timeout_s": "9"})
    pool.admit(blocker, "q", lambda: first)
    pool.admit(abandoned, "q", lambda: noted)
    pool.admit(patient, "q", lambda: noted)
    clock.now += 2.0
    pool.admit(hurried, "q", lambda: noted)
    release.set()
    results = [wait_answered(q) for q in (blocker, abandoned, patient, hurried)]
    pool.close()
    assert results[0] == ("ok", b"first") and results[1][1].startswith("expired:")
    assert results[2:] == [("ok", b"solved")] * 2 and budgets == [58.0, 9.0]
    assert caller_timeout(Query()) is None and caller_timeout(Query(None, {"timeout_s": "0.25"})) == 0.25
    assert all(caller_timeout(Query(None, {"timeout_s": bad})) is None for bad in ("-1", "0", "nan", "inf", "soon"))


def test_refusals_and_solver_errors_are_answered_and_counted():
    shell = Shell()
    pool = QueryPool(shell, workers=1, queue=0, deadline_s=5.0)

    def too_large():
        raise QueryRefused("too_large", "9 cells exceed 8")

    def broken(_budget):
        raise np.linalg.LinAlgError("Singular matrix")

    refused, failed = Query(), Query()
    pool.admit(refused, "q", too_large)
    assert refused.answers == [("err", "too_large: 9 cells exceed 8")]  # at once, and the slot is free again
    pool.admit(failed, "q", lambda: broken)
    kind, text = wait_answered(failed)
    pool.close()
    assert kind == "err" and text == "solve_error: LinAlgError: Singular matrix"
    assert shell.rejected == Counter(too_large=1, solve_error=1)
    pool.put_stats()
    assert shell.extra["query_pending"] == 0.0 and "query_solve_ms_median" in shell.extra


@pytest.mark.skipif(not hasattr(os, "setpriority"), reason="thread priorities are a Linux feature")
def test_workers_run_nicer_than_the_service():
    pool = QueryPool(Shell(), workers=1, queue=0, deadline_s=5.0, nice=7)
    query = Query()
    pool.admit(query, "q", lambda: lambda _budget: ("k", str(os.getpriority(os.PRIO_PROCESS, 0)).encode()))
    kind, niceness = wait_answered(query)
    pool.close()
    assert int(niceness) == os.getpriority(os.PRIO_PROCESS, 0) + 7 or int(niceness) == 19


def test_decode_query_refuses_empty_and_malformed_payloads():
    with pytest.raises(QueryRefused, match="empty"):
        decode_query(Query(), AssociationRequest)
    with pytest.raises(QueryRefused) as info:
        decode_query(Query(b"\x00garbage"), AssociationRequest)
    assert info.value.reason == "malformed"
    request = dense_request(2, 2)
    assert decode_query(Query(encode(request)), AssociationRequest).size == (2, 2)


def test_wildcards_are_told_from_concrete_keys():
    assert is_wildcard("fleet/assoc/**") and is_wildcard("fleet/*/localize") and is_wildcard("fleet/assoc/$*o")
    assert not is_wildcard("fleet/assoc/auto") and not is_wildcard("fleet/mcl/localize")


def test_light_queries_have_a_lane_of_their_own_that_heavy_ones_cannot_fill():
    shell, release = Shell(), threading.Event()
    pool = QueryPool(shell, workers=1, queue=0, deadline_s=60.0, light_cost=100.0, light_queue=0)

    def heavy(_budget):
        assert release.wait(10)
        return "k", b"heavy"

    blocker, second_heavy, light, second_light = Query(), Query(), Query(), Query()
    pool.admit(blocker, "q", lambda: Sized(heavy, cost=1e6))
    pool.admit(second_heavy, "q", lambda: Sized(heavy, cost=1e6))  # the heavy lane is full
    assert second_heavy.answers[0][1].startswith("busy:") and "query lane" in second_heavy.answers[0][1]
    gate = threading.Event()

    def light_solve(_budget):
        assert gate.wait(10)
        return "k", b"light"

    pool.admit(light, "q", lambda: Sized(light_solve, cost=50.0))
    pool.admit(second_light, "q", lambda: Sized(light_solve, cost=50.0))  # its one worker is taken
    assert "light lane" in second_light.answers[0][1] and "query lane" in second_light.answers[0][1]
    gate.set()
    assert wait_answered(light) == ("ok", b"light")  # while the heavy query still runs
    assert not blocker.dropped.is_set()
    release.set()
    assert wait_answered(blocker) == ("ok", b"heavy")
    pool.put_stats()
    pool.close()
    assert pool.total_replies == 2 and shell.rejected == Counter(busy=2)
    assert shell.extra["light_replies"] == 1.0 and shell.extra["query_replies"] == 1.0
