"""Association solvers against brute-force enumeration, and the core's gating, costs and edge cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from robots.models import RangeBearingSensor
from schemas.association import AMBIGUOUS, CLUTTER, NEW, AssociationReply, AssociationRequest
from schemas.codec import decode, encode
from services.association import solvers
from services.association.core import AssociationError, associate, build_problem, split_components

R = np.diag([0.05**2, math.radians(1.0) ** 2])


def brute_force(cost: np.ndarray) -> float:
    """Minimum of Σ c over every matching of the gated pairs (the all-dummy matching costs 0)."""
    m, n = cost.shape

    def best(row: int, used: frozenset) -> float:
        if row == m:
            return 0.0
        value = best(row + 1, used)
        for col in range(n):
            if col not in used and np.isfinite(cost[row, col]):
                value = min(value, cost[row, col] + best(row + 1, used | {col}))
        return value

    return best(0, frozenset())


def random_cost(rng: np.random.Generator, m: int, n: int) -> np.ndarray:
    cost = rng.normal(-1.0, 1.5, size=(m, n))
    cost[rng.random((m, n)) < 0.35] = np.inf
    return cost


def is_matching(rows: np.ndarray, cols: np.ndarray, cost: np.ndarray) -> bool:
    return len(set(rows.tolist())) == rows.size and len(set(cols.tolist())) == cols.size and bool(np.all(np.isfinite(cost[rows, cols])))


def random_request(rng: np.random.Generator, m: int, n: int, spread: float = 1.5, **fields) -> AssociationRequest:
    """Landmarks near the robot, measurements of some of them (noisy, permuted) plus a few far ones."""
    predicted = np.stack([rng.uniform(2.0, 6.0, n), rng.uniform(-1.0, 1.0, n)], -1)
    covs = np.einsum("nij,nkj->nik", a := rng.normal(size=(n, 2, 2)) * [[0.05], [0.01]], a) + R * spread
    k = min(m, n)
    source = rng.permutation(n)[:k]
    z = predicted[source] + rng.normal(size=(k, 2)) * np.sqrt(np.diag(R))
    extra = np.stack([rng.uniform(2.0, 6.0, m - k), rng.uniform(-1.0, 1.0, m - k)], -1)
    measurements = np.vstack([z, extra])[rng.permutation(m)] if m else np.zeros((0, 2))
    return AssociationRequest(measurements=measurements, noise=R, predicted=predicted, innovation_covs=covs, **fields)


# --- solvers on cost matrices -------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(6))
def test_exact_equals_brute_force(seed):
    rng = np.random.default_rng(seed)
    for _ in range(40):
        cost = random_cost(rng, int(rng.integers(1, 6)), int(rng.integers(1, 6)))
        rows, cols = solvers.solve_exact(cost)
        assert is_matching(rows, cols, cost)
        assert cost[rows, cols].sum() == pytest.approx(brute_force(cost), abs=1e-9)


@pytest.mark.parametrize("seed", range(4))
def test_ihgr_within_its_gap_of_brute_force(seed):
    rng = np.random.default_rng(100 + seed)
    for _ in range(25):
        cost = random_cost(rng, int(rng.integers(1, 6)), int(rng.integers(1, 6)))
        result = solvers.solve_ihgr(cost)
        optimum = brute_force(cost)
        value = cost[result.rows, result.cols].sum()
        assert is_matching(result.rows, result.cols, cost)
        assert result.lp_objective <= optimum + 1e-7
        assert value - optimum <= (value - result.lp_objective) + 1e-7
        assert value == pytest.approx(optimum, abs=1e-7)  # totally unimodular: the first LP is integral
        assert result.lp_solves == 1


def all_matchings(cost: np.ndarray) -> list[list[tuple[int, int]]]:
    m, n = cost.shape
    found = []

    def visit(row, pairs, used):
        if row == m:
            found.append(pairs)
            return
        visit(row + 1, pairs, used)
        for col in range(n):
            if col not in used and np.isfinite(cost[row, col]):
                visit(row + 1, pairs + [(row, col)], used | {col})

    visit(0, [], frozenset())
    return found


def barycentre_lp(weights, rows, cols, n_rows, n_cols):
    """An interior LP optimum (what an interior-point method without crossover returns): the mean of every optimal matching."""
    cost = np.full((n_rows, n_cols), np.inf)
    cost[rows, cols] = weights
    matchings = all_matchings(cost)
    values = np.array([sum(cost[p] for p in pairs) for pairs in matchings])
    optimal = [pairs for pairs, v in zip(matchings, values) if v <= values.min() + 1e-12]
    lookup = {(int(r), int(c)): e for e, (r, c) in enumerate(zip(rows, cols))}
    x = np.zeros(weights.size)
    for pairs in optimal:
        for p in pairs:
            x[lookup[p]] += 1.0 / len(optimal)
    return x, float(values.min())


def test_ihgr_rounds_fractional_lp_solutions():
    rng = np.random.default_rng(7)
    rounded = optimal = 0
    for _ in range(60):
        m, n = int(rng.integers(2, 5)), int(rng.integers(2, 5))
        cost = rng.integers(-3, 0, size=(m, n)).astype(float)  # integer costs: many optimal matchings
        cost[rng.random((m, n)) < 0.2] = np.inf
        result = solvers.solve_ihgr(cost, lp=barycentre_lp)
        value = cost[result.rows, result.cols].sum()
        optimum = brute_force(cost)
        assert is_matching(result.rows, result.cols, cost)
        assert result.lp_objective == pytest.approx(optimum)
        assert optimum - 1e-9 <= value <= result.lp_objective + (value - result.lp_objective) + 1e-9
        rounded += result.lp_solves > 1
        optimal += abs(value - optimum) < 1e-9
    assert rounded > 5  # the rounding loop did run
    assert optimal >= 55  # and the heuristic almost always lands on an optimum


def test_ihgr_tie_is_settled_by_enumeration():
    cost = np.array([[-3.0, -3.0], [-3.0, -1.0]])

    def half(weights, rows, cols, n_rows, n_cols):
        return np.full(weights.size, 0.5), float(weights.sum() * 0.5)

    result = solvers.solve_ihgr(cost, lp=half)
    assert cost[result.rows, result.cols].sum() == pytest.approx(brute_force(cost))  # -6: (0,1) and (1,0)
    assert result.lp_solves == 1


@pytest.mark.parametrize("seed", range(3))
def test_nn_and_greedy_against_brute_force(seed):
    rng = np.random.default_rng(200 + seed)
    for _ in range(40):
        m, n = int(rng.integers(1, 6)), int(rng.integers(1, 6))
        nis = rng.uniform(0.0, 9.0, size=(m, n))
        cost = np.where(rng.random((m, n)) < 0.6, 0.5 * nis - 5.0, np.inf)
        optimum = brute_force(cost)
        rows, cols = solvers.solve_greedy(nis, cost)
        assert is_matching(rows, cols, cost)
        assert cost[rows, cols].sum() >= optimum - 1e-9
        rows, cols = solvers.solve_nn(nis, cost)
        for r, c in zip(rows, cols):  # each measurement takes its nearest gated landmark
            assert nis[r, c] == pytest.approx(np.min(np.where(np.isfinite(cost[r]), nis[r], np.inf)))
    nis = np.array([[1.0, 2.0], [1.5, 8.0]])
    cost = 0.5 * nis - 5.0
    rows, cols = solvers.solve_nn(nis, cost)
    assert cols.tolist() == [0, 0]  # both measurements take landmark 0: NN's failure mode
    rows, cols = solvers.solve_greedy(nis, cost)
    assert sorted(zip(rows.tolist(), cols.tolist())) == [(0, 1), (1, 0)] or sorted(zip(rows.tolist(), cols.tolist())) == [(0, 0), (1, 1)]


def joint_nis(pairs, innovations, blocks, noise):
    if not pairs:
        return 0.0
    nu = np.concatenate([innovations[m, n] for m, n in pairs])
    feats = [n for _, n in pairs]
    s = np.block([[blocks[i, j] for j in feats] for i in feats]) + np.kron(np.eye(len(pairs)), noise)
    return float(nu @ np.linalg.solve(s, nu))


def joint_compatible_hypotheses(problem, probability) -> list[set]:
    """Every matching of gated pairs whose joint NIS passes the gate of its size (as sets of pairs)."""
    m, n = problem.nis.shape
    found = []

    def visit(row, pairs, used):
        if row == m:
            if not pairs or joint_nis(pairs, problem.innovations, problem.joint_blocks, problem.noise) <= \
                    solvers.gate_value(probability, 2 * len(pairs)):
                found.append(set(pairs))
            return
        visit(row + 1, pairs, used)
        for col in range(n):
            if col not in used and problem.gated[row, col]:
                visit(row + 1, pairs + [(row, col)], used | {col})

    visit(0, [], frozenset())
    return found


def brute_force_jcbb(problem, probability):
    """The jointly compatible hypothesis with the most pairings, then the smallest joint NIS: (pairs, d2)."""
    best = ([], np.inf)
    for hypothesis in joint_compatible_hypotheses(problem, probability):
        pairs = sorted(hypothesis)
        d2 = joint_nis(pairs, problem.innovations, problem.joint_blocks, problem.noise)
        if len(pairs) > len(best[0]) or (len(pairs) == len(best[0]) and d2 < best[1] - 1e-12):
            best = (pairs, d2)
    return best


@pytest.mark.parametrize("compiled", [True, False], ids=["kernel", "reference"])
@pytest.mark.parametrize("seed", range(4))
def test_jcbb_equals_brute_force_joint_compatibility(seed, compiled):
    rng = np.random.default_rng(300 + seed)
    checked = 0
    for _ in range(15):
        m, n = int(rng.integers(1, 5)), int(rng.integers(1, 5))
        pose_cov = np.diag([0.02, 0.02, 0.002]) * rng.uniform(0.5, 3.0)
        landmarks = rng.uniform([1.0, -1.0], [3.0, 1.0], size=(n, 2))
        request = AssociationRequest(
            measurements=np.stack([rng.uniform(1.0, 3.2, m), rng.uniform(-0.5, 0.5, m)], -1), noise=R * 4,
            landmarks=landmarks, landmark_covs=np.tile(np.eye(2) * 0.01, (n, 1, 1)), pose=np.zeros(3), pose_cov=pose_cov,
        )
        problem = build_problem(request)
        result = solvers.solve_jcbb(problem.innovations, problem.gated, problem.nis, problem.joint_blocks,
                                    problem.noise, request.gate_probability, compiled=compiled)
        pairs, d2 = brute_force_jcbb(problem, request.gate_probability)
        assert len(result.rows) == len(pairs)
        if pairs:
            checked += 1
            assert result.joint_nis == pytest.approx(d2, rel=1e-6, abs=1e-9)
            found = list(zip(result.rows.tolist(), result.cols.tolist()))
            assert result.joint_nis == pytest.approx(joint_nis(found, problem.innovations, problem.joint_blocks, problem.noise), rel=1e-6)
    assert checked > 5


@pytest.mark.parametrize("max_nodes", [20_000, 40])
@pytest.mark.parametrize("seed", range(3))
def test_jcbb_kernel_searches_the_tree_like_the_reference(seed, max_nodes):
    """Same pairings, same joint NIS, same node count, same truncation, on scans large enough to branch."""
    rng = np.random.default_rng(500 + seed)
    nodes, truncated = [], []
    for _ in range(10):
        n = int(rng.integers(6, 14))
        landmarks = rng.uniform([1.0, -1.5], [5.0, 1.5], size=(n, 2))
        seen = landmarks[rng.random(n) < 0.8]
        z = RangeBearingSensor().observe(np.array([0.05, -0.03, 0.02]), seen) + rng.normal(0.0, [0.05, 0.02], seen.shape)
        request = AssociationRequest(
            measurements=np.vstack([z, [[rng.uniform(1.0, 5.0), rng.uniform(-0.6, 0.6)]]]), noise=R * 4,
            landmarks=landmarks, landmark_covs=np.tile(np.eye(2) * 0.01, (n, 1, 1)), pose=np.zeros(3),
            pose_cov=np.diag([0.05, 0.05, 0.01]),
        )
        problem = build_problem(request)
        args = (problem.innovations, problem.gated, problem.nis, problem.joint_blocks, problem.noise,
                request.gate_probability, max_nodes)
        kernel, reference = solvers.solve_jcbb(*args, compiled=True), solvers.solve_jcbb(*args, compiled=False)
        np.testing.assert_array_equal(kernel.rows, reference.rows)
        np.testing.assert_array_equal(kernel.cols, reference.cols)
        assert (kernel.nodes, kernel.truncated) == (reference.nodes, reference.truncated)
        assert kernel.joint_nis == pytest.approx(reference.joint_nis, rel=1e-9, abs=1e-12)
        nodes.append(reference.nodes)
        truncated.append(reference.truncated)
    assert max(nodes) > 40  # trees that branch
    assert any(truncated) == (max_nodes == 40)  # and the bound on the search, when it bites


def test_jcbb_candidate_tables_order_like_the_reference_with_ties():
    """Candidates by NIS (ties in landmark order), measurements by candidate count (ties in measurement order),
    measurements without candidates left out."""
    from services.association import kernels

    gated = np.array([[True, True, False, True], [False, False, False, False], [True, False, True, False],
                      [False, True, False, False]])
    nis = np.array([[2.0, 1.0, 0.5, 1.0], [0.1, 0.1, 0.1, 0.1], [3.0, 9.0, 3.0, 1.0], [4.0, 0.2, 4.0, 4.0]])
    table, counts, order = kernels.jcbb_candidates(gated, nis)
    assert counts.tolist() == [3, 0, 2, 1]
    assert table[0, :3].tolist() == [1, 3, 0] and table[2, :2].tolist() == [0, 2] and table[3, 0] == 1
    assert order.tolist() == [3, 2, 0]
    empty = kernels.jcbb_candidates(np.zeros((2, 3), bool), np.zeros((2, 3)))
    assert empty[2].size == 0


# --- the core: gating, costs, components, edge cases -------------------------------------------------


def test_gate_values():
    assert solvers.gate_value(0.99, 2) == pytest.approx(9.21, abs=0.01)
    assert solvers.gate_value(0.99, 1) == pytest.approx(6.63, abs=0.01)


def test_cost_grows_with_distance_and_has_a_modelled_dummy():
    predicted = np.array([[5.0, 0.0]])
    s = np.array([R * 2])
    near = AssociationRequest(measurements=np.array([[5.01, 0.0]]), noise=R, predicted=predicted, innovation_covs=s)
    far = AssociationRequest(measurements=np.array([[5.15, 0.0]]), noise=R, predicted=predicted, innovation_covs=s)
    c_near, c_far = build_problem(near).cost[0, 0], build_problem(far).cost[0, 0]
    assert c_near < c_far  # the sign of eq. 5's exponent is corrected: farther is costlier
    nis = build_problem(near).nis[0, 0]
    expected = 0.5 * nis + 0.5 * math.log(np.linalg.det(2 * math.pi * s[0])) + math.log(2e-3) - math.log(0.9 / 0.1)
    assert c_near == pytest.approx(expected)
    dense_clutter = near.model_copy(update={"clutter_density": 1e12})
    assert associate(dense_clutter, "exact").assignment[0] == CLUTTER  # leaving it unassigned is cheaper
    assert associate(near, "exact").assignment[0] == 0


@pytest.mark.parametrize("method", ["nn", "greedy", "ihgr", "exact", "jcbb", "auto"])
def test_empty_inputs(method):
    none = np.zeros((0, 2))
    for m, n in ((0, 0), (0, 3), (3, 0)):
        request = random_request(np.random.default_rng(m * 10 + n), m, n)
        reply = associate(request, method)
        assert reply.assignment.shape == (m,) and reply.missed.shape == (n,)
        assert np.all(reply.missed) and reply.cost == 0.0
        if m:
            assert np.all(reply.assignment == NEW)
    request = AssociationRequest(measurements=none, noise=R, landmarks=none, landmark_covs=np.zeros((0, 2, 2)), pose=np.zeros(3))
    assert associate(request, method).assignment.shape == (0,)


@pytest.mark.parametrize("method", ["nn", "greedy", "ihgr", "exact", "jcbb"])
def test_everything_outside_the_gate(method):
    request = random_request(np.random.default_rng(1), 4, 4)
    request = request.model_copy(update={"measurements": request.measurements + np.array([3.0, 0.0])})
    reply = associate(request, method)
    assert reply.gated_pairs == 0
    assert np.all(reply.assignment == NEW) and np.all(reply.missed) and reply.cost == 0.0
    no_new = request.model_copy(update={"new_feature_density": 0.0})
    assert np.all(associate(no_new, method).assignment == CLUTTER)


def test_unassigned_near_a_landmark_is_clutter_not_new():
    predicted = np.array([[5.0, 0.0]])
    z = np.array([[5.0, 0.0], [5.0, 0.004 * math.pi]])  # landmark 0 goes to the first; the second is too close to it to start one
    reply = associate(AssociationRequest(measurements=z, noise=R, predicted=predicted, innovation_covs=np.array([R])), "exact")
    assert reply.assignment.tolist() == [0, CLUTTER]


@pytest.mark.parametrize("method", ["greedy", "ihgr", "exact", "jcbb"])
def test_ties_give_a_valid_optimal_matching(method):
    predicted = np.array([[5.0, 0.1], [5.0, -0.1]])
    covs = np.array([np.diag([0.01, 0.02]), np.diag([0.01, 0.02])])
    z = np.array([[5.0, 0.0], [5.0, 0.0]])  # both measurements exactly between both landmarks
    reply = associate(AssociationRequest(measurements=z, noise=R, predicted=predicted, innovation_covs=covs), method)
    assert sorted(reply.assignment.tolist()) == [0, 1]
    assert not reply.missed.any()


@pytest.mark.parametrize("seed", range(5))
def test_every_method_on_random_scans_against_brute_force(seed):
    rng = np.random.default_rng(400 + seed)
    for _ in range(10):
        request = random_request(rng, int(rng.integers(1, 6)), int(rng.integers(1, 6)), spread=rng.uniform(1.0, 30.0))
        optimum = brute_force(build_problem(request).cost)
        exact = associate(request, "exact")
        ihgr = associate(request, "ihgr")
        assert exact.cost == pytest.approx(optimum, abs=1e-9)
        assert ihgr.cost - optimum <= ihgr.gap + 1e-7 and ihgr.lp_objective <= optimum + 1e-7
        for method in ("nn", "greedy", "jcbb"):
            reply = associate(request, method)
            assigned = reply.assignment[reply.assignment >= 0]
            if method != "nn":
                assert len(set(assigned.tolist())) == assigned.size
                assert reply.cost >= optimum - 1e-9
            assert np.array_equal(reply.missed, ~np.isin(np.arange(reply.missed.size), assigned))


def test_components_split_and_solve_like_the_whole():
    rng = np.random.default_rng(5)
    gated = np.zeros((7, 6), bool)
    gated[0, 0] = True  # an isolated pair
    gated[1:3, 1:3] = True  # a 2 × 2 component
    gated[3, 3] = gated[4, 3] = gated[4, 4] = True  # a chain
    (single_rows, single_cols), comps = split_components(gated)
    assert list(zip(single_rows.tolist(), single_cols.tolist())) == [(0, 0)]
    assert sorted((r.tolist(), c.tolist()) for r, c in comps) == [([1, 2], [1, 2]), ([3, 4], [3, 4])]
    for _ in range(10):
        request = random_request(rng, 12, 12, spread=20.0)
        reply = associate(request, "exact")
        whole_rows, whole_cols = solvers.solve_exact(build_problem(request).cost)
        assert reply.cost == pytest.approx(build_problem(request).cost[whole_rows, whole_cols].sum(), abs=1e-9)


def test_landmark_form_matches_the_predicted_form():
    rng = np.random.default_rng(9)
    n = 6
    landmarks = rng.uniform(-4.0, 4.0, size=(n, 2))
    pose, pose_cov = np.array([0.5, -0.2, 0.3]), np.diag([0.03, 0.02, 0.004])
    lm_covs = np.tile(np.diag([0.02, 0.01]), (n, 1, 1))
    z = build_problem(AssociationRequest(
        measurements=np.zeros((0, 2)), noise=R, landmarks=landmarks, landmark_covs=lm_covs, pose=pose)).innovation_covs
    from robots.models import RangeBearingSensor
    sensor = RangeBearingSensor()
    zhat = sensor.observe(pose, landmarks)
    h_pose, h_lm = sensor.jacobians(pose, landmarks)
    joint = np.zeros((3 + 2 * n, 3 + 2 * n))
    joint[:3, :3] = pose_cov
    for i in range(n):
        joint[3 + 2 * i:5 + 2 * i, 3 + 2 * i:5 + 2 * i] = lm_covs[i]
    h = np.zeros((2 * n, 3 + 2 * n))
    for i in range(n):
        h[2 * i:2 * i + 2, :3] = h_pose[i]
        h[2 * i:2 * i + 2, 3 + 2 * i:5 + 2 * i] = h_lm[i]
    c = h @ joint @ h.T
    meas = zhat[[2, 0, 5]] + 0.01
    forms = [
        AssociationRequest(measurements=meas, noise=R, landmarks=landmarks, landmark_covs=lm_covs, pose=pose, pose_cov=pose_cov),
        AssociationRequest(measurements=meas, noise=R, landmarks=landmarks, landmark_covs=lm_covs, pose=pose, joint_cov=joint),
        AssociationRequest(measurements=meas, noise=R, predicted=zhat,
                           innovation_covs=np.stack([c[2 * i:2 * i + 2, 2 * i:2 * i + 2] for i in range(n)]) + R, joint_cov=c),
    ]
    problems = [build_problem(f) for f in forms]
    for p in problems[1:]:
        np.testing.assert_allclose(p.nis, problems[0].nis, rtol=1e-9)
        np.testing.assert_allclose(p.joint_blocks, problems[0].joint_blocks, rtol=1e-9, atol=1e-15)
    assert np.all(z.shape == (n, 2, 2))
    for f in forms:
        assert associate(f, "jcbb").assignment.tolist() == [2, 0, 5]
        assert associate(f, "auto").method == "jcbb"


def test_bad_requests_are_refused():
    good = dict(measurements=np.array([[5.0, 0.0]]), noise=R, predicted=np.array([[5.0, 0.0]]), innovation_covs=np.array([R]))
    with pytest.raises(ValidationError):
        AssociationRequest(**{**good, "landmarks": np.zeros((1, 2))})  # both forms
    with pytest.raises(ValidationError):
        AssociationRequest(**{**good, "innovation_covs": np.array([R, R])})  # lengths differ
    with pytest.raises(ValidationError):
        AssociationRequest(**{**good, "measurements": np.array([[-1.0, 0.0]])})  # negative range
    with pytest.raises(ValidationError):
        AssociationRequest(**{**good, "measurements": np.array([[np.nan, 0.0]])})
    with pytest.raises(ValidationError):
        AssociationRequest(**{**good, "joint_cov": np.eye(3)})
    with pytest.raises(ValidationError):
        AssociationRequest(**{**good, "clutter_density": 0.0, "new_feature_density": 0.0})
    with pytest.raises(AssociationError, match="bad_covariance"):
        associate(AssociationRequest(**{**good, "innovation_covs": np.array([-R])}))
    with pytest.raises(AssociationError, match="unknown_method"):
        associate(AssociationRequest(**good), "magic")


def test_reply_round_trips_through_the_codec():
    reply = associate(random_request(np.random.default_rng(3), 5, 5), "ihgr")
    back = decode(encode(reply), AssociationReply)
    assert np.array_equal(back.assignment, reply.assignment) and back.gap == reply.gap and back.method == "ihgr"
    request = random_request(np.random.default_rng(3), 5, 5)
    assert np.array_equal(decode(encode(request), AssociationRequest).innovation_covs, request.innovation_covs)


def test_unique_pairs_sets_aside_a_pairing_another_hypothesis_does_as_well_without():
    """Two landmarks 2 m apart and a pose known to ±3 m: one sighting fits either landmark, so with
    ``unique_pairs`` it is AMBIGUOUS (plain JCBB guesses one); sightings of both pin the pairing down (the swap
    would need a half turn the heading std of 0.05 rad rules out), so both stay paired."""
    sensor = RangeBearingSensor()
    landmarks = np.array([[5.0, 1.0], [5.0, -1.0]])
    pose, pose_cov = np.zeros(3), np.diag([3.0**2, 3.0**2, 0.05**2])
    lm_covs = np.tile(np.diag([0.01, 0.01]), (2, 1, 1))
    zhat = sensor.observe(pose, landmarks)

    def reply(measurements: np.ndarray, unique: bool) -> np.ndarray:
        request = AssociationRequest(measurements=measurements, noise=R, landmarks=landmarks, landmark_covs=lm_covs,
                                     pose=pose, pose_cov=pose_cov, unique_pairs=unique)
        return associate(request, "jcbb").assignment

    one = zhat[[0]] + [0.02, 0.0]
    assert reply(one, unique=False).tolist() == [0]
    assert reply(one, unique=True).tolist() == [AMBIGUOUS]
    both = zhat[[1, 0]] + [0.02, 0.0]
    assert reply(both, unique=False).tolist() == [1, 0]
    assert reply(both, unique=True).tolist() == [1, 0]


@pytest.mark.parametrize("compiled", [True, False], ids=["kernel", "reference"])
@pytest.mark.parametrize("seed", range(3))
def test_jcbb_ambiguous_against_brute_force(seed, compiled):
    """A pair of JCBB's hypothesis is flagged exactly when a jointly compatible hypothesis without it pairs as
    many measurements (every hypothesis enumerated); scans with a wide pose uncertainty, so that both cases occur."""
    rng = np.random.default_rng(500 + seed)
    flagged = kept = 0
    for _ in range(15):
        m, n = int(rng.integers(1, 5)), int(rng.integers(2, 5))
        landmarks = rng.uniform([1.0, -1.5], [4.0, 1.5], size=(n, 2))
        request = AssociationRequest(
            measurements=np.stack([rng.uniform(1.0, 4.2, m), rng.uniform(-0.6, 0.6, m)], -1), noise=R * 4,
            landmarks=landmarks, landmark_covs=np.tile(np.eye(2) * 0.01, (n, 1, 1)), pose=np.zeros(3),
            pose_cov=np.diag([0.1, 0.1, 0.01]) * rng.uniform(0.1, 3.0),
        )
        problem = build_problem(request)
        args = (problem.innovations, problem.gated, problem.nis, problem.joint_blocks, problem.noise,
                request.gate_probability)
        best = solvers.solve_jcbb(*args, compiled=compiled)
        flags = solvers.jcbb_ambiguous(*args, best, compiled=compiled)
        hypotheses = joint_compatible_hypotheses(problem, request.gate_probability)
        for k, pair in enumerate(zip(best.rows.tolist(), best.cols.tolist())):
            assert flags[k] == any(len(h) >= best.rows.size and pair not in h for h in hypotheses)
        flagged += int(flags.sum())
        kept += int((~flags).sum())
    assert flagged > 0 and kept > 0
