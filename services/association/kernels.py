"""Compiled (numba) kernel of joint compatibility branch and bound; :func:`services.association.solvers.solve_jcbb`
keeps the recursive numpy reference and calls this by default.

The same search as the reference (Neira and Tardós, "Data association in stochastic mapping using the joint
compatibility test"): measurements visited in the given order, candidates in the given order, a pairing
branch before the branch that leaves the measurement out, the joint NIS grown by the inverse Cholesky factor
of S_H one 2 × 2 Schur complement at a time, pruning by the χ² bound and by the number of pairings still
possible. The recursion becomes a loop over depth: the factor, the whitened innovation and the pairings of
the current branch live in arrays whose first 2k rows belong to the k pairings made so far, so a deeper
branch never disturbs its ancestors' rows. As the whole state lives in arrays (:class:`JcbbState`), the search
can stop after a slice of work and go on in the next call: the caller checks its time budget between slices
(numba reads no clock, and a budget on an injected clock is one tests control).
"""

from __future__ import annotations

import math

import numpy as np

from services.compiled import AVAILABLE, njit


@njit
def jcbb_candidates(gated, nis):
    """(table ``(M, C)``, counts ``(M,)``, order): each measurement's gated landmarks by increasing NIS (ties in
    landmark order), and the measurements with any candidate, fewest candidates first (ties in measurement
    order): the search order of :func:`services.association.solvers.solve_jcbb`."""
    m_count, l_count = gated.shape
    counts = np.zeros(m_count, np.int64)
    for m in range(m_count):
        for n in range(l_count):
            if gated[m, n]:
                counts[m] += 1
    table = np.zeros((m_count, max(1, counts.max()) if m_count else 1), np.int64)
    for m in range(m_count):
        chosen = np.empty(counts[m], np.int64)
        k = 0
        for n in range(l_count):
            if gated[m, n]:
                chosen[k] = n
                k += 1
        ranked = np.argsort(nis[m, chosen], kind="mergesort")
        for k in range(counts[m]):
            table[m, k] = chosen[ranked[k]]
    by_count = np.argsort(counts, kind="mergesort")
    order = np.empty(m_count, np.int64)
    kept = 0
    for m in by_count:
        if counts[m] > 0:
            order[kept] = m
            kept += 1
    return table, counts, order[:kept]


class JcbbState:
    """Where a paused search stands: the current branch (factor, whitened innovation, pairings, per-depth cursors)
    and the best pairings found so far. :func:`jcbb_search` takes it up again where it stopped."""

    def __init__(self, depth_count: int):
        size = 2 * depth_count
        self.lower = np.zeros((size, size))
        self.white = np.zeros(size)
        self.pair_m = np.zeros(depth_count, np.int64)
        self.pair_n = np.zeros(depth_count, np.int64)
        self.d2_at = np.zeros(depth_count + 1)
        self.k_at = np.zeros(depth_count + 1, np.int64)
        self.cursor = np.zeros(depth_count + 1, np.int64)
        self.skipped = np.zeros(depth_count + 1, np.bool_)
        self.best_m = np.zeros(depth_count, np.int64)
        self.best_n = np.zeros(depth_count, np.int64)
        self.counters = np.array([0, 0, 1, 0], np.int64)  # depth, best pairings, nodes, truncated
        self.best_d2 = np.array([np.inf])

    def arrays(self) -> tuple:
        return (self.lower, self.white, self.pair_m, self.pair_n, self.d2_at, self.k_at, self.cursor, self.skipped,
                self.best_m, self.best_n, self.counters, self.best_d2)

    def result(self) -> tuple:
        """(pair measurement indices, pair landmark indices, pairings, joint NIS, truncated, nodes) of the best so far."""
        count = int(self.counters[1])
        return (self.best_m[:count].copy(), self.best_n[:count].copy(), count, float(self.best_d2[0]),
                bool(self.counters[3]), int(self.counters[2]))


