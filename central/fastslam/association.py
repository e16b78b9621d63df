"""Data association per particle, and the landmark updates it leads to.

- ``known``: landmark ids come with the scan; every particle updates the same landmarks.
- ``shared``: the ids come from one association of the scan against the filter's marginal map
  (:mod:`~central.fastslam.shared`), then as ``known``.
- ``nn``: per particle, the maximum-likelihood landmark inside the χ² gate; a detection outside the wider
  new-landmark gate of every landmark starts a new one, one in between is ignored. Detections of one scan
  have sequential semantics (a detection sees the landmarks the earlier ones created or updated) but are
  processed in vectorised rounds: a detection waits for the next round only if an earlier one in the same
  particle picked the same landmark or started a new landmark near it.
- ``mht``: the split of Howard, "Multi-robot simultaneous localization and mapping using particle
  filters": each particle becomes one child per gated landmark, one for a new landmark and one for a
  spurious detection (n+2), weighted by their likelihoods; children far below their parent's best are
  pruned, and the set goes back to N particles by systematic resampling (at the end of the scan, or sooner
  when it grows past ``mht_max_factor``·N).

Weights: an update contributes its innovation likelihood N(ν; 0, S), S = H Σ Hᵀ + R. A new or ignored
detection contributes the likelihood at the new-landmark gate of a landmark known to sensor precision,
−½ χ²_new − ½ ln|2πR|, so a particle never gains by calling a detection new rather than matching it; MHT
shares that weight between its new-landmark and spurious children in the ratio of expected new landmarks to
false detections per scan.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from central.fastslam import evidence, kernels, landmarks, resampling, shared
from central.fastslam.lifecycle import RobotState
from robots.gaussian import LOG_2PI, inv2, quad2, sandwich2
from robots.models import wrap_angle

if TYPE_CHECKING:
    from central.fastslam.core import FastSlam


@dataclass
class ScanState:
    """Per-scan bookkeeping of candidate landmarks, gathered with the particles when they are resampled or split.

    ``cand[p, k]`` is a slot of particle p's map: the first ``k_view`` columns are
    the landmarks near the robot when the scan arrived, the next ``n`` columns the
    landmarks created by detection 0..n-1 of this scan.
    """

    cand: np.ndarray
    mask: np.ndarray
    used: np.ndarray
    hit: np.ndarray
    k_view: int
    rival: np.ndarray | None = None  # landmarks gated by a detection that went to another landmark (duplicate suspects)
    terms: tuple = ()  # (ẑ, H, S, S⁻¹, |S|) of every candidate from the last scoring, reused by the updates

    def __post_init__(self) -> None:
        if self.rival is None:
            self.rival = np.zeros_like(self.mask)

    def select(self, index: np.ndarray) -> None:
        self.cand, self.mask, self.used, self.hit = self.cand[index], self.mask[index], self.used[index], self.hit[index]
        self.rival = self.rival[index]
        self.terms = tuple(t[index] for t in self.terms)

    def terms_at(self, p: np.ndarray, k: np.ndarray) -> tuple:
        flat = p * self.cand.shape[1] + k
        return tuple(t.reshape((-1,) + t.shape[2:])[flat] for t in self.terms)


# ------------------------------------------------------------------ landmark updates
def update(slam: FastSlam, robot: RobotState, p: np.ndarray, z: np.ndarray, slot: np.ndarray,
           terms: tuple) -> np.ndarray:
    """EKF update of landmark ``slot`` of particle ``p`` by detection ``z`` (one pair per row); log N(ν; 0, S)."""
    return landmarks.update(slam.map, robot.sensor, p, z, slot, terms, slam.config.exist_hit, slam.config.exist_max)


def create(slam: FastSlam, robot: RobotState, p: np.ndarray, z: np.ndarray, r: np.ndarray,
           label: np.ndarray) -> np.ndarray:
    """New landmarks of particle ``p`` (sorted) where detection ``z`` puts them; returns their slots."""
    slam.counts["landmarks_created"] += p.size
    return landmarks.create(slam.map, robot.sensor, slam.pose[p, robot.index], p, z, r, slam.config.exist_init, label)


# ------------------------------------------------------------------ known association
def update_known(slam: FastSlam, robot: RobotState, z, r, ids, weigh: bool, updated: np.ndarray | None = None) -> None:
    """Update (or create) the landmarks the scan's ids name, in every particle; weigh the particles unless the
    proposal already did (with shared association, only by confirmed landmarks). Detections ``updated`` (indices)
    were already applied to their landmarks by the FastSLAM 2.0 kernel."""
    if ids is None:
        slam.counts["scans_without_ids"] += 1
        return
    identified = ids >= 0
    slam.counts["detections_unidentified"] += identified.size - int(np.count_nonzero(identified))
    if updated is not None and updated.size:
        identified[updated] = False
    z, ids = z[identified], ids[identified]
    if not ids.size:
        return
    order = np.argsort(ids, kind="stable")
    first = np.searchsorted(ids[order], ids[order])
    occurrence = np.empty(ids.size, np.int64)
    occurrence[order] = np.arange(ids.size) - first
    for k in range(int(occurrence.max()) + 1):  # a landmark seen twice in one scan: one update per round
        zk, idk = z[occurrence == k], ids[occurrence == k]
        known = np.array([int(i) in slam.known_slots for i in idk], bool)
        if known.any():
            slots = np.array([slam.known_slots[int(i)] for i in idk[known]], np.int64)
            counted = np.ones(slots.size, bool) if slam.config.association == "known" else shared.confirmed(slam, idk[known])
            if slam.config.compiled:
                ll = kernels.known_update(slam.map, robot.sensor, slam.pose[:, robot.index], slots, zk[known], r,
                                          slam.config.exist_hit, slam.config.exist_max, slam.workers)
            else:
                ll = known_update_reference(slam, robot, slots, zk[known], r)
            if weigh and counted.any():
                slam.logw += ll[:, counted].sum(1)
        if (~known).any():
            create_known(slam, robot, zk[~known], r, idk[~known])


def known_update_reference(slam: FastSlam, robot: RobotState, slots: np.ndarray, z: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The numpy reference of :func:`central.fastslam.kernels.known_update`: the slots copied out of every particle
    into a dense :class:`~central.fastslam.landmarks.LandmarkMap`, updated there, written back; log N ``(P, m)``."""
    n, m = slam.pose.shape[0], slots.size
    scratch = landmarks.LandmarkMap(n, m)
    scratch.mean[:], scratch.cov[:] = slam.map.gather(np.arange(n)[:, None], slots[None])
    scratch.exist[:], scratch.hits[:] = slam.map.exist[slots], slam.map.hits[slots]
    p, slot = np.repeat(np.arange(n), m), np.tile(np.arange(m), n)
    terms = landmarks.predict(scratch, robot.sensor, slam.pose[p, robot.index], p, slot, r)
    ll = landmarks.update(scratch, robot.sensor, p, np.tile(z, (n, 1)), slot, terms, slam.config.exist_hit,
                          slam.config.exist_max)
    slam.map.write(slots, scratch.mean, scratch.cov)
    slam.map.exist[slots], slam.map.hits[slots] = scratch.exist[0], scratch.hits[0]
    return ll.reshape(n, m)


