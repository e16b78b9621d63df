"""Single-scan data association: gating, costs, components and the one entry point :func:`associate`.

Every service calls :func:`associate` in-process, and the ``fleetslam assoc``
queryable calls it too. Steps (paper 000 §II-III, DESIGN §4):

1. Predicted observations ẑ_n and innovation covariances S_n, given or computed
   from landmarks + pose with the sensor model of :mod:`robots.models`.
2. Innovations ν_mn = z_m − ẑ_n (bearing wrapped) and NIS d²_mn = νᵀS_n⁻¹ν.
3. Gate: d²_mn ≤ χ²₂(gate_probability) (9.21 for 0.99; the paper's 6.63 is the
   1-dof value).
4. Cost (the paper's eq. 5 with its exponent's sign corrected, as a likelihood
   ratio against the dummy): c_nm = ½d² + ½ln|2πS_n| + ln λ − ln(P_D/(1−P_D)).
5. Isolated gated pairs are decided at once (c < 0); IHGR solves one LP over
   the rest of the gate graph (separable over its connected components).
6. Unassigned measurements become NEW when they lie outside every landmark's
   new-feature gate, CLUTTER otherwise.

A time budget (``time_budget_s`` on an injected ``clock``) bounds a solve: the
iterative solvers stop with their best so far (the reply says ``truncated``),
and a solve with nothing to give raises AssociationError ``deadline``.
:func:`query_cells` sizes a request before any of this is built.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from functools import cached_property
from typing import Callable

import numpy as np

from robots.models import RangeBearingSensor, wrap_angle
from schemas.association import AMBIGUOUS, CLUTTER, NEW, AssociationReply, AssociationRequest
from services.association import solvers


class AssociationError(ValueError):
    """A request that cannot be solved (bad covariance, unknown method); ``reason`` labels it."""

    def __init__(self, reason: str, detail: str = ""):
        self.reason = reason
        self.detail = detail
        super().__init__(f"{reason}: {detail}" if detail else reason)


@dataclass
class Problem:
    """The gated assignment problem of one scan."""

    range_innovations: np.ndarray  # (M, N) r_m − r̂_n
    bearing_innovations: np.ndarray  # (M, N) φ_m − φ̂_n, wrapped
    nis: np.ndarray  # (M, N) squared Mahalanobis distances
    cost: np.ndarray  # (M, N) pair costs c_nm, +inf outside the gate
    innovation_covs: np.ndarray  # (N, 2, 2) S_n
    noise: np.ndarray  # (2, 2) R
    new_feature_gate: float
    blocks: Callable[[], np.ndarray]  # computes the joint covariance blocks (only JCBB needs them)

    @property
    def gated(self) -> np.ndarray:
        return np.isfinite(self.cost)

    @cached_property
    def innovations(self) -> np.ndarray:
        """(M, N, 2) innovations z_m − ẑ_n (bearing wrapped)."""
        return np.stack([self.range_innovations, self.bearing_innovations], -1)

    @cached_property
    def joint_blocks(self) -> np.ndarray:
        """(N, N, 2, 2) blocks of the joint covariance of the predicted observations (without R)."""
        return self.blocks()


def _inverse_and_logdet(covs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse and ln|2πS| of (N, 2, 2) covariances; AssociationError unless positive definite."""
    a, b, c, d = covs[:, 0, 0], covs[:, 0, 1], covs[:, 1, 0], covs[:, 1, 1]
    det = a * d - b * c
    bad = np.flatnonzero(~((a > 0) & (d > 0) & (det > 0)))
    if bad.size:
        raise AssociationError("bad_covariance", f"innovation covariance of landmark {int(bad[0])} is not positive definite")
    inverse = np.empty_like(covs)
    inverse[:, 0, 0], inverse[:, 0, 1], inverse[:, 1, 0], inverse[:, 1, 1] = d / det, -b / det, -c / det, a / det
    return inverse, np.log((2 * math.pi) ** 2 * det)


