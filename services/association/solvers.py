"""Assignment solvers for one scan (paper 000 §III, Neira & Tardós 2001).

Every solver works on a cost matrix ``cost`` (M, N) of pair costs c_nm with
``+inf`` for pairs outside the gate; the cost of leaving a measurement
unassigned or a landmark missed is 0 (the dummy, already folded into c_nm by
:mod:`services.association.core`). A solver returns the chosen pairs as two
index arrays ``(rows, cols)`` (measurement, landmark).

- :func:`solve_nn`: nearest neighbour per measurement (smallest Mahalanobis
  distance among gated landmarks; several measurements may take one landmark).
- :func:`solve_greedy`: greedy global nearest neighbour (smallest distance
  first, each measurement and landmark used once).
- :func:`solve_ihgr`: the paper's LP relaxation with iterative heuristic greedy
  rounding (IHGR).
- :func:`solve_exact`: the optimum of eqs. 6-8 by ``linear_sum_assignment`` on
  the dummy-augmented square matrix.
- :func:`solve_jcbb`: joint compatibility branch and bound (maximum number of
  jointly compatible pairings, then smallest joint NIS).

The iterative solvers (greedy, IHGR, JCBB) take a :class:`Budget`, a time
budget on an injected clock: they check it between steps and stop with their
best pairs so far (``truncated``), or raise :class:`DeadlineExceeded` when they
have nothing to give.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from functools import lru_cache
from typing import Callable

import numpy as np
from scipy import sparse

from robots.gaussian import chi2_quantile
from services.association import kernels

Pairs = tuple[np.ndarray, np.ndarray]
LpSolver = Callable[[np.ndarray, np.ndarray, np.ndarray, int, int], tuple[np.ndarray, float]]

_EMPTY = np.zeros(0, np.int64)


gate_value = chi2_quantile  # the chi-square gate ε with P(τ ≤ ε) = probability for dof degrees of freedom


@lru_cache(maxsize=64)
def _chi2_bounds(probability: float, count: int) -> np.ndarray:
    bounds = np.array([gate_value(probability, 2 * k) for k in range(1, count + 1)])
    bounds.flags.writeable = False
    return bounds


def chi2_bounds(probability: float, count: int) -> np.ndarray:
    """JCBB's bounds ``(count,)``: the χ² gate of k = 1..``count`` pairings (2k degrees of freedom), computed once per
    (probability, power of two at least ``count``) and shared, so read-only."""
    return _chi2_bounds(float(probability), max(8, 1 << max(count - 1, 0).bit_length()))[:count]


class DeadlineExceeded(RuntimeError):
    """The time budget ran out before the solver had an answer to give."""


class Budget:
    """``seconds`` of time from now on ``clock`` (None: unbounded); the solvers ask :meth:`spent` between steps.

    The clock is injected, so that tests decide when the time is up. A solver that stops short because of it sets
    ``cut``.
    """

    def __init__(self, seconds: float | None = None, clock: Callable[[], float] = time.perf_counter):
        self.seconds = seconds
        self.clock = clock
        self.started = clock()
        self.cut = False

    @property
    def bounded(self) -> bool:
        return self.seconds is not None

    def remaining(self) -> float:
        return math.inf if self.seconds is None else self.seconds - (self.clock() - self.started)

    def spent(self) -> bool:
        return self.seconds is not None and self.remaining() <= 0.0


def solve_nn(nis: np.ndarray, cost: np.ndarray) -> Pairs:
    """Per measurement, the gated landmark of smallest NIS, kept if its cost beats the dummy (c < 0)."""
    if nis.size == 0:
        return _EMPTY, _EMPTY
    distance = np.where(np.isfinite(cost), nis, np.inf)
    best = np.argmin(distance, axis=1)
    rows = np.arange(nis.shape[0])
    keep = cost[rows, best] < 0.0
    return rows[keep], best[keep]


def solve_greedy(nis: np.ndarray, cost: np.ndarray, budget: Budget | None = None) -> Pairs:
    """Global greedy nearest neighbour: take gated pairs by increasing NIS while both ends are free (the pairs taken
    so far once the ``budget`` is spent)."""
    rows, cols = np.nonzero(np.isfinite(cost) & (cost < 0.0))
    order = np.argsort(nis[rows, cols], kind="stable")
    used_rows, used_cols, chosen = set(), set(), []
    for step, k in enumerate(order):
        if step % 4096 == 4095 and budget is not None and budget.spent():
            budget.cut = True
            break
        r, c = int(rows[k]), int(cols[k])
        if r not in used_rows and c not in used_cols:
            used_rows.add(r)
            used_cols.add(c)
            chosen.append(k)
    chosen = np.asarray(chosen, np.int64)
    return (rows[chosen], cols[chosen]) if chosen.size else (_EMPTY, _EMPTY)


def solve_exact(cost: np.ndarray) -> Pairs:
    """Optimum of eqs. 6-8: ``linear_sum_assignment`` on the (M+N)×(N+M) dummy-augmented matrix.

    Row m < M may take landmark column n (cost c_nm) or its own dummy column
    N+m (cost 0); dummy row M+n may take landmark column n (landmark n missed,
    cost 0) or any dummy column (cost 0).
    """
    m, n = cost.shape
    if m == 0 or n == 0:
        return _EMPTY, _EMPTY
    big = np.full((m + n, n + m), np.inf)
    big[:m, :n] = cost
    big[np.arange(m), n + np.arange(m)] = 0.0
    big[m + np.arange(n), np.arange(n)] = 0.0
    big[m:, n:] = 0.0
    from scipy.optimize import linear_sum_assignment  # scipy.optimize takes 0.1 s to load: only where it is used

    rows, cols = linear_sum_assignment(big)
    keep = (rows < m) & (cols < n)
    return rows[keep].astype(np.int64), cols[keep].astype(np.int64)


def lp_relaxation(weights: np.ndarray, rows: np.ndarray, cols: np.ndarray, n_rows: int, n_cols: int,
                  time_limit: float | None = None) -> tuple[np.ndarray, float]:
    """Solve the LP relaxation of eqs. 6-8 over the pairs (rows[e], cols[e]) with HiGHS (within ``time_limit``
    seconds when given, else DeadlineExceeded).

    min Σ w_e x_e  s.t.  Σ_{e ∋ m} x_e ≤ 1,  Σ_{e ∋ n} x_e ≤ 1,  0 ≤ x ≤ 1
    (the slack of each inequality is the dummy variable x_0m or x_n0, cost 0).
    When every pair shares one measurement or one landmark, a single constraint
    couples them and the optimum is in closed form (the cheapest negative pair).
    """
    e = weights.shape[0]
    if e and (np.all(rows == rows[0]) or np.all(cols == cols[0])):
        x = np.zeros(e)
        best = int(np.argmin(weights))
        x[best] = float(weights[best] < 0.0)
        return x, min(float(weights[best]), 0.0)
    index = np.arange(e)
    a_ub = sparse.csr_matrix(
        (np.ones(2 * e), (np.concatenate([rows, n_rows + cols]), np.concatenate([index, index]))),
        shape=(n_rows + n_cols, e),
    )
    from scipy.optimize import linprog

    options = {} if time_limit is None else {"time_limit": max(float(time_limit), 1e-3)}
    result = linprog(weights, A_ub=a_ub, b_ub=np.ones(n_rows + n_cols), bounds=(0.0, 1.0), method="highs",
                     options=options)
    if result.status == 1 and time_limit is not None:
        raise DeadlineExceeded(f"IHGR: the LP relaxation of {e} pairs ran out of time ({time_limit:.3g} s)")
    if result.status != 0:
        raise RuntimeError(f"IHGR: the LP relaxation failed ({result.message})")
    return np.clip(result.x, 0.0, 1.0), float(result.fun)


@dataclass
class IhgrResult:
    rows: np.ndarray
    cols: np.ndarray
    lp_objective: float  # optimum of the first LP (a lower bound on the IP optimum)
    lp_solves: int
    truncated: bool = False  # the budget ran out while rounding: the pairs fixed so far


def _best_matching(weights: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> list[int]:
    """Enumerate every matching among the given pairs; return the indices of the cheapest (ties: first found)."""
    best_cost, best = 0.0, []
    order = np.argsort(rows, kind="stable")

    def extend(k: int, used_r: frozenset, used_c: frozenset, total: float, chosen: list[int]) -> None:
        nonlocal best_cost, best
        if k == order.size:
            if total < best_cost:
                best_cost, best = total, list(chosen)
            return
        e = int(order[k])
        if rows[e] not in used_r and cols[e] not in used_c:
            extend(k + 1, used_r | {rows[e]}, used_c | {cols[e]}, total + weights[e], chosen + [e])
        extend(k + 1, used_r, used_c, total, chosen)

    extend(0, frozenset(), frozenset(), 0.0, [])
    return best


def solve_ihgr(
    cost: np.ndarray,
    tie_margin: float = 0.05,
    tolerance: float = 1e-6,
    max_tie_pairs: int = 16,
    lp: LpSolver = lp_relaxation,
    budget: Budget | None = None,
) -> IhgrResult:
    """Paper 000 §III-B: LP relaxation, then iterative heuristic greedy rounding.

    Solve the LP; fix every variable at 1 and delete its row and column (with
    the variables they implicate). While fractional variables remain: set the
    largest to 1 (if the runner-up is within ``tie_margin`` of it, a tie:
    enumerate every combination of the tied variables and fix the cheapest),
    delete its row and column, and solve the LP of what is left. The
    single-scan LP is totally unimodular, so HiGHS' vertex optimum is already
    integral and the loop usually ends after one LP; ``lp`` can be replaced
    (tests inject fractional optima to exercise the rounding; with a bounded
    ``budget`` it is given the time left as ``time_limit``). Once the budget
    is spent, the rounding stops with the pairs fixed so far (``truncated``);
    DeadlineExceeded when the first LP does not finish in time.
    """
    n_rows, n_cols = cost.shape
    pair_rows, pair_cols = np.nonzero(np.isfinite(cost))
    weights = cost[pair_rows, pair_cols]
    active = np.ones(weights.shape[0], bool)
    fixed: list[int] = []
    if weights.size == 0:
        return IhgrResult(_EMPTY, _EMPTY, 0.0, 0)

    def fix(indices) -> None:
        for e in indices:
            fixed.append(int(e))
        hit_rows, hit_cols = pair_rows[list(indices)], pair_cols[list(indices)]
        active[np.isin(pair_rows, hit_rows) | np.isin(pair_cols, hit_cols)] = False

    def solve_lp(*args) -> tuple[np.ndarray, float]:
        if budget is None or not budget.bounded:
            return lp(*args)
        remaining = budget.remaining()
        if remaining <= 0.0:
            raise DeadlineExceeded("IHGR: no time left for the LP relaxation")
        return lp(*args, time_limit=remaining)

    values, lp_objective = solve_lp(weights, pair_rows, pair_cols, n_rows, n_cols)
    values = values.copy()
    solves = 1
    truncated = False
    while True:
        ones = np.flatnonzero(active & (values > 1.0 - tolerance))
        if ones.size:
            fix(ones)
        fractional = np.flatnonzero(active & (values > tolerance))
        if fractional.size == 0:
            break
        if budget is not None and budget.spent():
            truncated = budget.cut = True
            break
        ranked = fractional[np.argsort(-values[fractional], kind="stable")]
        top = values[ranked[0]]
        tied = ranked[values[ranked] > top - tie_margin]
        if tied.size > 1 and tied.size <= max_tie_pairs:
            chosen = [int(tied[k]) for k in _best_matching(weights[tied], pair_rows[tied], pair_cols[tied])]
            if chosen:
                fix(chosen)
            else:
                active[tied] = False
        else:
            fix([int(ranked[0])])
        remaining = np.flatnonzero(active)
        if remaining.size == 0:
            break
        try:
            x, _ = solve_lp(weights[remaining], pair_rows[remaining], pair_cols[remaining], n_rows, n_cols)
        except DeadlineExceeded:
            truncated = budget.cut = True
            break
        solves += 1
        values[:] = 0.0
        values[remaining] = x
    fixed_array = np.asarray(fixed, np.int64)
    return IhgrResult(pair_rows[fixed_array].astype(np.int64), pair_cols[fixed_array].astype(np.int64), lp_objective, solves,
                      truncated)


def _inverse_cholesky_2x2(s: np.ndarray) -> np.ndarray | None:
    """L⁻¹ for the lower Cholesky factor L of a 2 × 2 matrix; None unless positive definite."""
    if s[0, 0] <= 0.0:
        return None
    l11 = math.sqrt(s[0, 0])
    l21 = s[1, 0] / l11
    rest = s[1, 1] - l21 * l21
    if rest <= 0.0:
        return None
    l22 = math.sqrt(rest)
    return np.array([[1.0 / l11, 0.0], [-l21 / (l11 * l22), 1.0 / l22]])


@dataclass
class JcbbResult:
    rows: np.ndarray
    cols: np.ndarray
    joint_nis: float
    truncated: bool  # the node budget or the time budget ran out: the best found so far
    nodes: int


def solve_jcbb(
    innovations: np.ndarray,
    gated: np.ndarray,
    nis: np.ndarray,
    joint_blocks: np.ndarray,
    noise: np.ndarray,
    probability: float,
    max_nodes: int = 20_000,
    compiled: bool = True,
    budget: Budget | None = None,
    slice_work: int = 20_000_000,
) -> JcbbResult:
    """Joint compatibility branch and bound (Neira & Tardós 2001).

    Searches the interpretation tree measurement by measurement for the
    hypothesis H with the most pairings whose joint innovation ν_H passes
    ν_Hᵀ S_H⁻¹ ν_H ≤ χ²(2|H|) with S_H = C_H + blockdiag(R) (``joint_blocks``
    (N, N, 2, 2) are the blocks of C, the joint covariance of the predicted
    observations); ties go to the smaller joint NIS. The joint NIS is grown
    incrementally with the inverse L⁻¹ of the Cholesky factor of S_H (a 2 × 2
    Schur complement per new pair). Measurements are visited
    fewest candidates first; a branch stops once it cannot beat the best
    pairings found. ``max_nodes`` bounds the search (``truncated`` then), and
    so does the time ``budget`` (checked every ``slice_work`` multiply-adds
    of the kernel, every node of the reference): the best pairings so far
    (``truncated``, ``budget.cut``), or DeadlineExceeded if there are none.

    ``compiled`` runs the same search in the numba kernel of :mod:`services.association.kernels`; False,
    this recursive reference.
    """
    m_count = innovations.shape[0]
    if compiled and kernels.AVAILABLE and budget is None:
        rows, cols, d2, truncated, nodes = kernels.jcbb_whole_kernel(
            np.ascontiguousarray(innovations, float), np.ascontiguousarray(joint_blocks, float),
            np.asarray(noise, float), np.ascontiguousarray(gated, np.bool_), np.ascontiguousarray(nis, float),
            chi2_bounds(probability, m_count), max_nodes)
        return JcbbResult(rows, cols, float(d2), bool(truncated), int(nodes))
    if compiled and kernels.AVAILABLE:
        table, counts, order = kernels.jcbb_candidates(np.ascontiguousarray(gated, np.bool_),
                                                        np.ascontiguousarray(nis, float))
        if not order.size:
            return JcbbResult(_EMPTY, _EMPTY, 0.0, False, 0)
        bounds = np.array([gate_value(probability, 2 * k) for k in range(1, order.size + 1)])
        state = kernels.JcbbState(order.size)
        inputs = (np.ascontiguousarray(innovations, float), np.ascontiguousarray(joint_blocks, float),
                  np.asarray(noise, float), table, counts, order, bounds, max_nodes)
        limit = slice_work if budget is not None and budget.bounded else 0
        while not (budget is not None and budget.spent()):
            if kernels.jcbb_search(*inputs, *state.arrays(), limit):
                break
        else:
            budget.cut = True
        rows, cols, count, d2, truncated, nodes = state.result()
        if budget is not None and budget.cut and not count:
            raise DeadlineExceeded(f"JCBB: no jointly compatible pairing found in {budget.seconds:.3g} s ({nodes} nodes)")
        return JcbbResult(rows, cols, float(d2) if count else 0.0, truncated or (budget is not None and budget.cut), nodes)
    candidates = [np.flatnonzero(gated[m])[np.argsort(nis[m, gated[m]], kind="stable")] for m in range(m_count)]
    order = [m for m in sorted(range(m_count), key=lambda m: len(candidates[m])) if candidates[m].size]
    if not order:
        return JcbbResult(_EMPTY, _EMPTY, 0.0, False, 0)
    bounds = [gate_value(probability, 2 * k) for k in range(1, len(order) + 1)]
    best = {"pairs": [], "d2": np.inf}
    nodes = 0
    truncated = False

    def search(depth: int, pairs: list[tuple[int, int]], inv_chol: np.ndarray, white: np.ndarray, d2: float) -> None:
        nonlocal nodes, truncated
        nodes += 1
        if nodes > max_nodes:
            truncated = True
            return
        if budget is not None and budget.spent():
            truncated = budget.cut = True
            return
        if depth == len(order):
            if len(pairs) > len(best["pairs"]) or (len(pairs) == len(best["pairs"]) and d2 < best["d2"]):
                best["pairs"], best["d2"] = list(pairs), d2
            return
        m = order[depth]
        features = [n for _, n in pairs]
        for n in candidates[m]:
            if n in features:
                continue
            b = inv_chol @ joint_blocks[features, n].reshape(-1, 2)  # L⁻¹ C_{H,n}
            schur = joint_blocks[n, n] + noise - b.T @ b
            residual = innovations[m, n] - b.T @ white
            inv_lower = _inverse_cholesky_2x2(schur)
            if inv_lower is None:
                continue
            u = inv_lower @ residual
            d2_new = d2 + float(u @ u)
            if d2_new > bounds[len(pairs)]:
                continue
            k = inv_chol.shape[0]
            grown = np.zeros((k + 2, k + 2))
            grown[:k, :k] = inv_chol
            grown[k:, :k] = -inv_lower @ b.T @ inv_chol
            grown[k:, k:] = inv_lower
            search(depth + 1, pairs + [(m, int(n))], grown, np.concatenate([white, u]), d2_new)
            if truncated:
                return
        if len(pairs) + len(order) - depth - 1 >= len(best["pairs"]):
            search(depth + 1, pairs, inv_chol, white, d2)

    search(0, [], np.zeros((0, 0)), np.zeros(0), 0.0)
    pairs = best["pairs"]
    if budget is not None and budget.cut and not pairs:
        raise DeadlineExceeded(f"JCBB: no jointly compatible pairing found in {budget.seconds:.3g} s ({nodes} nodes)")
    rows = np.asarray([p[0] for p in pairs], np.int64)
    cols = np.asarray([p[1] for p in pairs], np.int64)
    return JcbbResult(rows, cols, float(best["d2"]) if pairs else 0.0, truncated, nodes)


def jcbb_ambiguous(
    innovations: np.ndarray,
    gated: np.ndarray,
    nis: np.ndarray,
    joint_blocks: np.ndarray,
    noise: np.ndarray,
    probability: float,
    best: JcbbResult,
    max_nodes: int = 20_000,
    compiled: bool = True,
    budget: Budget | None = None,
) -> np.ndarray:
    """Which pairs of the JCBB hypothesis ``best`` are not unique: (len(best.rows),) bool.

    A pair (m, n) is ambiguous when, with that one pairing forbidden, JCBB still finds a hypothesis with as
    many jointly compatible pairings: another reading of the scan explains it as well, so the pair is a guess
    (the local-uniqueness test of E. Olson, "Recognizing places using spectrally clustered local matches",
    RAS 2009, on JCBB's hypotheses). Under a wide pose uncertainty among evenly spaced landmarks a
    confident wrong pairing passes every gate; this test is what sets it apart. One JCBB search per pair.
    """
    flags = np.zeros(best.rows.size, bool)
    for k, (m, n) in enumerate(zip(best.rows.tolist(), best.cols.tolist())):
        if budget is not None and budget.spent():
            break
        without = gated.copy()
        without[m, n] = False
        try:
            other = solve_jcbb(innovations, without, nis, joint_blocks, noise, probability, max_nodes, compiled, budget)
        except DeadlineExceeded:
            break
        flags[k] = other.rows.size >= best.rows.size
    return flags