def create_known(slam: FastSlam, robot: RobotState, z: np.ndarray, r: np.ndarray, ids: np.ndarray) -> None:
    """New landmarks ``ids`` (not in the map) where detections ``z`` ``(m, 2)`` put them, in every particle: one slot
    each, the same in all particles, the sensor noise ``r`` carried into the map."""
    if slam.config.compiled:
        slots = slam.map.allocate(ids.size)
        kernels.create(slam.map, robot.sensor, slam.pose[:, robot.index], slots, z, r)
        slam.map.register(slots, slam.config.exist_init, 1, ids)
    else:
        pose = slam.pose[:, robot.index][:, None, :]
        mean = robot.sensor.inverse(pose, z[None])
        _, g = robot.sensor.inverse_jacobians(pose, z[None])
        slots = slam.map.add(mean, sandwich2(g, r), slam.config.exist_init, 1, ids)
    slam.known_slots.update(zip(ids.tolist(), slots.tolist()))
    slam.counts["landmarks_created"] += slam.pose.shape[0] * ids.size


# ------------------------------------------------------------------ candidates and scoring
def candidates(slam: FastSlam, robot: RobotState, extra: int, r: np.ndarray) -> ScanState:
    """Landmarks each particle could see now (within reach of the sensor's range and field of view, with a
    margin for the noise), padded to a common width, with ``extra`` free columns for this scan's new ones."""
    pose = slam.pose[:, robot.index]
    width = int(slam.map.used.max(initial=0))
    position, _ = robot.sensor.sensor_position(pose)
    delta = slam.map.mean[:, :width] - position[:, None, :]
    reach = robot.info.sensor.max_range if slam.config.max_obs_range is None else slam.config.max_obs_range
    reach = reach + 3.0 * float(np.sqrt(r[0, 0])) + 1.0
    distance2 = np.einsum("pkj,pkj->pk", delta, delta)
    near = slam.map.valid[:, :width] & (distance2 < reach * reach)
    half_view = 0.5 * robot.info.sensor.fov + 3.0 * float(np.sqrt(r[1, 1])) + 0.2
    if half_view < np.pi:
        ahead = delta[..., 0] * np.cos(pose[:, 2])[:, None] + delta[..., 1] * np.sin(pose[:, 2])[:, None]
        near &= (ahead >= np.cos(half_view) * np.sqrt(distance2)) | (distance2 < 1.0)
    rows, cols = np.nonzero(near)
    k_view = int(near.sum(1).max(initial=0))
    n = slam.pose.shape[0]
    cand = np.zeros((n, k_view + extra), np.int64)
    mask = np.zeros((n, k_view + extra), bool)
    position_in_row = np.arange(rows.size) - np.searchsorted(rows, rows)
    cand[rows, position_in_row] = cols
    mask[rows, position_in_row] = True
    return ScanState(cand, mask, np.zeros_like(mask), np.zeros_like(mask), k_view)