def _predict(request: AssociationRequest) -> tuple[np.ndarray, np.ndarray, Callable[[], np.ndarray]]:
    """(ẑ (N,2), S (N,2,2), a function giving the joint-covariance blocks of ẑ (N,N,2,2)) from either form.

    Landmark form: ẑ = h(pose, l_n) and cov(ẑ) = J P Jᵀ with J = [H_pose | blockdiag(H_lm)],
    P the joint covariance of [pose, landmarks] (block-diagonal unless ``joint_cov`` is given).
    """
    noise = request.noise
    if request.predicted is not None:
        predicted, covs = request.predicted, request.innovation_covs
        n = predicted.shape[0]
        if request.joint_cov is not None:
            return predicted, covs, lambda: request.joint_cov.reshape(n, 2, n, 2).transpose(0, 2, 1, 3)

        def diagonal() -> np.ndarray:
            blocks = np.zeros((n, n, 2, 2))
            blocks[np.arange(n), np.arange(n)] = covs - noise
            return blocks

        return predicted, covs, diagonal
    sensor = RangeBearingSensor(tuple(request.sensor_offset))
    landmarks = request.landmarks
    n = landmarks.shape[0]
    predicted = sensor.observe(request.pose, landmarks)
    h_pose, h_lm = sensor.jacobians(request.pose, landmarks)
    if request.joint_cov is not None:
        p = request.joint_cov
        p_pp, p_pl = p[:3, :3], p[:3, 3:].reshape(3, n, 2).transpose(1, 0, 2)  # (n, 3, 2)
        p_ll = p[3:, 3:].reshape(n, 2, n, 2).transpose(0, 2, 1, 3)
    else:
        p_pp = request.pose_cov if request.pose_cov is not None else np.zeros((3, 3))
        p_pl = np.zeros((n, 3, 2))
        p_ll = None
    p_ll_diag = p_ll[np.arange(n), np.arange(n)] if p_ll is not None else request.landmark_covs
    covs = h_pose @ p_pp @ np.swapaxes(h_pose, -1, -2) + h_lm @ p_ll_diag @ np.swapaxes(h_lm, -1, -2) + noise
    if request.joint_cov is not None:
        cross = h_pose @ p_pl @ np.swapaxes(h_lm, -1, -2)
        covs += cross + np.swapaxes(cross, -1, -2)

    def joint() -> np.ndarray:
        blocks = np.einsum("iab,bc,jdc->ijad", h_pose, p_pp, h_pose)
        cross = np.einsum("iab,jbc,jdc->ijad", h_pose, p_pl, h_lm)
        blocks += cross + np.swapaxes(cross, 0, 1).swapaxes(-1, -2)
        if p_ll is not None:
            blocks += np.einsum("iab,ijbc,jdc->ijad", h_lm, p_ll, h_lm)
        else:
            blocks[np.arange(n), np.arange(n)] += h_lm @ p_ll_diag @ np.swapaxes(h_lm, -1, -2)
        return blocks

    return predicted, covs, joint


def build_problem(request: AssociationRequest) -> Problem:
    """Innovations, NIS, gate and costs of every (measurement, landmark) pair (steps 1-4)."""
    predicted, covs, blocks = _predict(request)
    inverse, logdet = _inverse_and_logdet(covs) if covs.shape[0] else (np.zeros((0, 2, 2)), np.zeros(0))
    z = request.measurements
    v0 = z[:, 0, None] - predicted[None, :, 0]
    v1 = wrap_angle(z[:, 1, None] - predicted[None, :, 1])
    nis = inverse[:, 0, 0] * v0 * v0 + 2.0 * inverse[:, 0, 1] * v0 * v1 + inverse[:, 1, 1] * v1 * v1
    gate = solvers.gate_value(request.gate_probability, 2)
    p_d = request.detection_probability
    log_ratio = math.log(request.clutter_density + request.new_feature_density) - math.log(p_d / (1.0 - p_d))
    cost = np.where(nis <= gate, 0.5 * nis + 0.5 * logdet[None, :] + log_ratio, np.inf)
    return Problem(
        range_innovations=v0, bearing_innovations=v1, nis=nis, cost=cost, innovation_covs=covs, noise=request.noise,
        blocks=blocks, new_feature_gate=solvers.gate_value(request.new_feature_gate_probability, 2),
    )


