"""Compiled (numba) kernels of FastSLAM's per-scan work; the numpy functions they replace stay as the references.

With ids given or chosen once per scan (``known``, ``shared``), a scan's work is the same few operations on
every particle and every detected landmark; vectorised numpy pays its call overhead a dozen times per scan for
arrays of a few hundred 2 × 2 blocks, more than the arithmetic. Each kernel does one of them in a single pass:

- :func:`known_update`: every particle's EKF update of the scan's landmarks (Montemerlo et al., "FastSLAM: a
  factored solution to the simultaneous localization and mapping problem", one 2-D EKF per landmark and
  particle), with the innovation log-likelihood that weighs the particle
  (:func:`central.fastslam.landmarks.predict` then :func:`~central.fastslam.landmarks.update`);
- :func:`integrate_controls` (from :mod:`robots.kernels`, shared with MCL): the buffered controls as one
  Gaussian relative motion (:func:`robots.models.integrate_controls`, unicycle and Ackermann models);
- :func:`weighted_pose`: a robot's particle-weighted mean and covariance, with its pending motion
  (:meth:`central.fastslam.core.FastSlam.poses`);
- :func:`pose_belief_kernel`: the mean pose and covariance a scan is associated from, the pending motion composed
  onto the mean (:func:`central.fastslam.shared.pose_belief`);
- :func:`private_blocks`, :func:`select_kernel`: copy on write of the blocks of
  :class:`central.fastslam.aligned_map.AlignedMap`, and resampling of its tables' mixed columns with their
  reference counts (:meth:`~central.fastslam.aligned_map.AlignedMap.select`);
- :func:`create`: new landmarks where the scan's detections put them, in each particle's copy of their blocks
  (:func:`central.fastslam.association.create_known`);
- :func:`association_draw_kernel`: the particles the association's mixtures come from, drawn by weight, with
  their shares (:func:`central.fastslam.shared.association_draw_reference`: the systematic draw and its run count);
- :func:`marginal_map`: the landmarks' particle mixtures near the robot (:func:`central.fastslam.shared.marginal_map`),
  reading only the blocks of the candidates the map's spatial index gives (:func:`refile_kernel` files the slots
  of the blocks written otherwise, :func:`refile_slots_kernel` those the FastSLAM 2.0 step updated,
  :func:`near_kernel` lists the candidates of the grid cells within reach);
- :func:`shared_gating_kernel`, :func:`joint_blocks_kernel`: the predicted detections, Jacobians and gating
  distances of a scan against those mixtures (with the gates' verdicts), and the joint covariance JCBB
  searches with (:func:`central.fastslam.shared.associate`);
- :func:`drift_accumulate`, :func:`drift_condition`: a robot's drift grown by its motion and updated by its matches
  (:func:`central.fastslam.reacquire.accumulate`, :func:`~central.fastslam.reacquire.condition`);
- :func:`propose`: every particle's FastSLAM 2.0 step, its motion prior updated by the scan's matched detections,
  a draw from the result, then the matched landmarks' EKF updates from the drawn pose, one particle at a time
  (:func:`central.fastslam.proposal.propose` then :func:`central.fastslam.association.update_known`;
  :func:`proposal_moments` gives the moments alone, against
  :func:`central.fastslam.proposal.proposal_moments_reference`, for the tests: the warm-up leaves it out).
- :func:`negative_evidence_kernel`: the per-particle association's (``nn``, ``mht``) negative evidence, the visibility
  of every candidate in view that the scan left unassociated, the particles' miss weights and the landmarks aged or
  deleted (:func:`central.fastslam.evidence.negative_evidence_reference`);
- :func:`silence_kernel`: the shared association's views of confirmed landmarks, the silences they end and grow, and
  the landmarks silent past the null (:func:`central.fastslam.silence.silence_reference`).
- :func:`vote_kernel`: the Hough vote of a blind robot's re-acquisition, every turn's binned shifts and the scores
  of its best ones (:func:`central.fastslam.reacquire.vote_reference`, about 60 turns of a dozen numpy calls each).

Inside the loops nothing is allocated and no sub-array is copied by slice: numba pays for each (a block's slice
copy took a fifth of the FastSLAM 2.0 step at 1000 particles, the gating's per-landmark 2 × 2 arrays half its time).

The per-particle kernels (:func:`known_update`, :func:`propose`) also come as parallel ones
(:func:`known_update_parallel_kernel`, :func:`propose_parallel_kernel`): numba's ``prange`` over particles, on
``FastSlamConfig.workers`` threads; the serial kernels run with one worker and stay the references. Each particle's
arithmetic is the same in both and no sum runs across particles inside a parallel loop; the random normals are
drawn before the call and the free blocks of copy on write are handed out in particle order before the loop, so
the numbers, the blocks and the tables do not depend on the thread count.

Each has a thin wrapper that takes the Python objects; ``FastSlamConfig.compiled`` chooses kernels or references.
A robot's poses are a strided view of the (P, R, 3) particle poses when the filter holds several robots: the
wrappers hand the kernels a contiguous copy (P × 3 numbers), so each kernel is compiled for one array layout,
the one the warm-up compiles, and a fleet's first scan does not wait for the compiler.
"""

from __future__ import annotations

import math
import os

import numpy as np

from robots import kernels as robot_kernels
from robots.kernels import integrate_controls
from robots.gaussian import LOG_2PI
from services.compiled import AVAILABLE, HELPERS_DIGEST, ndtr, njit, renew_cache_if_stale, wrap_angle

if AVAILABLE:
    import numba

# GNU OpenMP, numba's threading layer here, has its idle threads spin between parallel loops by default. A scan calls
# one kernel between milliseconds of Python, and on a machine whose cores are busy with other processes the spinning
# thread took their time and made 2 workers 5-14 times slower per scan than 1 (MR.CLAM, 300 and 1000 particles);
# passive threads sleep until the next loop. Read by libgomp when numba starts its threads, at the first parallel call.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def njit_parallel(function):
    """:func:`services.compiled.njit` with ``parallel=True``: the kernel's ``prange`` loops run on numba's threads (as
    many as :func:`use_threads` last set in the calling thread), cached on disk too. Without numba it runs as it is
    (``prange`` is then ``range``). Declared here, not in :mod:`services.compiled`: an edit there renews every
    kernel's cache."""
    if not AVAILABLE:
        return function
    dispatcher = numba.njit(cache=True, nogil=True, parallel=True)(function)
    renew_cache_if_stale(dispatcher, HELPERS_DIGEST)
    return dispatcher


prange = numba.prange if AVAILABLE else range


def max_threads() -> int:
    """The threads the parallel kernels can use at most: numba's pool, ``NUMBA_NUM_THREADS`` (the machine's cores
    unless set); 1 without numba."""
    return int(numba.config.NUMBA_NUM_THREADS) if AVAILABLE else 1


def use_threads(workers: int) -> int:
    """Let the parallel kernels called from this thread use ``workers`` threads, capped at :func:`max_threads`
    (numba keeps the count per calling thread, so the wrappers set it before each parallel call); the count set."""
    count = max(1, min(int(workers), max_threads()))
    if AVAILABLE:
        numba.set_num_threads(count)
    return count


@njit
def _places(slots, block):
    """(block, offset in the block) ``(m, 2)`` of each slot: divided once per scan, not once per particle."""
    places = np.empty((slots.shape[0], 2), np.int64)
    for j in range(slots.shape[0]):
        places[j, 0], places[j, 1] = slots[j] // block, slots[j] % block
    return places


@njit
def _particle_update(pool_mean, pool_cov, table, p, pose, a, b, places, z, r, log_likelihood, weigh):
    """EKF update of particle ``p``'s landmarks at ``places[j]`` (:func:`_places`) by detections ``z[j]`` seen from
    its ``pose`` (3,), in place in its (private) blocks; with ``weigh``, ``log_likelihood[j]`` gets log N(ν; 0, S),
    S = H Σ Hᵀ + R (the FastSLAM 2.0 step weighs by its proposal instead, and skips the logarithms)."""
    theta = pose[2]
    c, s = math.cos(theta), math.sin(theta)
    px = pose[0] + a * c - b * s
    py = pose[1] + a * s + b * c
    r00, r01, r10, r11 = r[0, 0], r[0, 1], r[1, 0], r[1, 1]  # read once: the stores below may alias any array
    for j in range(places.shape[0]):
        mean = pool_mean[table[p, places[j, 0]]]
        cov = pool_cov[table[p, places[j, 0]]]
        k = places[j, 1]
        dx, dy = mean[k, 0] - px, mean[k, 1] - py
        q = dx * dx + dy * dy
        distance = math.sqrt(q)
        q = max(q, 1e-18)
        rs = max(distance, 1e-9)
        h00, h01, h10, h11 = dx / rs, dy / rs, -dy / q, dx / q
        m00, m01, m10, m11 = cov[k, 0, 0], cov[k, 0, 1], cov[k, 1, 0], cov[k, 1, 1]
        t00, t01 = h00 * m00 + h01 * m01, h00 * m01 + h01 * m11
        t10, t11 = h10 * m00 + h11 * m01, h10 * m01 + h11 * m11
        cross = t00 * h10 + t01 * h11
        s00 = t00 * h00 + t01 * h01 + r00
        s01 = cross + r01
        s10 = cross + r10
        s11 = t10 * h10 + t11 * h11 + r11
        det = s00 * s11 - s01 * s10
        safe = det if abs(det) > 1e-300 else 1e-300
        i00, i01, i10, i11 = s11 / safe, -s01 / safe, -s10 / safe, s00 / safe
        n0 = z[j, 0] - distance
        n1 = wrap_angle(z[j, 1] - wrap_angle(math.atan2(dy, dx) - theta))
        u00, u01 = m00 * h00 + m01 * h01, m00 * h10 + m01 * h11  # Σ Hᵀ
        u10, u11 = m10 * h00 + m11 * h01, m10 * h10 + m11 * h11
        g00, g01 = u00 * i00 + u01 * i10, u00 * i01 + u01 * i11  # K = Σ Hᵀ S⁻¹
        g10, g11 = u10 * i00 + u11 * i10, u10 * i01 + u11 * i11
        mean[k, 0] += g00 * n0 + g01 * n1
        mean[k, 1] += g10 * n0 + g11 * n1
        v00, v01 = g00 * s00 + g01 * s01, g00 * s01 + g01 * s11  # K S Kᵀ (S symmetric)
        v10, v11 = g10 * s00 + g11 * s01, g10 * s01 + g11 * s11
        shared = v00 * g10 + v01 * g11
        cov[k, 0, 0] = m00 - (v00 * g00 + v01 * g01)
        cov[k, 0, 1] = m01 - shared
        cov[k, 1, 0] = m10 - shared
        cov[k, 1, 1] = m11 - (v10 * g10 + v11 * g11)
        if weigh:
            d2 = i00 * n0 * n0 + (i01 + i10) * n0 * n1 + i11 * n1 * n1
            log_likelihood[j] = -0.5 * d2 - 0.5 * math.log(max(det, 1e-300)) - LOG_2PI