def prepare(slam: FastSlam, robot: RobotState, scan: ScanState, r: np.ndarray) -> None:
    """Compute (ẑ, H, S, S⁻¹, |S|) of every candidate at the current poses and landmark estimates."""
    rows = np.arange(scan.cand.shape[0])[:, None]
    scan.terms = landmarks.predict(slam.map, robot.sensor, slam.pose[rows, robot.index], rows, scan.cand, r)


def score(scan: ScanState, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(d² ``(P, m, K)``, log N(ν; 0, S) ``(P, m, K)``) of detections ``z (m, 2)`` against every candidate
    (after :func:`prepare`)."""
    zhat, _, _, s_inv, det = scan.terms
    nu = z[None, :, None, :] - zhat[:, None, :, :]
    nu[..., 1] = wrap_angle(nu[..., 1])
    d2 = quad2(nu, s_inv[:, None])
    ll = -0.5 * d2 - 0.5 * np.log(np.maximum(det, 1e-300))[:, None, :] - LOG_2PI
    return d2, ll


def new_log_likelihood(slam: FastSlam, r: np.ndarray) -> float:
    """Weight of a new (or ignored) detection: the likelihood at the new-landmark gate of a landmark known to
    sensor precision (so no particle gains by calling a detection new rather than matching it)."""
    return -0.5 * slam.new_gate - 0.5 * float(np.log(np.linalg.det(r))) - LOG_2PI


def unexplained_split(slam: FastSlam, robot: RobotState, r: np.ndarray) -> tuple[float, float]:
    """MHT weights of the new-landmark and spurious children of one detection.

    Together they carry the weight of an unexplained detection (:func:`new_log_likelihood`, as in NN), shared
    in the ratio of the expected new landmarks per scan λ_n to the expected false detections per scan λ_c.
    Clutter that does become a landmark is removed later by the existence score.
    """
    clutter = robot.info.sensor.clutter_rate if slam.config.clutter_rate is None else slam.config.clutter_rate
    fresh = slam.config.new_landmark_rate
    unexplained = new_log_likelihood(slam, r)
    spurious = unexplained + np.log(clutter / (clutter + fresh)) if clutter > 0 else -np.inf
    return unexplained + float(np.log(fresh / (clutter + fresh))), float(spurious)


def near_pairs(slam: FastSlam, robot: RobotState, scan: ScanState, z: np.ndarray, r: np.ndarray, available: np.ndarray):
    """(particle, detection, candidate, d², log N) of the pairs that may pass the new-landmark gate.

    A cheap Cartesian pre-test keeps the work O(pairs) instead of O(P·m·K): with y the detection projected
    from the particle's pose, d² ≥ |y − μ|² / (tr Σ + σ_r² + r²σ_φ²) (the largest eigenvalue of the
    innovation covariance in the landmark plane), so pairs farther than that bound (×1.5 for the
    linearisation) cannot pass; the rest get the exact d² from the candidates' (ẑ, S⁻¹, |S|).
    """
    pose = slam.pose[:, robot.index]
    particle = np.arange(pose.shape[0])[:, None]
    flat = slam.map.flat(particle, scan.cand)
    mean = slam.map.mean_rows()[flat]
    spread = np.einsum("pkii->pk", slam.map.cov_rows()[flat])
    y = robot.sensor.inverse(pose[:, None, :], z[None])
    dx = y[:, :, None, 0] - mean[:, None, :, 0]
    dy = y[:, :, None, 1] - mean[:, None, :, 1]
    sensor_var = r[0, 0] + z[:, 0] ** 2 * r[1, 1]
    bound = 1.5 * slam.new_gate * (spread[:, None, :] + sensor_var[None, :, None])
    p, i, k = np.nonzero(available[:, None, :] & (dx * dx + dy * dy < bound))
    zhat, _, _, s_inv, det = scan.terms
    nu = z[i] - zhat[p, k]
    nu[:, 1] = wrap_angle(nu[:, 1])
    d2 = quad2(nu, s_inv[p, k])
    ll = -0.5 * d2 - 0.5 * np.log(np.maximum(det[p, k], 1e-300)) - LOG_2PI
    return p, i, k, d2, ll


# ------------------------------------------------------------------ unknown association
def update_unknown(slam: FastSlam, robot: RobotState, z, r, ids, weigh: bool) -> None:
    """Associate the scan's detections per particle (nn or mht), update and create landmarks, then apply the
    negative evidence, merge duplicates and bring the particle set back to N."""
    n = z.shape[0]
    slam.map.reserve(n)
    scan = candidates(slam, robot, n, r)
    labels = np.full(n, -1, np.int64) if ids is None else ids
    if slam.config.association == "nn":
        nearest_neighbour(slam, robot, scan, z, r, labels, weigh)
    else:
        multiple_hypotheses(slam, robot, scan, z, r, labels)
    evidence.negative_evidence(slam, robot, scan, r)
    if slam.config.merge_duplicates:
        evidence.merge_duplicates(slam, scan)
    if slam.pose.shape[0] != slam.config.particles:
        resampling.resample(slam, slam.config.particles)


def nearest_neighbour(slam: FastSlam, robot: RobotState, scan: ScanState, z, r, labels, weigh: bool) -> None:
    """Gated maximum-likelihood association per particle, in rounds of detections that cannot conflict."""
    n_particles, n = slam.pose.shape[0], z.shape[0]
    ll_new = new_log_likelihood(slam, r)
    dz = z[:, None, :] - z[None, :, :]
    dz[..., 1] = wrap_angle(dz[..., 1])
    close = quad2(dz, inv2(2.0 * r)[0]) < slam.new_gate
    pending = np.ones((n_particles, n), bool)
    while pending.any():
        slam.counts["nn_rounds"] += 1
        cols = np.flatnonzero(pending.any(0))
        m = cols.size
        prepare(slam, robot, scan, r)
        available = scan.mask & ~scan.used if slam.config.exclusive else scan.mask
        p, i, k, d2, ll = near_pairs(slam, robot, scan, z[cols], r, available)
        gated = d2 < slam.gate
        key = p * m + i
        order = np.lexsort((-ll, ~gated, key))
        first = order[np.flatnonzero(np.r_[True, key[order][1:] != key[order][:-1]])] if key.size else order
        first = first[gated[first]]
        best = np.full((n_particles, m), -1, np.int64)
        best[p[first], i[first]] = k[first]
        has = best >= 0
        near = np.zeros((n_particles, m), bool)
        near[p[d2 < slam.new_gate], i[d2 < slam.new_gate]] = True
        fresh = ~near
        waiting = pending[:, cols]
        target = np.where(has & waiting, best, -1)
        same = (target[:, :, None] == target[:, None, :]) & (target[:, :, None] >= 0)
        near_new = (fresh & waiting)[:, :, None] & close[np.ix_(cols, cols)][None]
        earlier = np.triu(np.ones((m, m), bool), 1)[None]
        act = waiting & ~((same | near_new) & earlier & waiting[:, :, None]).any(1)
        p_u, c_u = np.nonzero(act & has)
        k_u = best[p_u, c_u]
        rival = gated & act[p, i] & (k != best[p, i])
        scan.rival[p[rival], k[rival]] = True
        ll_u = update(slam, robot, p_u, z[cols[c_u]], scan.cand[p_u, k_u], scan.terms_at(p_u, k_u))
        scan.used[p_u, k_u] = scan.hit[p_u, k_u] = True
        p_n, c_n = np.nonzero(act & fresh)
        column = scan.k_view + cols[c_n]
        scan.cand[p_n, column] = create(slam, robot, p_n, z[cols[c_n]], r, labels[cols[c_n]])
        scan.mask[p_n, column] = scan.used[p_n, column] = scan.hit[p_n, column] = True
        unexplained = (act & ~has).sum(1)
        slam.counts["detections_ignored"] += int((act & ~has & ~fresh).sum())
        if weigh:
            slam.logw += np.bincount(p_u, ll_u, n_particles)
        slam.logw += ll_new * unexplained
        pending[:, cols] &= ~act


def multiple_hypotheses(slam: FastSlam, robot: RobotState, scan: ScanState, z, r, labels) -> None:
    """Howard's MHT: per detection, split every particle into its gated, new and spurious children."""
    n = slam.config.particles
    ll_new, ll_spurious = unexplained_split(slam, robot, r)
    log_prune = float(np.log(slam.config.mht_prune))
    for i in range(z.shape[0]):
        prepare(slam, robot, scan, r)
        d2, ll = score(scan, z[i:i + 1])
        d2, ll = d2[:, 0], ll[:, 0]
        available = scan.mask & ~scan.used if slam.config.exclusive else scan.mask
        width = scan.cand.shape[1]
        hyp = np.empty((slam.pose.shape[0], width + 2))
        gated = available & (d2 < slam.gate)
        hyp[:, :width] = np.where(gated, ll, -np.inf)
        hyp[:, width], hyp[:, width + 1] = ll_new, ll_spurious
        best = hyp.max(1)
        keep = hyp >= (best + log_prune)[:, None]
        if np.all(keep.sum(1) == 1):
            choice = np.argmax(hyp, 1)
            slam.logw += best
        else:
            parent, choice = np.nonzero(keep)
            child_logw = slam.logw[parent] + hyp[parent, choice]
            gated = gated[parent]
            resampling.select(slam, parent, scan)
            slam.logw = child_logw
            slam.counts["mht_splits"] += 1
        p_u = np.flatnonzero(choice < width)
        k_u = choice[p_u]
        rivals = gated[p_u]
        rivals[np.arange(p_u.size), k_u] = False
        scan.rival[p_u] |= rivals
        update(slam, robot, p_u, np.broadcast_to(z[i], (p_u.size, 2)), scan.cand[p_u, k_u], scan.terms_at(p_u, k_u))
        scan.used[p_u, k_u] = scan.hit[p_u, k_u] = True
        p_n = np.flatnonzero(choice == width)
        column = scan.k_view + i
        scan.cand[p_n, column] = create(slam, robot, p_n, np.broadcast_to(z[i], (p_n.size, 2)), r,
                                        np.full(p_n.size, labels[i]))
        scan.mask[p_n, column] = scan.used[p_n, column] = scan.hit[p_n, column] = True
        slam.counts["detections_spurious"] += int((choice == width + 1).sum())
        if slam.pose.shape[0] > slam.config.mht_max_factor * n:
            resampling.resample(slam, n, scan)