def split_components(gated: np.ndarray) -> tuple[tuple[np.ndarray, np.ndarray], list[tuple[np.ndarray, np.ndarray]]]:
    """Split the gate graph: (isolated pairs (rows, cols), [(rows, cols) of each larger component]).

    An isolated pair is a measurement with one gated landmark that no other
    measurement gates; every other connected component of the bipartite gate
    graph is returned as its measurement and landmark indices (found by
    propagating the smallest measurement index along the edges).
    """
    single_rows, single_cols, rest = _isolated_pairs(gated)
    rows, cols = np.nonzero(rest)
    if rows.size == 0:
        return (single_rows, single_cols), []
    row_label = np.arange(gated.shape[0])
    while True:
        col_label = np.full(gated.shape[1], gated.shape[0])
        np.minimum.at(col_label, cols, row_label[rows])
        updated = row_label.copy()
        np.minimum.at(updated, rows, col_label[cols])
        if np.array_equal(updated, row_label):
            break
        row_label = updated
    comp_rows, comp_cols = np.unique(rows), np.unique(cols)
    comp_rows = comp_rows[np.argsort(row_label[comp_rows], kind="stable")]
    comp_cols = comp_cols[np.argsort(col_label[comp_cols], kind="stable")]
    row_cuts = np.flatnonzero(np.diff(row_label[comp_rows])) + 1
    col_cuts = np.flatnonzero(np.diff(col_label[comp_cols])) + 1
    return (single_rows, single_cols), list(zip(np.split(comp_rows, row_cuts), np.split(comp_cols, col_cuts)))