@njit
def _count_hits(exist, hits, slots, exist_hit, exist_max):
    """Hit counts and existence scores of the updated ``slots`` (per slot, the same in every particle)."""
    for j in range(slots.shape[0]):
        exist[slots[j]] = min(exist[slots[j]] + exist_hit, exist_max)
        hits[slots[j]] += 1


@njit
def known_update_kernel(pool_mean, pool_cov, table, block, exist, hits, pose, a, b, slots, z, r, exist_hit,
                        exist_max, log_likelihood):
    """EKF update of landmark ``slots[j]`` by detection ``z[j]`` in every particle (in place, in the blocks the
    particles' ``table`` names: they must be private, :meth:`AlignedMap.private`); ``log_likelihood`` ``(P, m)``
    gets log N(ν; 0, S), S = H Σ Hᵀ + R, with H the Jacobian at the prior landmark estimate; (a, b) is the
    sensor's offset on the robot. Hit counts and existence scores are per slot, counted once."""
    places = _places(slots, block)
    for p in range(pose.shape[0]):
        _particle_update(pool_mean, pool_cov, table, p, pose[p], a, b, places, z, r, log_likelihood[p], True)
    _count_hits(exist, hits, slots, exist_hit, exist_max)


@njit_parallel
def known_update_parallel_kernel(pool_mean, pool_cov, table, block, exist, hits, pose, a, b, slots, z, r, exist_hit,
                                 exist_max, log_likelihood):
    """:func:`known_update_kernel` with the particles spread over numba's threads: each particle writes only its
    own (private) blocks and its row of ``log_likelihood``, so any thread count gives the same numbers."""
    places = _places(slots, block)
    for p in prange(pose.shape[0]):
        _particle_update(pool_mean, pool_cov, table, p, pose[p], a, b, places, z, r, log_likelihood[p], True)
    _count_hits(exist, hits, slots, exist_hit, exist_max)


def known_update(landmarks, sensor, pose: np.ndarray, slots: np.ndarray, z: np.ndarray, r: np.ndarray,
                 exist_hit: float, exist_max: float, workers: int = 1) -> np.ndarray:
    """Update landmarks ``slots`` ``(m,)`` (distinct) of every particle of an :class:`AlignedMap` by detections ``z``
    ``(m, 2)`` seen from ``pose`` ``(P, 3)``; returns log N(ν; 0, S) ``(P, m)``. ``workers`` > 1: the parallel kernel
    on that many threads (the same numbers)."""
    landmarks.private(slots)
    out = np.empty((pose.shape[0], slots.shape[0]))
    kernel = known_update_kernel
    if workers > 1:
        use_threads(workers)
        kernel = known_update_parallel_kernel
    kernel(landmarks.pool_mean, landmarks.pool_cov, landmarks.table, landmarks.block, landmarks.exist,
           landmarks.hits, np.ascontiguousarray(pose), sensor.offset[0], sensor.offset[1], slots, z, r, exist_hit,
           exist_max, out)
    return out


@njit
def _flat_pools(pool_mean, pool_cov):
    """The pools as one row per block, ``(blocks, block · 2)`` and ``(blocks, block · 4)``: views, for
    :func:`_copy_block`. Taken once per kernel call: a reshape per copy cost as much as the copy."""
    return (pool_mean.reshape(pool_mean.shape[0], pool_mean.shape[1] * 2),
            pool_cov.reshape(pool_cov.shape[0], pool_cov.shape[1] * 4))


@njit
def _private_particle(table, p, blocks, refs, flat_mean, flat_cov, free_blocks, free_count):
    """Copy on write for particle ``p``: each of its blocks in ``blocks`` that other particles share (or that is not
    written yet) becomes a block of its own, taken from ``free_blocks``. The last holder of a shared block keeps it.
    ``flat_mean``, ``flat_cov``: the pools as rows (:func:`_flat_pools`)."""
    for b in blocks:
        phys = table[p, b]
        if phys >= 0 and refs[phys] == 1:
            continue
        free_count[0] -= 1
        fresh = free_blocks[free_count[0]]
        _copy_block(flat_mean, flat_cov, phys, fresh)
        if phys >= 0:
            refs[phys] -= 1
        refs[fresh] = 1
        table[p, b] = fresh


@njit
def _claim_blocks(table, p, blocks, refs, free_blocks, free_count, source, target):
    """The bookkeeping of :func:`_private_particle` without the copy: particle ``p``'s table, the reference counts and
    the free list change as there, and ``target[i]`` gets the fresh block taken for ``blocks[i]`` (−1: none taken,
    the particle's own block already) and ``source[i]`` the block to copy into it (−1: zeros). Run in particle order
    before a parallel loop copies (:func:`_copy_claimed`), so the blocks handed out do not depend on the threads."""
    for i in range(blocks.shape[0]):
        b = blocks[i]
        phys = table[p, b]
        target[i] = -1
        if phys >= 0 and refs[phys] == 1:
            continue
        free_count[0] -= 1
        fresh = free_blocks[free_count[0]]
        source[i], target[i] = phys, fresh
        if phys >= 0:
            refs[phys] -= 1
        refs[fresh] = 1
        table[p, b] = fresh


@njit
def _copy_claimed(flat_mean, flat_cov, source, target):
    """The copies :func:`_claim_blocks` listed for one particle (rows of the flat pools, :func:`_flat_pools`)."""
    for i in range(target.shape[0]):
        if target[i] >= 0:
            _copy_block(flat_mean, flat_cov, source[i], target[i])


@njit
def _copy_block(flat_mean, flat_cov, source, target):
    """Row ``target`` of the flat pools (:func:`_flat_pools`) becomes a copy of row ``source`` (zeros when
    ``source`` is −1). numba's slice assignment of a (block, 2, 2) sub-array took a fifth of the FastSLAM 2.0 step
    with 1000 particles on Victoria Park; an element loop over the three indices of the pools, 2–3 times what a
    loop over a flat row takes."""
    if source < 0:
        for k in range(flat_mean.shape[1]):
            flat_mean[target, k] = 0.0
        for k in range(flat_cov.shape[1]):
            flat_cov[target, k] = 0.0
        return
    for k in range(flat_mean.shape[1]):
        flat_mean[target, k] = flat_mean[source, k]
    for k in range(flat_cov.shape[1]):
        flat_cov[target, k] = flat_cov[source, k]


@njit
def private_blocks(table, blocks, refs, pool_mean, pool_cov, free_blocks, free_count):
    """Copy on write: each particle's block ``b`` in ``blocks`` that other particles share (or that is not written
    yet) becomes a block of its own, taken from ``free_blocks`` (enough must be free)."""
    flat_mean, flat_cov = _flat_pools(pool_mean, pool_cov)
    for p in range(table.shape[0]):
        _private_particle(table, p, blocks, refs, flat_mean, flat_cov, free_blocks, free_count)


@njit
def select_kernel(table, mixed, index, refs, free_blocks, free_count):
    """Resampling of the tables' ``mixed`` columns: row p becomes row ``index[p]``; reference counts follow, and
    the blocks no particle holds any more go to ``free_blocks``. Returns which of the columns are now the same in
    every row."""
    particles = table.shape[0]
    old = np.empty(particles, table.dtype)
    uniform = np.ones(mixed.shape[0], np.bool_)
    for c in range(mixed.shape[0]):
        column = mixed[c]
        for p in range(particles):
            old[p] = table[p, column]
        for p in range(particles):
            held = old[index[p]]
            table[p, column] = held
            if held >= 0:
                refs[held] += 1
            if held != old[index[0]]:
                uniform[c] = False
        for p in range(particles):  # the new holders are counted first: a block reaches 0 once, when freed
            held = old[p]
            if held >= 0:
                refs[held] -= 1
                if refs[held] == 0:
                    free_blocks[free_count[0]] = held
                    free_count[0] += 1
    return uniform


@njit
def weighted_pose_kernel(pose, w, delta, delta_cov, moved):
    """(mean, covariance) of poses ``(P, 3)`` under weights ``w``; with ``moved``, of every pose ⊕ ``delta``, the
    covariance plus the weighted J_p Σ_Δ J_pᵀ (J_p: the composition's Jacobian in the increment). Sums are kept in
    local scalars, in particle order."""
    count = pose.shape[0]
    moved_pose = np.empty((count, 3))
    e00, e01, e02, e10, e11, e12, e20, e21, e22 = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    q00, q01, q02 = delta_cov[0, 0], delta_cov[0, 1], delta_cov[0, 2]
    q10, q11, q12 = delta_cov[1, 0], delta_cov[1, 1], delta_cov[1, 2]
    q20, q21, q22 = delta_cov[2, 0], delta_cov[2, 1], delta_cov[2, 2]
    dx, dy, dtheta = delta[0], delta[1], delta[2]
    sum_sin, sum_cos, mean_x, mean_y = 0.0, 0.0, 0.0, 0.0
    for p in range(count):
        x, y, theta = pose[p, 0], pose[p, 1], pose[p, 2]
        wp = w[p]
        if moved:
            c, s = math.cos(theta), math.sin(theta)  # J = [[c, −s, 0], [s, c, 0], [0, 0, 1]]
            a00, a01, a02 = c * q00 - s * q10, c * q01 - s * q11, c * q02 - s * q12  # rows of J Σ
            a10, a11, a12 = s * q00 + c * q10, s * q01 + c * q11, s * q02 + c * q12
            e00 += wp * (a00 * c - a01 * s)
            e01 += wp * (a00 * s + a01 * c)
            e02 += wp * a02
            e10 += wp * (a10 * c - a11 * s)
            e11 += wp * (a10 * s + a11 * c)
            e12 += wp * a12
            e20 += wp * (q20 * c - q21 * s)
            e21 += wp * (q20 * s + q21 * c)
            e22 += wp * q22
            x, y, theta = x + c * dx - s * dy, y + s * dx + c * dy, wrap_angle(theta + dtheta)
        moved_pose[p, 0], moved_pose[p, 1], moved_pose[p, 2] = x, y, theta
        sum_sin += wp * math.sin(theta)
        sum_cos += wp * math.cos(theta)
        mean_x += wp * x
        mean_y += wp * y
    mean = np.array([mean_x, mean_y, math.atan2(sum_sin, sum_cos)])
    mean_theta = mean[2]
    v00, v01, v02, v11, v12, v22 = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    for p in range(count):
        d0, d1 = moved_pose[p, 0] - mean_x, moved_pose[p, 1] - mean_y
        d2 = wrap_angle(moved_pose[p, 2] - mean_theta)
        wp = w[p]
        v00 += wp * d0 * d0
        v01 += wp * d0 * d1
        v02 += wp * d0 * d2
        v11 += wp * d1 * d1
        v12 += wp * d1 * d2
        v22 += wp * d2 * d2
    cov = np.array([[v00 + e00, v01 + e01, v02 + e02], [v01 + e10, v11 + e11, v12 + e12],
                    [v02 + e20, v12 + e21, v22 + e22]])
    return mean, 0.5 * (cov + cov.T)