@njit
def jcbb_search(innovations, joint_blocks, noise, candidates, counts, order, bounds, max_nodes, lower, white, pair_m,
                pair_n, d2_at, k_at, cursor, skipped, best_m, best_n, counters, best_d2, work_limit):
    """Search from the state held in the arrays (a :class:`JcbbState`) until the tree is done or ``max_nodes`` are
    spent (True), or until ``work_limit`` units of work were done in this call (False; 0: no limit), the state then
    saved for the next call. A unit is one multiply-add of a candidate's test, so a slice takes about as long
    whatever the size of the branch: the caller checks its clock between slices."""
    depth_count = order.shape[0]
    scratch = np.empty((2 * depth_count, 2))  # b = L⁻¹ C_{H,n} of the candidate being tested
    depth, best_count, nodes, truncated = counters[0], counters[1], counters[2], counters[3] != 0
    best = best_d2[0]
    work = 0
    paused = False
    while depth >= 0:
        if work_limit > 0 and work >= work_limit:
            paused = True
            break
        k = k_at[depth]
        if depth == depth_count:
            if k > best_count or (k == best_count and d2_at[k] < best):
                best_count, best = k, d2_at[k]
                best_m[:k] = pair_m[:k]
                best_n[:k] = pair_n[:k]
            depth -= 1
            continue
        if skipped[depth]:
            depth -= 1
            continue
        m = order[depth]
        descended = False
        while cursor[depth] < counts[m]:
            if work_limit > 0 and work >= work_limit:
                paused = True
                break
            n = candidates[m, cursor[depth]]
            cursor[depth] += 1
            work += 8 * (k * k + k + 1)
            used = False
            for j in range(k):
                if pair_n[j] == n:
                    used = True
                    break
            if used:
                continue
            rows = 2 * k
            btb00, btb01, btb11, bw0, bw1 = 0.0, 0.0, 0.0, 0.0, 0.0
            for i in range(rows):  # b = L⁻¹ C_{H,n} (rows × 2), L⁻¹ lower triangular; bᵀ b and bᵀ w with it
                b0, b1 = 0.0, 0.0
                for j in range(i + 1):
                    b0 += lower[i, j] * joint_blocks[pair_n[j >> 1], n, j & 1, 0]
                    b1 += lower[i, j] * joint_blocks[pair_n[j >> 1], n, j & 1, 1]
                scratch[i, 0], scratch[i, 1] = b0, b1
                btb00, btb01, btb11 = btb00 + b0 * b0, btb01 + b0 * b1, btb11 + b1 * b1
                bw0, bw1 = bw0 + b0 * white[i], bw1 + b1 * white[i]
            schur00 = joint_blocks[n, n, 0, 0] + noise[0, 0] - btb00
            schur10 = joint_blocks[n, n, 1, 0] + noise[1, 0] - btb01
            schur11 = joint_blocks[n, n, 1, 1] + noise[1, 1] - btb11
            if schur00 <= 0.0:
                continue
            l11 = math.sqrt(schur00)
            l21 = schur10 / l11
            rest = schur11 - l21 * l21
            if rest <= 0.0:
                continue
            l22 = math.sqrt(rest)
            i00, i10, i11 = 1.0 / l11, -l21 / (l11 * l22), 1.0 / l22  # the inverse of [[l11, 0], [l21, l22]]
            r0, r1 = innovations[m, n, 0] - bw0, innovations[m, n, 1] - bw1
            u0, u1 = i00 * r0, i10 * r0 + i11 * r1
            d2_new = d2_at[k] + u0 * u0 + u1 * u1
            if d2_new > bounds[k]:
                continue
            for c in range(rows):  # the new rows of L⁻¹: −(inv · bᵀ) L⁻¹
                t0, t1 = 0.0, 0.0
                for i in range(c, rows):
                    t0 += i00 * scratch[i, 0] * lower[i, c]
                    t1 += (i10 * scratch[i, 0] + i11 * scratch[i, 1]) * lower[i, c]
                lower[rows, c], lower[rows + 1, c] = -t0, -t1
            lower[rows, rows], lower[rows, rows + 1] = i00, 0.0
            lower[rows + 1, rows], lower[rows + 1, rows + 1] = i10, i11
            white[rows], white[rows + 1] = u0, u1
            pair_m[k], pair_n[k] = m, n
            d2_at[k + 1] = d2_new
            depth += 1
            k_at[depth], cursor[depth], skipped[depth] = k + 1, 0, False
            nodes += 1
            if nodes > max_nodes:
                truncated = True
            descended = True
            break
        if paused or truncated:
            break
        if descended:
            continue
        skipped[depth] = True
        if k + depth_count - depth - 1 >= best_count:
            depth += 1
            k_at[depth], cursor[depth], skipped[depth] = k, 0, False
            nodes += 1
            if nodes > max_nodes:
                truncated = True
                break
            continue
        depth -= 1
    counters[0], counters[1], counters[2], counters[3] = depth, best_count, nodes, truncated
    best_d2[0] = best
    return not paused


@njit
def jcbb_whole_kernel(innovations, joint_blocks, noise, gated, nis, bounds, max_nodes):
    """(pair measurement indices, pair landmark indices, joint NIS, truncated, nodes): the candidates
    (:func:`jcbb_candidates`) and the whole search in one call, with no time budget (FastSLAM's shared association
    once per scan: a dozen small arrays and a call with twenty arguments cost as much as the search).
    ``bounds[k]`` is the χ² bound of k + 1 pairings, at least one per measurement. The search state is a
    :class:`JcbbState`'s arrays, made here: a compiled function cannot build the class."""
    table, counts, order = jcbb_candidates(gated, nis)
    depth_count = order.shape[0]
    size = 2 * depth_count
    best_m, best_n = np.zeros(depth_count, np.int64), np.zeros(depth_count, np.int64)
    counters, best_d2 = np.array([0, 0, 1 if depth_count else 0, 0], np.int64), np.array([np.inf])
    if depth_count:
        jcbb_search(innovations, joint_blocks, noise, table, counts, order, bounds, max_nodes, np.zeros((size, size)),
                    np.zeros(size), np.zeros(depth_count, np.int64), np.zeros(depth_count, np.int64),
                    np.zeros(depth_count + 1), np.zeros(depth_count + 1, np.int64), np.zeros(depth_count + 1, np.int64),
                    np.zeros(depth_count + 1, np.bool_), best_m, best_n, counters, best_d2, 0)
    count = counters[1]
    return best_m[:count].copy(), best_n[:count].copy(), best_d2[0] if count else 0.0, counters[3] != 0, counters[2]


def warm_up() -> None:
    """Compile (or load from the cache) the kernel on a tiny input (:func:`services.compiled.warm_up` times it)."""
    if AVAILABLE:
        jcbb_candidates(np.ones((1, 1), np.bool_), np.zeros((1, 1)))
        bounds = np.full(1, 9.0)
        bounds.flags.writeable = False  # as :func:`services.association.solvers.chi2_bounds` shares them
        jcbb_whole_kernel(np.zeros((1, 1, 2)), np.zeros((1, 1, 2, 2)), np.eye(2), np.ones((1, 1), np.bool_),
                          np.zeros((1, 1)), bounds, 100)
        state = JcbbState(1)  # the search in slices, as a query with a time budget runs it
        jcbb_search(np.zeros((1, 1, 2)), np.zeros((1, 1, 2, 2)), np.eye(2), np.zeros((1, 1), np.int64),
                    np.ones(1, np.int64), np.zeros(1, np.int64), np.full(1, 9.0), 100, *state.arrays(), 0)