def _isolated_pairs(gated: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rows, cols) of the isolated gated pairs, and the mask of every other gated pair."""
    isolated = gated & (gated.sum(1)[:, None] == 1) & (gated.sum(0)[None, :] == 1)
    rows, cols = np.nonzero(isolated)
    return rows, cols, gated & ~isolated


def _solve_exact(problem: Problem, budget: solvers.Budget | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """The optimum: isolated pairs taken when c < 0, everything else in one ``linear_sum_assignment``.

    The problem is separable over the gate graph's components, so solving
    their union at once gives the same optimum, and the C solver copes with the
    block structure faster than a Python loop over components would.
    """
    single_rows, single_cols, rest = _isolated_pairs(problem.gated)
    take = problem.cost[single_rows, single_cols] < 0.0
    rows, cols = [single_rows[take]], [single_cols[take]]
    if rest.any():
        if budget is not None and budget.spent():
            raise solvers.DeadlineExceeded("exact: no time left for the assignment")
        union_rows, union_cols = np.flatnonzero(rest.any(1)), np.flatnonzero(rest.any(0))
        r, c = solvers.solve_exact(problem.cost[np.ix_(union_rows, union_cols)])
        rows.append(union_rows[r])
        cols.append(union_cols[c])
    return np.concatenate(rows).astype(np.int64), np.concatenate(cols).astype(np.int64), {}


def _solve_ihgr(problem: Problem, tie_margin: float, budget: solvers.Budget | None = None,
                ) -> tuple[np.ndarray, np.ndarray, dict]:
    """Paper 000 §III: isolated pairs taken when c < 0, then IHGR on the rest of the gate graph.

    The LP is separable over the gate graph's components, so one LP over their
    union has the optimum of one LP per component, and HiGHS starts once instead
    of once per component (its start-up, not the solve, is what costs). The
    rounding then picks the largest fractional variable over every component.
    """
    (single_rows, single_cols), components = split_components(problem.gated)
    take = problem.cost[single_rows, single_cols] < 0.0
    rows, cols = [single_rows[take]], [single_cols[take]]
    lp_objective = float(np.minimum(problem.cost[single_rows, single_cols], 0).sum())
    lp_solves = 0
    if components:  # an isolated pair's row and column gate nothing else: the union holds no isolated pair
        union_rows = np.sort(np.concatenate([comp_rows for comp_rows, _ in components]))
        union_cols = np.sort(np.concatenate([comp_cols for _, comp_cols in components]))
        result = solvers.solve_ihgr(problem.cost[np.ix_(union_rows, union_cols)], tie_margin=tie_margin, budget=budget)
        lp_objective += result.lp_objective
        lp_solves += result.lp_solves
        rows.append(union_rows[result.rows])
        cols.append(union_cols[result.cols])
    info = {"components": len(components), "lp_objective": lp_objective, "lp_solves": lp_solves}
    return np.concatenate(rows).astype(np.int64), np.concatenate(cols).astype(np.int64), info


def solve(problem: Problem, method: str, request: AssociationRequest, budget: solvers.Budget | None = None,
          ) -> tuple[np.ndarray, np.ndarray, dict]:
    """Run one concrete method on a built problem: (rows, cols, extra reply fields), within ``budget``."""
    if method == "nn":
        rows, cols = solvers.solve_nn(problem.nis, problem.cost)
        return rows, cols, {}
    if method == "greedy":
        rows, cols = solvers.solve_greedy(problem.nis, problem.cost, budget)
        return rows, cols, {}
    if method == "exact":
        return _solve_exact(problem, budget)
    if method == "ihgr":
        return _solve_ihgr(problem, request.ihgr_tie_margin, budget)
    if method == "jcbb":
        result = solvers.solve_jcbb(
            problem.innovations, problem.gated, problem.nis, problem.joint_blocks, problem.noise,
            request.gate_probability, request.jcbb_max_nodes, budget=budget,
        )
        extra = {"joint_nis": result.joint_nis, "truncated": result.truncated}
        if request.unique_pairs and result.rows.size:
            not_unique = solvers.jcbb_ambiguous(
                problem.innovations, problem.gated, problem.nis, problem.joint_blocks, problem.noise,
                request.gate_probability, result, request.jcbb_max_nodes, budget=budget,
            )
            extra["not_unique"] = result.rows[not_unique]
        return result.rows, result.cols, extra
    raise AssociationError("unknown_method", f"{method!r}; choose from nn, greedy, ihgr, exact, jcbb, auto")


def choose_method(request: AssociationRequest, problem: Problem) -> str:
    """``auto``: JCBB when correlations are known and few measurements are gated, else the exact solver."""
    correlated = request.joint_cov is not None or (request.landmarks is not None and request.pose_cov is not None)
    gated_measurements = int(problem.gated.any(1).sum())
    return "jcbb" if correlated and gated_measurements <= request.auto_jcbb_max_measurements else "exact"


def query_cells(request: AssociationRequest, method: str) -> int:
    """The largest array ``method`` builds for ``request``, in cells: the M × N cost matrix, the (M + N)² matrix of
    the exact solver (exact, auto), JCBB's 4N² joint-covariance blocks and its (2M)² Cholesky factor on top (jcbb,
    auto), and the request's own ``joint_cov``. A service refuses a request above its limit before building
    anything."""
    m, n = request.size
    cells = m * n
    if method in ("exact", "auto"):
        cells = max(cells, (m + n) ** 2)
    if method in ("jcbb", "auto"):
        cells = max(cells, m * n + 4 * n * n + 4 * m * m)
    if request.joint_cov is not None:
        cells = max(cells, int(request.joint_cov.size))
    return cells


def associate(request: AssociationRequest, method: str = "auto", time_budget_s: float | None = None,
              clock: Callable[[], float] = time.perf_counter) -> AssociationReply:
    """Associate one scan by ``method`` (nn, greedy, ihgr, exact, jcbb or auto) and build the reply.

    With ``time_budget_s`` (seconds on ``clock``), a solve that runs out of time gives its best pairs so far
    (``truncated``), or AssociationError ``deadline`` when it has none.
    """
    started = time.perf_counter()
    budget = solvers.Budget(time_budget_s, clock)
    problem = build_problem(request)
    concrete = choose_method(request, problem) if method == "auto" else method
    try:
        if budget.spent():
            raise solvers.DeadlineExceeded(f"{time_budget_s:.3g} s spent building the problem")
        rows, cols, extra = solve(problem, concrete, request, budget)
    except solvers.DeadlineExceeded as exc:
        raise AssociationError("deadline", str(exc)) from None
    if budget.cut:
        extra["truncated"] = True
    m, n = problem.cost.shape
    assignment = np.full(m, CLUTTER, np.int64)
    assignment[rows] = cols
    unassigned = assignment == CLUTTER
    if request.new_feature_density > 0:
        far = np.all(problem.nis > problem.new_feature_gate, axis=1) if n else np.ones(m, bool)
        assignment[unassigned & far] = NEW
    missed = np.ones(n, bool)
    missed[cols] = False
    not_unique = extra.pop("not_unique", None)
    if not_unique is not None and not_unique.size:
        assignment[not_unique] = AMBIGUOUS
        kept = assignment[rows] >= 0
        rows, cols = rows[kept], cols[kept]
    cost = float(problem.cost[rows, cols].sum())
    if concrete == "ihgr":
        extra["gap"] = max(0.0, cost - extra["lp_objective"])
    return AssociationReply.model_construct(  # built here from checked arrays: no validation pass
        request_id=request.request_id, method=concrete, assignment=assignment, missed=missed, cost=cost,
        solve_time_ms=(time.perf_counter() - started) * 1e3, gated_pairs=int(problem.gated.sum()), **extra,
    )