@njit
def pose_belief_kernel(pose, w, delta, delta_cov, moved):
    """(mean, covariance) of poses ``(P, 3)`` under weights ``w``; with ``moved``, the mean then composed with
    ``delta`` and the covariance plus J Σ_Δ Jᵀ, J the composition's Jacobian in the increment at the mean's heading
    (the belief :func:`central.fastslam.shared.pose_belief` associates from: the mean moved, not every particle)."""
    mean, cov = weighted_pose_kernel(pose, w, delta, delta_cov, False)
    if not moved:
        return mean, cov
    c, s = math.cos(mean[2]), math.sin(mean[2])
    jac = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    out = np.array([mean[0] + c * delta[0] - s * delta[1], mean[1] + s * delta[0] + c * delta[1],
                    wrap_angle(mean[2] + delta[2])])
    for i in range(3):
        for j in range(3):
            total = 0.0
            for k in range(3):
                for l in range(3):
                    total += jac[i, k] * delta_cov[k, l] * jac[j, l]
            cov[i, j] += total
    return out, cov


def weighted_pose(pose: np.ndarray, w: np.ndarray, pending: tuple[np.ndarray, np.ndarray] | None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(mean, covariance) of one robot's particles ``(P, 3)``, its ``pending`` motion (Δ̄, Σ_Δ) applied if any."""
    moved = pending is not None
    delta, delta_cov = pending if moved else (np.zeros(3), np.zeros((3, 3)))
    return weighted_pose_kernel(np.ascontiguousarray(pose), w, delta, delta_cov, moved)


@njit
def _cell_bucket(cx, cy, mask):
    """The hash bucket of grid cell (cx, cy) in a table of ``mask + 1`` buckets."""
    return ((cx * 73856093) ^ (cy * 19349663)) & mask


@njit
def _file_slot(slot, low_x, low_y, high_x, high_y, valid, cell, filed_state, filed_cell, bucket, following):
    """File ``slot`` under the box [low, high] of its particles' means: the grid cell of the box's centre (its
    anchor, ``IN_CELL`` = 1) unless half the box's diagonal (its spread) exceeds ``cell`` (``WIDE`` = 2); an
    invalid slot is unfiled (0). Returns (whether it entered or left ``WIDE``, its state)."""
    mask = bucket.shape[0] - 1
    state = 0
    cx, cy = 0, 0
    if valid[slot]:  # a valid slot was written in every particle
        ax, ay = 0.5 * (low_x + high_x), 0.5 * (low_y + high_y)  # the anchor: the box's centre
        half_x, half_y = 0.5 * (high_x - low_x), 0.5 * (high_y - low_y)
        state = 2 if half_x * half_x + half_y * half_y > cell * cell else 1  # spread: half the box's diagonal
        cx, cy = int(math.floor(ax / cell)), int(math.floor(ay / cell))
    old = filed_state[slot]
    if state == old and (state != 1 or (cx == filed_cell[slot, 0] and cy == filed_cell[slot, 1])):
        return False, state
    if old == 1:  # unlink from its cell's list
        h = _cell_bucket(filed_cell[slot, 0], filed_cell[slot, 1], mask)
        previous, current = -1, bucket[h]
        while current != slot:
            previous, current = current, following[current]
        if previous < 0:
            bucket[h] = following[slot]
        else:
            following[previous] = following[slot]
    if state == 1:
        h = _cell_bucket(cx, cy, mask)
        following[slot] = bucket[h]
        bucket[h] = slot
        filed_cell[slot, 0], filed_cell[slot, 1] = cx, cy
    filed_state[slot] = state
    return old == 2 or state == 2, state


@njit
def refile_kernel(table, pool_mean, valid, blocks, block, cell, filed_state, filed_cell, bucket, following):
    """File again the slots of ``blocks`` in the map's spatial index, a hashed grid (:meth:`AlignedMap.near`), each
    under the box holding every particle's mean (:func:`_file_slot`). A cell's slots are a list threaded through
    ``following`` from ``bucket`` (cells sharing a bucket share the list; ``filed_cell`` tells them apart).
    Returns (slots, states) of the slots that entered or left ``WIDE``."""
    particles = table.shape[0]
    wide_slots = np.empty(blocks.shape[0] * block, np.int64)
    wide_states = np.empty(blocks.shape[0] * block, np.int8)
    wide = 0
    low = np.empty((block, 2))
    high = np.empty((block, 2))
    for b in blocks:
        for k in range(block):
            low[k, 0], low[k, 1], high[k, 0], high[k, 1] = np.inf, np.inf, -np.inf, -np.inf
        for p in range(particles):  # the box of every particle's mean, slot by slot (a block is contiguous)
            phys = table[p, b]
            if phys < 0:
                continue
            for k in range(block):
                for axis in range(2):
                    value = pool_mean[phys, k, axis]
                    low[k, axis] = min(low[k, axis], value)
                    high[k, axis] = max(high[k, axis], value)
        for k in range(block):
            slot = b * block + k
            changed, state = _file_slot(slot, low[k, 0], low[k, 1], high[k, 0], high[k, 1], valid, cell, filed_state,
                                        filed_cell, bucket, following)
            if changed:
                wide_slots[wide], wide_states[wide] = slot, state
                wide += 1
    return wide_slots[:wide], wide_states[:wide]


@njit
def refile_slots_kernel(slots, box, valid, cell, filed_state, filed_cell, bucket, following):
    """File again ``slots`` under their boxes ``box`` ``(m, 4)`` (low x, low y, high x, high y of every particle's
    mean, as :func:`propose_kernel` leaves them), as :func:`refile_kernel` would from the blocks."""
    wide_slots = np.empty(slots.shape[0], np.int64)
    wide_states = np.empty(slots.shape[0], np.int8)
    wide = 0
    for j in range(slots.shape[0]):
        changed, state = _file_slot(slots[j], box[j, 0], box[j, 1], box[j, 2], box[j, 3], valid, cell, filed_state,
                                    filed_cell, bucket, following)
        if changed:
            wide_slots[wide], wide_states[wide] = slots[j], state
            wide += 1
    return wide_slots[:wide], wide_states[:wide]


@njit
def grid_candidates_kernel(low_x, low_y, high_x, high_y, bucket, following, filed_state, filed_cell, valid, cell,
                           point, reach):
    """The valid slots filed in the grid cells [low_x, high_x] × [low_y, high_y] of :func:`refile_kernel`'s index
    that come within ``reach`` of ``point`` (cells of side ``cell``; the corners of the square hold no more)."""
    mask = bucket.shape[0] - 1
    out = np.empty(0, np.int64)
    for rounds in range(2):  # count, then fill
        found = 0
        for cx in range(low_x, high_x + 1):
            gap_x = max(cx * cell - point[0], 0.0, point[0] - (cx + 1) * cell)
            for cy in range(low_y, high_y + 1):
                gap_y = max(cy * cell - point[1], 0.0, point[1] - (cy + 1) * cell)
                if gap_x * gap_x + gap_y * gap_y > reach * reach:
                    continue
                slot = bucket[_cell_bucket(cx, cy, mask)]
                while slot >= 0:
                    if filed_state[slot] == 1 and filed_cell[slot, 0] == cx and filed_cell[slot, 1] == cy and valid[slot]:
                        if rounds == 1:
                            out[found] = slot
                        found += 1
                    slot = following[slot]
        if rounds == 0:
            out = np.empty(found, np.int64)
    return out


@njit
def near_kernel(point, radius, cell, bucket, following, filed_state, filed_cell, valid, wide, serial):
    """:meth:`AlignedMap.near` in one call: the valid slots filed in the grid cells within ``radius`` + ``cell`` of
    ``point`` (:func:`grid_candidates_kernel`), and the valid ones of ``wide``, in the order of their ``serial``."""
    low_x, low_y = math.floor((point[0] - radius - cell) / cell), math.floor((point[1] - radius - cell) / cell)
    high_x, high_y = math.floor((point[0] + radius + cell) / cell), math.floor((point[1] + radius + cell) / cell)
    filed = grid_candidates_kernel(int(low_x), int(low_y), int(high_x), int(high_y), bucket, following, filed_state,
                                   filed_cell, valid, cell, point, radius + cell)
    slots = np.empty(filed.shape[0] + wide.shape[0], np.int64)
    slots[:filed.shape[0]] = filed
    count = filed.shape[0]
    for slot in wide:
        if valid[slot]:
            slots[count] = slot
            count += 1
    slots = slots[:count]
    return slots[np.argsort(serial[slots], kind="mergesort")]


@njit
def association_draw_kernel(w, total, count, offset):
    """(distinct rows ``(k,)``, their shares ``(k,)``) of ``count`` systematic draws by weight ``w`` (summed to
    ``total`` by the caller, as numpy sums) at the fixed ``offset``: the same rows and shares as
    :func:`robots.gaussian.systematic_resample` (its cumulative sum, last entry 1, and right-sided search) followed
    by the run count of the sorted draw, in one pass over the weights instead of half a dozen numpy calls."""
    size = w.shape[0]
    rows = np.empty(count, np.int64)
    shares = np.empty(count)
    kept, row, cdf = 0, 0, w[0] / total
    if size == 1:
        cdf = 1.0
    run = 0
    for i in range(count):
        point = (offset + i) / count
        while row < size - 1 and cdf <= point:
            row += 1
            cdf = 1.0 if row == size - 1 else cdf + w[row] / total
        if run > 0 and rows[kept - 1] == row:
            run += 1
            continue
        if run > 0:
            shares[kept - 1] = run / count
        rows[kept] = row
        kept += 1
        run = 1
    if run > 0:
        shares[kept - 1] = run / count
    return rows[:kept], shares[:kept]


@njit
def _block_weights(w, table, rows, blocks, position):
    """For each block ``blocks[b]``: the distinct physical blocks the particles ``rows`` hold there
    (``phys[b, :count[b]]``, in order of first holder) and the summed weight ``w`` of the rows holding each
    (``weight[b, :count[b]]``). ``position`` (one entry per physical block, all −1) is scratch, left all −1."""
    particles = rows.shape[0]
    phys = np.empty((blocks.shape[0], particles), np.int64)
    weight = np.zeros((blocks.shape[0], particles))
    count = np.zeros(blocks.shape[0], np.int64)
    for b in range(blocks.shape[0]):
        for p in range(particles):
            held = table[rows[p], blocks[b]]
            j = position[held]
            if j < 0:
                j = count[b]
                count[b] += 1
                position[held] = j
                phys[b, j] = held
            weight[b, j] += w[p]
        for j in range(count[b]):
            position[phys[b, j]] = -1
    return phys, weight, count


@njit
def marginal_map_kernel(w, pool_mean, pool_cov, table, rows, block, slots, point, radius, position):
    """(kept rows of ``slots``, means ``(k, 2)``, covariances ``(k, 2, 2)``): the mixture over particles ``rows``
    (weights ``w``) of each landmark slot whose weighted mean lies within ``radius`` of ``point`` (the weighted
    covariances plus the spread of the means). Particles sharing a block share its Gaussians: each distinct block
    is read, with the summed weight of its holders, so the cost follows the blocks of ``slots``, not
    particles × landmarks, nor the size of the map; each slot sums its holders in the order of their first
    holder, in local scalars. ``position`` is :func:`_block_weights`' scratch."""
    count = slots.shape[0]
    blocks = np.unique(slots // block)
    local = np.searchsorted(blocks, slots // block)
    order = np.argsort(local, kind="mergesort")  # the slots block by block: start[b]..start[b + 1] in ``order``
    start = np.searchsorted(local[order], np.arange(blocks.shape[0] + 1))
    offset = np.empty(count, np.int64)  # each slot's place in its block, in ``order``: divided once, not per holder
    for n in range(count):
        offset[n] = slots[order[n]] % block
    phys, weight, holders = _block_weights(w, table, rows, blocks, position)
    means = np.empty((count, 2))
    for b in range(blocks.shape[0]):  # slot by slot, its holders summed in local scalars
        for n in range(start[b], start[b + 1]):
            k, m0, m1 = offset[n], 0.0, 0.0
            for j in range(holders[b]):
                wj, held = weight[b, j], phys[b, j]
                m0 += wj * pool_mean[held, k, 0]
                m1 += wj * pool_mean[held, k, 1]
            means[order[n], 0], means[order[n], 1] = m0, m1
    row_of = np.full(count, -1, np.int64)  # the output row of each kept slot, −1 for the others
    kept = 0
    for i in range(count):
        if math.hypot(means[i, 0] - point[0], means[i, 1] - point[1]) < radius:
            row_of[i] = kept
            kept += 1
    keep = np.flatnonzero(row_of >= 0)
    out_mean = np.empty((kept, 2))
    out_cov = np.empty((kept, 2, 2))
    for n in range(kept):
        out_mean[n, 0], out_mean[n, 1] = means[keep[n], 0], means[keep[n], 1]
    kept_start = np.zeros(blocks.shape[0] + 1, np.int64)  # the kept slots block by block, in ``order``
    kept_row, kept_offset = np.empty(kept, np.int64), np.empty(kept, np.int64)
    for b in range(blocks.shape[0]):
        kept_start[b + 1] = kept_start[b]
        for q in range(start[b], start[b + 1]):
            if row_of[order[q]] >= 0:
                kept_row[kept_start[b + 1]], kept_offset[kept_start[b + 1]] = row_of[order[q]], offset[q]
                kept_start[b + 1] += 1
    for b in range(blocks.shape[0]):
        for q in range(kept_start[b], kept_start[b + 1]):
            n, k = kept_row[q], kept_offset[q]
            mean0, mean1 = out_mean[n, 0], out_mean[n, 1]
            v00, v01, v10, v11 = 0.0, 0.0, 0.0, 0.0
            for j in range(holders[b]):
                wj, held = weight[b, j], phys[b, j]
                r0, r1 = pool_mean[held, k, 0] - mean0, pool_mean[held, k, 1] - mean1
                v00 += wj * (pool_cov[held, k, 0, 0] + r0 * r0)
                v01 += wj * (pool_cov[held, k, 0, 1] + r0 * r1)
                v10 += wj * (pool_cov[held, k, 1, 0] + r0 * r1)
                v11 += wj * (pool_cov[held, k, 1, 1] + r1 * r1)
            out_cov[n, 0, 0], out_cov[n, 0, 1], out_cov[n, 1, 0], out_cov[n, 1, 1] = v00, v01, v10, v11
    return keep, out_mean, out_cov


def marginal_map(landmarks, w: np.ndarray, slots: np.ndarray, point: np.ndarray, radius: float,
                 rows: np.ndarray | None = None) -> tuple:
    """:func:`marginal_map_kernel` on an :class:`AlignedMap`: over every particle, or over particles ``rows`` with
    weights ``w`` (one per row)."""
    rows = np.arange(landmarks.particles) if rows is None else np.asarray(rows, np.int64)
    return marginal_map_kernel(w, landmarks.pool_mean, landmarks.pool_cov, landmarks.table, rows, landmarks.block,
                               np.asarray(slots, np.int64), point, radius, landmarks.scratch_positions())


@njit
def _sandwich3(h, k, m, out):
    """``out`` ``(2, 2)`` = H_k M H_kᵀ for the 2 × 3 block ``h[k]`` and a 3 × 3 ``m``."""
    for i in range(2):
        t0 = h[k, i, 0] * m[0, 0] + h[k, i, 1] * m[1, 0] + h[k, i, 2] * m[2, 0]
        t1 = h[k, i, 0] * m[0, 1] + h[k, i, 1] * m[1, 1] + h[k, i, 2] * m[2, 1]
        t2 = h[k, i, 0] * m[0, 2] + h[k, i, 1] * m[1, 2] + h[k, i, 2] * m[2, 2]
        for j in range(2):
            out[i, j] = t0 * h[k, j, 0] + t1 * h[k, j, 1] + t2 * h[k, j, 2]


@njit
def shared_gating_kernel(pose, a, b, mean, cov, tentative, spread, drift, r, z, gate, new_gate, view):
    """(ẑ ``(K, 2)``, H_x ``(K, 2, 3)``, H_m Σ H_mᵀ ``(K, 2, 2)``, ν ``(m, K, 2)``, d² ``(m, K)``, gated
    ``(m, K)``, fresh ``(m,)``, tentative in view ``(K,)``) of detections ``z`` against landmarks (``mean``,
    ``cov``) seen from the robot's mean ``pose``: S = H_m Σ H_mᵀ + H_x P H_xᵀ + R, plus H_x D H_xᵀ (drift)
    for the confirmed ones; (a, b) is the sensor's offset. Gated: d² < ``gate``; fresh: every d² >
    ``new_gate``; in view: ẑ within ``view`` = (min range, max range, half the field of view)."""
    count = mean.shape[0]
    theta = pose[2]
    c, s = math.cos(theta), math.sin(theta)
    px, py = pose[0] + a * c - b * s, pose[1] + a * s + b * c
    d_theta0, d_theta1 = -a * s - b * c, a * c - b * s
    zhat = np.empty((count, 2))
    h_x = np.empty((count, 2, 3))
    own = np.empty((count, 2, 2))
    s_inv = np.empty((count, 2, 2))
    pose_part, drift_part, total = np.empty((2, 2)), np.empty((2, 2)), np.empty((2, 2))
    for k in range(count):
        dx, dy = mean[k, 0] - px, mean[k, 1] - py
        zhat[k, 0] = math.hypot(dx, dy)
        zhat[k, 1] = wrap_angle(math.atan2(dy, dx) - theta)
        q = max(dx * dx + dy * dy, 1e-18)
        distance = math.sqrt(q)
        h00, h01, h10, h11 = dx / distance, dy / distance, -dy / q, dx / q
        h_x[k, 0, 0], h_x[k, 0, 1], h_x[k, 1, 0], h_x[k, 1, 1] = -h00, -h01, -h10, -h11
        h_x[k, 0, 2] = -(h00 * d_theta0 + h01 * d_theta1)
        h_x[k, 1, 2] = -(h10 * d_theta0 + h11 * d_theta1) - 1.0
        m00, m01, m11 = cov[k, 0, 0], cov[k, 0, 1], cov[k, 1, 1]
        t00, t01 = h00 * m00 + h01 * m01, h00 * m01 + h01 * m11
        t10, t11 = h10 * m00 + h11 * m01, h10 * m01 + h11 * m11
        own[k, 0, 0] = t00 * h00 + t01 * h01
        own[k, 0, 1] = own[k, 1, 0] = t00 * h10 + t01 * h11
        own[k, 1, 1] = t10 * h10 + t11 * h11
        _sandwich3(h_x, k, spread, pose_part)
        for i in range(2):
            for j in range(2):
                total[i, j] = own[k, i, j] + pose_part[i, j] + r[i, j]
        if not tentative[k]:
            _sandwich3(h_x, k, drift, drift_part)
            for i in range(2):
                for j in range(2):
                    total[i, j] += drift_part[i, j]
        det = total[0, 0] * total[1, 1] - total[0, 1] * total[1, 0]
        safe = det if abs(det) > 1e-300 else 1e-300
        s_inv[k, 0, 0], s_inv[k, 0, 1] = total[1, 1] / safe, -total[0, 1] / safe
        s_inv[k, 1, 0], s_inv[k, 1, 1] = -total[1, 0] / safe, total[0, 0] / safe
    nu = np.empty((z.shape[0], count, 2))
    d2 = np.empty((z.shape[0], count))
    gated = np.empty((z.shape[0], count), np.bool_)
    fresh = np.empty(z.shape[0], np.bool_)
    for i in range(z.shape[0]):
        z0, z1, outside = z[i, 0], z[i, 1], True
        for k in range(count):
            n0 = z0 - zhat[k, 0]
            n1 = wrap_angle(z1 - zhat[k, 1])
            nu[i, k, 0], nu[i, k, 1] = n0, n1
            value = s_inv[k, 0, 0] * n0 * n0 + (s_inv[k, 0, 1] + s_inv[k, 1, 0]) * n0 * n1 + s_inv[k, 1, 1] * n1 * n1
            d2[i, k] = value
            gated[i, k] = value < gate
            outside &= value > new_gate  # as numpy's min > new_gate, NaN included
        fresh[i] = outside
    in_view = np.empty(count, np.bool_)
    for k in range(count):
        in_view[k] = tentative[k] and view[0] < zhat[k, 0] < view[1] and abs(zhat[k, 1]) < view[2]
    return zhat, h_x, own, nu, d2, gated, fresh, in_view


@njit
def _particle_proposal(pool_mean, pool_cov, table, p, pose, cov, a, b, places, z, r, weighed, shift):
    """Particle ``p``'s FastSLAM 2.0 proposal: the Kalman update of its pose prior N(``pose``, ``cov``) by the
    detections ``z[j]`` of the landmarks at ``places[j]`` (:func:`_places`), all linearised at ``pose``, one
    detection after the other (with Q_j = H_m Σ_j H_mᵀ + R block diagonal this is the batch update exactly).
    ``cov`` becomes the posterior, ``shift`` the mean's offset; returns log N(ν; 0, H_x P H_xᵀ + Q) of the first
    ``weighed`` detections, the particle's weight. The covariance, P H_xᵀ and the gain K live in local scalars
    while the detections are folded in: as arrays, every store to one made the compiler load the others again."""
    theta = pose[2]
    c, s = math.cos(theta), math.sin(theta)
    px, py = pose[0] + a * c - b * s, pose[1] + a * s + b * c
    d_theta0, d_theta1 = -a * s - b * c, a * c - b * s
    c00, c01, c02 = cov[0, 0], cov[0, 1], cov[0, 2]
    c10, c11, c12 = cov[1, 0], cov[1, 1], cov[1, 2]
    c20, c21, c22 = cov[2, 0], cov[2, 1], cov[2, 2]
    x0, x1, x2 = 0.0, 0.0, 0.0
    log_weight = 0.0
    for j in range(places.shape[0]):
        mean = pool_mean[table[p, places[j, 0]]]
        sigma = pool_cov[table[p, places[j, 0]]]
        k = places[j, 1]
        dx, dy = mean[k, 0] - px, mean[k, 1] - py
        q = max(dx * dx + dy * dy, 1e-18)
        distance = math.sqrt(q)
        h00, h01, h10, h11 = dx / distance, dy / distance, -dy / q, dx / q
        g0, g1, g2 = -h00, -h01, -(h00 * d_theta0 + h01 * d_theta1)  # H_x: rows (g0, g1, g2) and (k0, k1, k2)
        k0, k1, k2 = -h10, -h11, -(h10 * d_theta0 + h11 * d_theta1) - 1.0
        m00, m01, m11 = sigma[k, 0, 0], sigma[k, 0, 1], sigma[k, 1, 1]
        t00, t01 = h00 * m00 + h01 * m01, h00 * m01 + h01 * m11
        t10, t11 = h10 * m00 + h11 * m01, h10 * m01 + h11 * m11
        ph00, ph01 = c00 * g0 + c01 * g1 + c02 * g2, c00 * k0 + c01 * k1 + c02 * k2  # P H_xᵀ, row by row
        ph10, ph11 = c10 * g0 + c11 * g1 + c12 * g2, c10 * k0 + c11 * k1 + c12 * k2
        ph20, ph21 = c20 * g0 + c21 * g1 + c22 * g2, c20 * k0 + c21 * k1 + c22 * k2
        s00 = g0 * ph00 + g1 * ph10 + g2 * ph20 + t00 * h00 + t01 * h01 + r[0, 0]
        s01 = g0 * ph01 + g1 * ph11 + g2 * ph21 + t00 * h10 + t01 * h11 + r[0, 1]
        s11 = k0 * ph01 + k1 * ph11 + k2 * ph21 + t10 * h10 + t11 * h11 + r[1, 1]
        det = s00 * s11 - s01 * s01
        safe = det if abs(det) > 1e-300 else 1e-300
        i00, i01, i11 = s11 / safe, -s01 / safe, s00 / safe
        e0 = z[j, 0] - distance - (g0 * x0 + g1 * x1 + g2 * x2)
        e1 = wrap_angle(z[j, 1] - wrap_angle(math.atan2(dy, dx) - theta)) - (k0 * x0 + k1 * x1 + k2 * x2)
        gain00, gain01 = ph00 * i00 + ph01 * i01, ph00 * i01 + ph01 * i11  # K = P H_xᵀ S⁻¹
        gain10, gain11 = ph10 * i00 + ph11 * i01, ph10 * i01 + ph11 * i11
        gain20, gain21 = ph20 * i00 + ph21 * i01, ph20 * i01 + ph21 * i11
        x0 += gain00 * e0 + gain01 * e1
        x1 += gain10 * e0 + gain11 * e1
        x2 += gain20 * e0 + gain21 * e1
        c00 -= gain00 * ph00 + gain01 * ph01  # P −= K H P = K (P Hᵀ)ᵀ
        c01 -= gain00 * ph10 + gain01 * ph11
        c02 -= gain00 * ph20 + gain01 * ph21
        c10 -= gain10 * ph00 + gain11 * ph01
        c11 -= gain10 * ph10 + gain11 * ph11
        c12 -= gain10 * ph20 + gain11 * ph21
        c20 -= gain20 * ph00 + gain21 * ph01
        c21 -= gain20 * ph10 + gain21 * ph11
        c22 -= gain20 * ph20 + gain21 * ph21
        if j < weighed:
            log_weight += -0.5 * (i00 * e0 * e0 + 2.0 * i01 * e0 * e1 + i11 * e1 * e1) \
                - 0.5 * math.log(max(det, 1e-300)) - LOG_2PI
    shift[0], shift[1], shift[2] = x0, x1, x2
    cov[0, 0], cov[1, 1], cov[2, 2] = c00, c11, c22
    cov[0, 1] = cov[1, 0] = 0.5 * (c01 + c10)
    cov[0, 2] = cov[2, 0] = 0.5 * (c02 + c20)
    cov[1, 2] = cov[2, 1] = 0.5 * (c12 + c21)
    return log_weight


@njit
def proposal_moments_kernel(pool_mean, pool_cov, table, block, pose, prior, a, b, slots, z, r):
    """(shift ``(P, 3)``, posterior ``(P, 3, 3)``, log weight ``(P,)``) of every particle's proposal from its moved
    ``pose`` and motion ``prior`` (:func:`_particle_proposal`)."""
    count = pose.shape[0]
    shift = np.zeros((count, 3))
    post = np.empty((count, 3, 3))
    log_weight = np.zeros(count)
    places = _places(slots, block)
    for p in range(count):
        post[p] = prior[p]
        log_weight[p] = _particle_proposal(pool_mean, pool_cov, table, p, pose[p], post[p], a, b, places, z, r,
                                           slots.shape[0], shift[p])
    return shift, post, log_weight


@njit
def _propose_particle(pool_mean, pool_cov, table, p, pose, delta, motion_cov, a, b, places, z, r, weighed, normals,
                      jitter, cov, shift, lower, unused):
    """Particle ``p``'s FastSLAM 2.0 step of :func:`propose_kernel`, in place on its ``pose`` ``(3,)`` and its (private)
    blocks: the motion composed on, the proposal, the draw with its ``normals`` ``(3,)``, the landmark updates;
    returns its log weight. The same arithmetic as the serial kernel's loop body, which keeps its own copy: called
    as a function there it made the serial step 20 % slower (arrays passed per particle); the tests hold the two
    equal bit for bit. ``cov``, ``shift``, ``lower`` are its scratch ((3, 3), (3,), (3, 3), ``lower`` zero above
    the diagonal); ``unused``, an empty array: the updates' own likelihoods are not computed (the proposal weighs)."""
    m00, m11, m22 = motion_cov[0, 0], motion_cov[1, 1], motion_cov[2, 2]
    m01 = 0.5 * (motion_cov[0, 1] + motion_cov[1, 0])
    m02 = 0.5 * (motion_cov[0, 2] + motion_cov[2, 0])
    m12 = 0.5 * (motion_cov[1, 2] + motion_cov[2, 1])
    c, s = math.cos(pose[2]), math.sin(pose[2])
    pose[0] += c * delta[0] - s * delta[1]
    pose[1] += s * delta[0] + c * delta[1]
    pose[2] = wrap_angle(pose[2] + delta[2])
    # the prior J Σ Jᵀ, J the rotation R of the position block: R Σ_xy Rᵀ, R Σ_xθ, Σ_θθ
    a00 = c * m00 - s * m01
    a01 = c * m01 - s * m11
    a10 = s * m00 + c * m01
    a11 = s * m01 + c * m11
    cov[0, 0] = a00 * c - a01 * s
    cov[0, 1] = cov[1, 0] = a00 * s + a01 * c
    cov[1, 1] = a10 * s + a11 * c
    cov[0, 2] = cov[2, 0] = c * m02 - s * m12
    cov[1, 2] = cov[2, 1] = s * m02 + c * m12
    cov[2, 2] = m22
    log_weight = _particle_proposal(pool_mean, pool_cov, table, p, pose, cov, a, b, places, z, r, weighed, shift)
    for i in range(3):
        cov[i, i] += jitter
    for j in range(3):  # Cholesky, lower
        total = cov[j, j]
        for k in range(j):
            total -= lower[j, k] * lower[j, k]
        lower[j, j] = math.sqrt(max(total, 0.0))
        for i in range(j + 1, 3):
            total = cov[i, j]
            for k in range(j):
                total -= lower[i, k] * lower[j, k]
            lower[i, j] = total / lower[j, j] if lower[j, j] > 0.0 else 0.0
    for i in range(3):
        pose[i] += shift[i] + lower[i, 0] * normals[0] + lower[i, 1] * normals[1] + lower[i, 2] * normals[2]
    pose[2] = wrap_angle(pose[2])
    _particle_update(pool_mean, pool_cov, table, p, pose, a, b, places, z, r, unused, False)
    return log_weight


@njit
def _grow_box(pool_mean, table, p, places, box):
    """Widen ``box`` ``(m, 4)`` (low x, low y, high x, high y) to particle ``p``'s means of the landmarks at ``places``
    (min and max: the same box whatever order the particles come in)."""
    for j in range(places.shape[0]):
        mean = pool_mean[table[p, places[j, 0]], places[j, 1]]
        box[j, 0], box[j, 1] = min(box[j, 0], mean[0]), min(box[j, 1], mean[1])
        box[j, 2], box[j, 3] = max(box[j, 2], mean[0]), max(box[j, 3], mean[1])


@njit
def propose_kernel(pool_mean, pool_cov, table, block, refs, free_blocks, free_count, blocks, exist, hits, pose, delta,
                   motion_cov, a, b, slots, z, r, weighed, normals, jitter, exist_hit, exist_max, log_weight, box):
    """Every particle's FastSLAM 2.0 step, in place on ``pose`` ``(P, 3)`` and on its landmarks: the buffered motion
    (``delta``, ``motion_cov`` in the robot's frame) composed onto the pose, its prior J Σ Jᵀ updated by the scan
    (:func:`_particle_proposal`), a draw ``shift + L · normals[p]`` from the posterior (L its Cholesky factor,
    ``jitter`` added to the diagonal), then the EKF updates of the landmarks ``slots`` (distinct) from the drawn
    pose (:func:`_particle_update`), in the particle's own copy of ``blocks`` (:func:`_private_particle`);
    ``log_weight`` gets the particles' weights and ``box`` ``(m, 4)`` (low x, low y, high x, high y; start empty)
    the box of every particle's updated mean of each slot, for the map's spatial index
    (:meth:`AlignedMap.refile_slots`). One particle at a time, so its landmarks are read from memory once for the
    proposal, the update and the box: with 1000 particles the blocks outgrow the cache, and each pass over them
    of a separate kernel paid the misses."""
    cov = np.empty((3, 3))
    shift = np.empty(3)
    lower = np.zeros((3, 3))
    unused = np.empty(0)  # the updates' own likelihoods, not computed: the proposal weighs instead
    places = _places(slots, block)
    flat_mean, flat_cov = _flat_pools(pool_mean, pool_cov)
    m00, m11, m22 = motion_cov[0, 0], motion_cov[1, 1], motion_cov[2, 2]
    m01 = 0.5 * (motion_cov[0, 1] + motion_cov[1, 0])
    m02 = 0.5 * (motion_cov[0, 2] + motion_cov[2, 0])
    m12 = 0.5 * (motion_cov[1, 2] + motion_cov[2, 1])
    for p in range(pose.shape[0]):
        c, s = math.cos(pose[p, 2]), math.sin(pose[p, 2])
        pose[p, 0] += c * delta[0] - s * delta[1]
        pose[p, 1] += s * delta[0] + c * delta[1]
        pose[p, 2] = wrap_angle(pose[p, 2] + delta[2])
        # the prior J Σ Jᵀ, J the rotation R of the position block: R Σ_xy Rᵀ, R Σ_xθ, Σ_θθ
        a00 = c * m00 - s * m01
        a01 = c * m01 - s * m11
        a10 = s * m00 + c * m01
        a11 = s * m01 + c * m11
        cov[0, 0] = a00 * c - a01 * s
        cov[0, 1] = cov[1, 0] = a00 * s + a01 * c
        cov[1, 1] = a10 * s + a11 * c
        cov[0, 2] = cov[2, 0] = c * m02 - s * m12
        cov[1, 2] = cov[2, 1] = s * m02 + c * m12
        cov[2, 2] = m22
        _private_particle(table, p, blocks, refs, flat_mean, flat_cov, free_blocks, free_count)
        log_weight[p] = _particle_proposal(pool_mean, pool_cov, table, p, pose[p], cov, a, b, places, z, r, weighed,
                                           shift)
        for i in range(3):
            cov[i, i] += jitter
        for j in range(3):  # Cholesky, lower
            total = cov[j, j]
            for k in range(j):
                total -= lower[j, k] * lower[j, k]
            lower[j, j] = math.sqrt(max(total, 0.0))
            for i in range(j + 1, 3):
                total = cov[i, j]
                for k in range(j):
                    total -= lower[i, k] * lower[j, k]
                lower[i, j] = total / lower[j, j] if lower[j, j] > 0.0 else 0.0
        for i in range(3):
            pose[p, i] += shift[i] + lower[i, 0] * normals[p, 0] + lower[i, 1] * normals[p, 1] + lower[i, 2] * normals[p, 2]
        pose[p, 2] = wrap_angle(pose[p, 2])
        _particle_update(pool_mean, pool_cov, table, p, pose[p], a, b, places, z, r, unused, False)
        for j in range(places.shape[0]):
            mean = pool_mean[table[p, places[j, 0]], places[j, 1]]
            box[j, 0], box[j, 1] = min(box[j, 0], mean[0]), min(box[j, 1], mean[1])
            box[j, 2], box[j, 3] = max(box[j, 2], mean[0]), max(box[j, 3], mean[1])
    _count_hits(exist, hits, slots, exist_hit, exist_max)


@njit_parallel
def propose_parallel_kernel(pool_mean, pool_cov, table, block, refs, free_blocks, free_count, blocks, exist, hits,
                            pose, delta, motion_cov, a, b, slots, z, r, weighed, normals, jitter, exist_hit, exist_max,
                            log_weight, box):
    """:func:`propose_kernel` with the particles spread over numba's threads, in three passes: the blocks of copy on
    write handed out in particle order (:func:`_claim_blocks`: the same tables, free list and reference counts as
    the serial kernel), the copies in parallel (every source is read before any particle writes: a block's last
    holder keeps it and updates it in place), then each particle's step in parallel (:func:`_propose_particle`, its
    own scratch), and the box of the updated means, in particle order. The same numbers for any thread count."""
    count, held = pose.shape[0], blocks.shape[0]
    places = _places(slots, block)
    flat_mean, flat_cov = _flat_pools(pool_mean, pool_cov)
    source = np.empty((count, held), np.int64)
    target = np.empty((count, held), np.int64)
    for p in range(count):
        _claim_blocks(table, p, blocks, refs, free_blocks, free_count, source[p], target[p])
    for p in prange(count):
        _copy_claimed(flat_mean, flat_cov, source[p], target[p])
    cov = np.empty((count, 3, 3))
    shift = np.empty((count, 3))
    lower = np.zeros((count, 3, 3))
    unused = np.empty(0)
    for p in prange(count):
        log_weight[p] = _propose_particle(pool_mean, pool_cov, table, p, pose[p], delta, motion_cov, a, b, places, z,
                                          r, weighed, normals[p], jitter, cov[p], shift[p], lower[p], unused)
    for p in range(count):
        _grow_box(pool_mean, table, p, places, box)
    _count_hits(exist, hits, slots, exist_hit, exist_max)


@njit
def create_kernel(pool_mean, pool_cov, table, block, refs, free_blocks, free_count, blocks, pose, a, b, slots, z, r):
    """New landmarks ``slots`` where detections ``z`` ``(m, 2)`` put them from each particle's ``pose`` ``(P, 3)``, in
    the particle's own copy of ``blocks`` (:func:`_private_particle`): the mean the inverse sensor model gives and
    the covariance G R Gᵀ, G its Jacobian in the detection ((a, b) the sensor's offset on the robot), as
    :meth:`robots.models.RangeBearingSensor.inverse` and ``inverse_jacobians`` with
    :func:`robots.gaussian.sandwich2`."""
    places = _places(slots, block)
    flat_mean, flat_cov = _flat_pools(pool_mean, pool_cov)
    r00, r01, r11 = r[0, 0], r[0, 1], r[1, 1]
    for p in range(pose.shape[0]):
        _private_particle(table, p, blocks, refs, flat_mean, flat_cov, free_blocks, free_count)
        c, s = math.cos(pose[p, 2]), math.sin(pose[p, 2])
        px, py = pose[p, 0] + a * c - b * s, pose[p, 1] + a * s + b * c
        for j in range(places.shape[0]):
            mean = pool_mean[table[p, places[j, 0]]]
            cov = pool_cov[table[p, places[j, 0]]]
            k = places[j, 1]
            beta = pose[p, 2] + z[j, 1]
            distance = z[j, 0]
            cb, sb = math.cos(beta), math.sin(beta)
            mean[k, 0], mean[k, 1] = px + distance * cb, py + distance * sb
            a00, a01, a10, a11 = cb, -distance * sb, sb, distance * cb
            t00, t01 = a00 * r00 + a01 * r01, a00 * r01 + a01 * r11
            t10, t11 = a10 * r00 + a11 * r01, a10 * r01 + a11 * r11
            cov[k, 0, 0] = t00 * a00 + t01 * a01
            cov[k, 0, 1] = cov[k, 1, 0] = t00 * a10 + t01 * a11
            cov[k, 1, 1] = t10 * a10 + t11 * a11


def create(landmarks, sensor, pose: np.ndarray, slots: np.ndarray, z: np.ndarray, r: np.ndarray) -> None:
    """Write new landmarks ``slots`` (allocated, distinct) of every particle of an :class:`AlignedMap` where detections
    ``z`` ``(m, 2)`` put them from ``pose`` ``(P, 3)`` (:func:`create_kernel`); the caller registers them."""
    blocks = landmarks.reserve_private(slots)
    create_kernel(landmarks.pool_mean, landmarks.pool_cov, landmarks.table, landmarks.block, landmarks.refs,
                  landmarks.free_blocks, landmarks.free_count, blocks, np.ascontiguousarray(pose), float(sensor.offset[0]),
                  float(sensor.offset[1]), slots, np.ascontiguousarray(z, float), np.ascontiguousarray(r, float))


def proposal_moments(landmarks, sensor, pose: np.ndarray, prior: np.ndarray, slots: np.ndarray, z: np.ndarray,
                     r: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """FastSLAM 2.0 proposal of every particle of an :class:`AlignedMap` from its moved ``pose`` ``(P, 3)`` and motion
    ``prior`` ``(P, 3, 3)``, given detections ``z`` ``(m, 2)`` of landmarks ``slots`` ``(m,)`` held by every particle:
    (shift, posterior covariance, log weight)."""
    return proposal_moments_kernel(landmarks.pool_mean, landmarks.pool_cov, landmarks.table, landmarks.block, pose,
                                   prior, sensor.offset[0], sensor.offset[1], slots, z, r)


def propose(landmarks, sensor, pose: np.ndarray, delta: np.ndarray, motion_cov: np.ndarray, slots: np.ndarray,
            z: np.ndarray, r: np.ndarray, weighed: int, normals: np.ndarray, jitter: float, exist_hit: float,
            exist_max: float, workers: int = 1) -> np.ndarray:
    """Move every particle's ``pose`` ``(P, 3)`` (in place) by a draw from its FastSLAM 2.0 proposal given the motion
    (``delta``, ``motion_cov``) and detections ``z`` of landmarks ``slots`` (distinct) held by every particle, then
    update those landmarks from the drawn poses, as :func:`known_update` would; returns the log weights ``(P,)``
    (:func:`propose_kernel`; ``workers`` > 1: :func:`propose_parallel_kernel` on that many threads, the same
    numbers). The updated slots are filed again in the map's spatial index from the boxes the kernel leaves: the
    other slots of their blocks changed in no particle."""
    blocks = landmarks.reserve_private(slots, refile=False)
    out = np.empty(pose.shape[0])
    box = np.empty((slots.shape[0], 4))
    box[:, :2], box[:, 2:] = np.inf, -np.inf
    moved = np.ascontiguousarray(pose)
    kernel = propose_kernel
    if workers > 1:
        use_threads(workers)
        kernel = propose_parallel_kernel
    kernel(landmarks.pool_mean, landmarks.pool_cov, landmarks.table, landmarks.block, landmarks.refs,
           landmarks.free_blocks, landmarks.free_count, blocks, landmarks.exist, landmarks.hits, moved, delta, motion_cov,
           sensor.offset[0], sensor.offset[1], slots, z, r, weighed, normals, jitter, exist_hit, exist_max, out, box)
    landmarks.refile_slots(slots, box)
    if moved is not pose:
        pose[...] = moved
    return out


@njit
def vote_kernel(cells, weights, landmarks, centre, turns, shift_limit, inlier, shifts_per_turn):
    """The Hough vote of :func:`central.fastslam.reacquire.vote_reference`, turn after turn in one pass: (detections,
    index of the turn, shift, landmark reached by each cell or −1 when none is within ``inlier``) of each scored
    shift, in the reference's order. A bin's pairs are sorted stably by key, so they keep the reference's order
    (cell after cell): the mean adds them in the same order, and a cell's repeated votes in a bin are adjacent."""
    n, k = cells.shape[0], landmarks.shape[0]
    capacity = turns.shape[0] * shifts_per_turn
    scores, turn_index = np.empty(capacity), np.empty(capacity, np.int64)
    shifts_out, reached = np.empty((capacity, 2)), np.empty((capacity, n), np.int64)
    moved = np.empty((n, 2))
    shift, voter = np.empty((n * k, 2)), np.empty(n * k, np.int64)
    cell, key = np.empty((n * k, 2), np.int64), np.empty(n * k, np.int64)
    bin_votes, bin_sum, bin_count = np.empty(n * k), np.empty((n * k, 2)), np.empty(n * k, np.int64)
    taken = np.empty(n * k, np.bool_)
    found = 0
    for t in range(turns.shape[0]):
        c, s = math.cos(turns[t]), math.sin(turns[t])
        for i in range(n):
            dx, dy = cells[i, 0] - centre[0], cells[i, 1] - centre[1]
            moved[i, 0] = (c * dx - s * dy) + centre[0]
            moved[i, 1] = (s * dx + c * dy) + centre[1]
        m = 0
        for i in range(n):
            for j in range(k):
                sx, sy = landmarks[j, 0] - moved[i, 0], landmarks[j, 1] - moved[i, 1]
                if math.hypot(sx, sy) <= shift_limit:
                    shift[m, 0], shift[m, 1], voter[m] = sx, sy, i
                    m += 1
        if m == 0:
            continue
        for q in range(m):
            cell[q, 0], cell[q, 1] = math.floor(shift[q, 0] / inlier), math.floor(shift[q, 1] / inlier)
        low_x, low_y, high_y = cell[0, 0], cell[0, 1], cell[0, 1]
        for q in range(1, m):
            low_x, low_y, high_y = min(low_x, cell[q, 0]), min(low_y, cell[q, 1]), max(high_y, cell[q, 1])
        for q in range(m):
            key[q] = (cell[q, 0] - low_x) * (high_y - low_y + 1) + (cell[q, 1] - low_y)
        order = np.argsort(key[:m], kind="mergesort")
        bins, last = -1, 0
        for q in order:
            if bins < 0 or key[q] != key[last]:
                bins += 1
                bin_votes[bins], bin_sum[bins, 0], bin_sum[bins, 1], bin_count[bins] = weights[voter[q]], 0.0, 0.0, 0
            elif voter[q] != voter[last]:  # each cell votes once per bin
                bin_votes[bins] += weights[voter[q]]
            bin_sum[bins, 0] += shift[q, 0]
            bin_sum[bins, 1] += shift[q, 1]
            bin_count[bins] += 1
            last = q
        bins += 1
        taken[:bins] = False
        for _ in range(min(shifts_per_turn, bins)):
            best = -1
            for b in range(bins):  # the most votes, the lowest key among equals
                if not taken[b] and (best < 0 or bin_votes[b] > bin_votes[best]):
                    best = b
            taken[best] = True
            sx, sy = bin_sum[best, 0] / bin_count[best], bin_sum[best, 1] / bin_count[best]
            score = 0.0
            for i in range(n):
                px, py = moved[i, 0] + sx, moved[i, 1] + sy
                nearest, gap = 0, math.hypot(px - landmarks[0, 0], py - landmarks[0, 1])
                for j in range(1, k):
                    d = math.hypot(px - landmarks[j, 0], py - landmarks[j, 1])
                    if d < gap:
                        nearest, gap = j, d
                if gap < inlier:
                    score += weights[i]
                    reached[found, i] = nearest
                else:
                    reached[found, i] = -1
            scores[found], turn_index[found], shifts_out[found, 0], shifts_out[found, 1] = score, t, sx, sy
            found += 1
    return scores[:found], turn_index[:found], shifts_out[:found], reached[:found]


def vote(cells: np.ndarray, weights: np.ndarray, landmarks: np.ndarray, centre: np.ndarray, turns: np.ndarray,
         shift_limit: float, inlier: float, shifts_per_turn: int) -> list[tuple[float, float, np.ndarray, np.ndarray]]:
    """:func:`central.fastslam.reacquire.vote_reference` by :func:`vote_kernel`: the same list, entry for entry."""
    scores, turn_index, shifts, reached = vote_kernel(
        np.ascontiguousarray(cells, np.float64), np.ascontiguousarray(weights, np.float64),
        np.ascontiguousarray(landmarks, np.float64), np.ascontiguousarray(centre, np.float64),
        np.ascontiguousarray(turns, np.float64), float(shift_limit), float(inlier), int(shifts_per_turn))
    return [(float(score), float(turns[t]), shift, row[row >= 0])
            for score, t, shift, row in zip(scores, turn_index, shifts, reached)]


@njit
def drift_accumulate_kernel(drift, heading, delta, cov, turn_slip_var):
    """:func:`central.fastslam.reacquire.accumulate` on a (3, 3) ``drift``: J D Jᵀ + R Σ Rᵀ, J the composition's
    Jacobian in the pose at ``heading``, R the rotation of ``cov`` (robot frame) into the world, plus
    ``turn_slip_var`` per radian turned."""
    c, s = math.cos(heading), math.sin(heading)
    j02, j12 = -(s * delta[0] + c * delta[1]), c * delta[0] - s * delta[1]
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    jac = np.array([[1.0, 0.0, j02], [0.0, 1.0, j12], [0.0, 0.0, 1.0]])
    out = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            total = 0.0
            for k in range(3):
                for l in range(3):
                    total += jac[i, k] * drift[k, l] * jac[j, l] + rot[i, k] * cov[k, l] * rot[j, l]
            out[i, j] = total
    out[2, 2] += turn_slip_var * abs(delta[2])
    return out


@njit
def drift_condition_kernel(drift, h_x, noise):
    """:func:`central.fastslam.reacquire.condition`: the Kalman update of the (3, 3) covariance ``drift`` by the
    detections' pose Jacobians ``h_x`` ``(n, 2, 3)`` with noise ``(n, 2, 2)``, one detection after the other (with
    block-diagonal noise the batch update exactly), each in Joseph form P ← (I − K H) P (I − K H)ᵀ + K N Kᵀ, then
    symmetrised."""
    p = drift.copy()
    ph = np.empty((3, 2))
    gain = np.empty((3, 2))
    i_kh = np.empty((3, 3))
    tmp = np.empty((3, 3))
    for n in range(h_x.shape[0]):
        h = h_x[n]
        for i in range(3):
            for j in range(2):
                ph[i, j] = p[i, 0] * h[j, 0] + p[i, 1] * h[j, 1] + p[i, 2] * h[j, 2]
        s00 = h[0, 0] * ph[0, 0] + h[0, 1] * ph[1, 0] + h[0, 2] * ph[2, 0] + noise[n, 0, 0]
        s01 = h[0, 0] * ph[0, 1] + h[0, 1] * ph[1, 1] + h[0, 2] * ph[2, 1] + noise[n, 0, 1]
        s10 = h[1, 0] * ph[0, 0] + h[1, 1] * ph[1, 0] + h[1, 2] * ph[2, 0] + noise[n, 1, 0]
        s11 = h[1, 0] * ph[0, 1] + h[1, 1] * ph[1, 1] + h[1, 2] * ph[2, 1] + noise[n, 1, 1]
        det = s00 * s11 - s01 * s10
        i00, i01, i10, i11 = s11 / det, -s01 / det, -s10 / det, s00 / det
        for i in range(3):
            gain[i, 0] = ph[i, 0] * i00 + ph[i, 1] * i10
            gain[i, 1] = ph[i, 0] * i01 + ph[i, 1] * i11
        for i in range(3):
            for j in range(3):
                i_kh[i, j] = (1.0 if i == j else 0.0) - gain[i, 0] * h[0, j] - gain[i, 1] * h[1, j]
        for i in range(3):
            for j in range(3):
                tmp[i, j] = i_kh[i, 0] * p[0, j] + i_kh[i, 1] * p[1, j] + i_kh[i, 2] * p[2, j]
        for i in range(3):
            kr0 = gain[i, 0] * noise[n, 0, 0] + gain[i, 1] * noise[n, 1, 0]  # row i of K N
            kr1 = gain[i, 0] * noise[n, 0, 1] + gain[i, 1] * noise[n, 1, 1]
            for j in range(3):
                p[i, j] = tmp[i, 0] * i_kh[j, 0] + tmp[i, 1] * i_kh[j, 1] + tmp[i, 2] * i_kh[j, 2] \
                    + kr0 * gain[j, 0] + kr1 * gain[j, 1]
        for i in range(3):
            for j in range(i + 1, 3):
                p[i, j] = p[j, i] = 0.5 * (p[i, j] + p[j, i])
    return p


def drift_accumulate(drift: np.ndarray | None, heading: float, delta: np.ndarray, cov: np.ndarray,
                     turn_slip_var: float) -> np.ndarray:
    """:func:`central.fastslam.reacquire.accumulate` by :func:`drift_accumulate_kernel` (None: no drift yet)."""
    drift = np.zeros((3, 3)) if drift is None else np.ascontiguousarray(drift, float)
    return drift_accumulate_kernel(drift, float(heading), np.ascontiguousarray(delta, float),
                                   np.ascontiguousarray(cov, float), float(turn_slip_var))


def drift_condition(drift: np.ndarray, h_x: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """:func:`central.fastslam.reacquire.condition` by :func:`drift_condition_kernel`."""
    return drift_condition_kernel(np.ascontiguousarray(drift, float), np.ascontiguousarray(h_x, float),
                                  np.ascontiguousarray(noise, float))


@njit
def joint_blocks_kernel(gated, h_x, own, pose_cov):
    """The inputs of JCBB over the landmarks some detection gates (``reach``, the columns of ``gated`` with any
    pair): (reach, the blocks ``(K, K, 2, 2)`` H_a P H_bᵀ of the predicted detections' joint covariance from the
    pose covariance ``pose_cov``, plus each landmark's own H_m Σ H_mᵀ on the diagonal blocks)."""
    count = 0
    reach = np.empty(gated.shape[1], np.int64)
    for n in range(gated.shape[1]):
        for m in range(gated.shape[0]):
            if gated[m, n]:
                reach[count] = n
                count += 1
                break
    reach = reach[:count]
    hp = np.empty((count, 2, 3))  # H_a P
    for a in range(count):
        for i in range(2):
            for j in range(3):
                hp[a, i, j] = (h_x[reach[a], i, 0] * pose_cov[0, j] + h_x[reach[a], i, 1] * pose_cov[1, j]
                               + h_x[reach[a], i, 2] * pose_cov[2, j])
    joint = np.empty((count, count, 2, 2))
    for a in range(count):
        for b in range(count):
            for i in range(2):
                for j in range(2):
                    joint[a, b, i, j] = (hp[a, i, 0] * h_x[reach[b], j, 0] + hp[a, i, 1] * h_x[reach[b], j, 1]
                                         + hp[a, i, 2] * h_x[reach[b], j, 2])
        for i in range(2):
            for j in range(2):
                joint[a, a, i, j] += own[reach[a], i, j]
    return reach, joint


@njit
def negative_evidence_kernel(cand, zhat, considered, limits, exist, hits, valid):
    """Negative evidence of one scan, one candidate at a time (:func:`central.fastslam.evidence.negative_evidence`;
    the numpy reference and the meaning of the arguments: :func:`~central.fastslam.evidence.negative_evidence_reference`).
    Returns ``(P + 1,)``: each particle's Σ ln(1 − P_D·v), then the number of landmarks deleted."""
    min_range, max_range, half_fov, sigma_r, sigma_b = limits[0], limits[1], limits[2], limits[3], limits[4]
    p_detect, exist_miss, exist_min, permanent = limits[5], limits[6], limits[7], limits[8]
    limited_view = half_fov < np.inf
    count, width = cand.shape
    out = np.zeros(count + 1)
    deleted = 0
    for p in range(count):
        total = 0.0
        for j in range(width):
            if not considered[p, j]:
                continue
            predicted_range = zhat[p, j, 0]
            visible = ndtr((max_range - predicted_range) / sigma_r) * ndtr((predicted_range - min_range) / sigma_r)
            if limited_view:
                visible *= ndtr((half_fov - abs(zhat[p, j, 1])) / sigma_b)
            log_miss = math.log1p(-p_detect * visible)
            total += log_miss
            if visible > 0.01:
                slot = cand[p, j]
                exist[p, slot] += exist_miss * log_miss
                if exist[p, slot] < exist_min and hits[p, slot] < permanent:
                    valid[p, slot] = False
                    deleted += 1
        out[p] = total
    out[count] = deleted
    return out


@njit
def silence_kernel(slots, confirmed, hit, zhat, h_x, own, pose_cov, r, min_range, max_range, half_fov, silence, views,
                   counts, gate, threshold):
    """One scan's views of the confirmed landmarks near a robot: silences ended by its associations, the robot's
    detection counts and last views, the silences of the landmarks it missed, and which of them pass ``threshold``
    (:func:`central.fastslam.silence.silence_reference`)."""
    count = slots.size
    bins_count = counts.shape[1]
    ended = np.empty(count)
    ended_count = 0
    pinned = 0
    for k in range(count):
        if confirmed[k] and hit[k]:
            pinned += 1
            slot = slots[k]
            if silence[slot] > 0.0:
                ended[ended_count] = silence[slot]
                ended_count += 1
            silence[slot] = 0.0
    deleted = np.zeros(count, np.bool_)
    if pinned == 0:
        return ended[:ended_count], deleted
    before = counts.copy()  # the model's chances as they stood before this scan
    det = r[0, 0] * r[1, 1] - r[0, 1] * r[1, 0]
    i00, i01, i10, i11 = r[1, 1] / det, -r[0, 1] / det, -r[1, 0] / det, r[0, 0] / det
    for k in range(count):
        if not confirmed[k] or (hit[k] and pinned < 2):
            continue
        s00 = own[k, 0, 0] + r[0, 0]
        s11 = own[k, 1, 1] + r[1, 1]
        for i in range(3):
            for j in range(3):
                s00 += h_x[k, 0, i] * pose_cov[i, j] * h_x[k, 0, j]
                s11 += h_x[k, 1, i] * pose_cov[i, j] * h_x[k, 1, j]
        sr, sb = math.sqrt(s00), math.sqrt(s11)
        v = ndtr((max_range - zhat[k, 0]) / sr) * ndtr((zhat[k, 0] - min_range) / sr)
        if half_fov < np.inf:
            v *= ndtr((half_fov - abs(zhat[k, 1])) / sb)
        if v <= 0.05:  # silence.MIN_VISIBILITY
            continue
        slot = slots[k]
        if not hit[k] and not np.isnan(views[slot, 0]):
            d0 = zhat[k, 0] - views[slot, 0]
            d1 = wrap_angle(zhat[k, 1] - views[slot, 1])
            if d0 * (i00 * d0 + i01 * d1) + d1 * (i10 * d0 + i11 * d1) < gate:
                continue
        views[slot, 0] = zhat[k, 0]
        views[slot, 1] = zhat[k, 1]
        b = min(max(int(zhat[k, 0] / max_range * bins_count), 0), bins_count - 1)
        counts[1, b] += v
        if hit[k]:
            counts[0, b] += v
            continue
        silence[slot] += (before[0, b] + 1.0) / (before[1, b] + 2.0) * v
        if silence[slot] > threshold:
            deleted[k] = True
            silence[slot] = 0.0
    return ended[:ended_count], deleted


def warm_up() -> None:
    """Compile (or load from the cache) every FastSLAM kernel on tiny inputs."""
    from central.fastslam.aligned_map import AlignedMap
    from robots.models import RangeBearingSensor

    landmarks = AlignedMap(2)
    slots = landmarks.add(np.array([[3.0, 0.0], [3.0, 1.0]]), np.broadcast_to(np.eye(2), (2, 2, 2)), 1.0, 1,
                          np.array([0, 1]))
    pose = np.zeros((2, 3))  # the wrappers make a robot's poses contiguous
    for workers in (1, 2):  # the serial kernels, then the parallel ones
        known_update(landmarks, RangeBearingSensor(), pose, slots[:1], np.array([[3.0, 0.0]]), np.eye(2) * 0.01, 1.0,
                     6.0, workers)
    robot_kernels.warm_up()  # integrate_controls, shared with MCL
    weights = np.full(2, 0.5)
    weighted_pose(pose, weights, None)
    weighted_pose(pose, weights, (np.zeros(3), np.eye(3)))
    pose_belief_kernel(pose, weights, np.zeros(3), np.eye(3), True)
    created = landmarks.allocate(1)
    create(landmarks, RangeBearingSensor(), pose, created, np.array([[2.0, 0.1]]), np.eye(2) * 0.01)
    landmarks.register(created, 1.0, 1, np.array([2]))
    landmarks.select(np.array([1, 0]))
    landmarks.near(np.zeros(2), 10.0)  # files the written blocks and searches: the index's kernels
    keep, mean, cov = marginal_map(landmarks, weights, slots, np.zeros(2), 10.0)
    association_draw_kernel(weights, 1.0, 1, 0.5)
    shared_gating_kernel(np.zeros(3), 0.0, 0.0, mean, cov, np.zeros(keep.size, np.bool_), np.eye(3), np.eye(3),
                         np.eye(2), np.array([[3.0, 0.0]]), 9.2, 13.8, np.array([0.0, 10.0, 1.0]))
    for workers in (1, 2):
        propose(landmarks, RangeBearingSensor(), pose, np.zeros(3), np.eye(3) * 0.01, slots,
                np.array([[3.0, 0.0], [3.1, 0.3]]), np.eye(2) * 0.01, 1, np.zeros((2, 3)), 1e-12, 1.0, 6.0, workers)
    vote(np.array([[0.0, 0.0], [1.0, 0.0]]), np.array([1, 2]), np.array([[0.1, 0.0], [1.1, 0.1]]), np.zeros(2),
         np.array([-0.1, 0.0, 0.1]), 0.5, 0.2, 4)
    drift = drift_accumulate(None, 0.0, np.zeros(3), np.eye(3), 0.0)
    h_x = np.ones((1, 2, 3))
    drift_condition(drift, h_x, np.eye(2)[None])
    joint_blocks_kernel(np.ones((1, 1), np.bool_), h_x, np.ones((1, 2, 2)), drift)
    negative_evidence_kernel(np.zeros((1, 1), np.int64), np.ones((1, 1, 2)), np.ones((1, 1), np.bool_),
                             np.array([0.0, 10.0, 1.0, 0.1, 0.01, 0.9, 1.0, 0.0, 5.0]), np.zeros((1, 1)),
                             np.zeros((1, 1), np.int32), np.ones((1, 1), np.bool_))
    silence_kernel(np.zeros(2, np.int64), np.ones(2, np.bool_), np.array([True, False]), np.ones((2, 2)), h_x.repeat(2, 0),
                   np.ones((2, 2, 2)), np.eye(3), np.eye(2), 0.0, 10.0, 1.0, np.zeros(2), np.full((2, 2), np.nan),
                   np.zeros((2, 8)), 9.2, 1.0)


__all__ = ["association_draw_kernel", "AVAILABLE", "create", "drift_accumulate", "drift_condition", "integrate_controls", "joint_blocks_kernel",
           "known_update", "known_update_parallel_kernel", "marginal_map", "max_threads", "near_kernel", "negative_evidence_kernel", "pose_belief_kernel", "private_blocks", "propose",
           "proposal_moments", "propose_parallel_kernel", "refile_slots_kernel", "select_kernel", "shared_gating_kernel", "silence_kernel", "use_threads", "vote", "warm_up",
           "weighted_pose"]
