"""Shared association: one assignment per scan for every particle, against the filter's marginal map.

Per-particle nearest neighbour (``nn``, ``mht``) fails on real data when the particle cloud is narrower than
the true pose error: every particle is off, every particle calls the detection new, and the map fills with
duplicates (MR.CLAM 6 without barcodes: over 200 landmarks for 15). Here the scan is associated once, as an
EKF-SLAM would (Neira and Tardós, "Data association in stochastic mapping using the joint compatibility
test"): against the particle-weighted mean and covariance of every landmark, from the robot's mean pose
with a covariance that is the cloud's spread plus a floor (``gate_pose_floor``) and a growth with the time
since the robot last matched a landmark (``gate_pose_growth``, dead reckoning is worse than its model). A
pose error shifts every prediction of a scan together, which joint compatibility (JCBB) accounts for;
``exact`` is the optimal one-to-one assignment of individually gated pairs (mutual exclusion). The chosen
landmark ids are then updated in every particle as with known ids, so particles whose pose disagrees lose
weight instead of escaping into a landmark of their own.

Unmatched detections outside the new-landmark gate of every landmark start a landmark, the others are
ignored (outliers). New landmarks are tentative (Wang, Huang and Dissanayake, "Implementation issues and
experimental evaluation of D-SLAM", §3.1: confirmed and tentative lists): they neither weigh particles nor
appear in the map until associated ``confirm_hits`` times, and a tentative landmark in view but not seen
``tentative_misses`` times is dropped. A confirmed landmark that the robots' pinned scans stop seeing for longer than
the silences its landmarks survived make likely is deleted (:mod:`central.fastslam.silence`).

A robot whose dead reckoning has drifted too far (its drift, conditioned on its matches) is not associated scan by
scan: its scans are held until one rigid correction puts them back on the map (:mod:`central.fastslam.reacquire`).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from central.fastslam import kernels, motion, reacquire, resampling, silence
from central.fastslam.lifecycle import RobotState
from robots.gaussian import diagonal_variances, inv2, quad2, sandwich, sandwich2, systematic_resample
from robots.models import compose_jacobian, se2_compose, wrap_angle
from services.association.solvers import jcbb_ambiguous, solve_exact, solve_jcbb

if TYPE_CHECKING:
    from central.fastslam.core import FastSlam


def association_draw_reference(w: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """(distinct rows, their shares) of ``count`` systematic draws by weight ``w`` at offset 0.5: the numpy reference
    of :func:`central.fastslam.kernels.association_draw_kernel`."""
    drawn = systematic_resample(w, count, None, offset=0.5)  # sorted: its runs are np.unique's counts
    first = np.flatnonzero(np.concatenate(([True], drawn[1:] != drawn[:-1])))
    return drawn[first], np.diff(np.append(first, count)) / count


def marginal_map(slam: FastSlam, near: tuple[np.ndarray, float] | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(ids, slots, means ``(K, 2)``, covariances ``(K, 2, 2)``) of every landmark with an id (known or shared
    association), mixed over the particles: the weighted mean, and the weighted covariances plus the spread of
    the means. ``near`` = (point, radius): only the landmarks whose mean lies within ``radius`` of ``point``
    (the association needs those alone; the kernel mixes only the candidates of the map's spatial index, the
    reference mixes every landmark and cuts)."""
    if not slam.known_slots:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 2, 2))
    w = slam.weights()
    rows = None  # every particle
    cap = slam.config.association_particles
    if near is not None and 0 < cap < w.size:  # the association's mixtures: from ``cap`` particles drawn by weight
        total = float(w.sum())
        if slam.config.compiled and 0.0 < total < math.inf:
            rows, w = kernels.association_draw_kernel(w, total, cap, 0.5)
        else:
            rows, w = association_draw_reference(w, cap)
    if slam.config.compiled and near is not None:
        point, radius = np.asarray(near[0], float), float(near[1])
        slots = slam.map.near(point, radius)
        keep, mean, cov = kernels.marginal_map(slam.map, w, slots, point, radius, rows)
        return slam.map.label[slots[keep]], slots[keep], mean, cov
    ids, slots = slam.known_slots.arrays()
    if slam.config.compiled:
        keep, mean, cov = kernels.marginal_map(slam.map, w, slots, np.zeros(2), np.inf, rows)
        return ids[keep], slots[keep], mean, cov
    means, covs = slam.map.gather((np.arange(w.size) if rows is None else rows)[:, None], slots[None])
    mean = np.einsum("p,pkj->kj", w, means)
    if near is not None:
        keep = np.hypot(*(mean - near[0]).T) < near[1]
        ids, slots, mean, means, covs = ids[keep], slots[keep], mean[keep], means[:, keep], covs[:, keep]
    resid = means - mean
    cov = np.einsum("p,pkij->kij", w, covs) + np.einsum("p,pki,pkj->kij", w, resid, resid)
    return ids, slots, mean, cov


def pose_belief(slam: FastSlam, robot: RobotState) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The robot's weighted mean pose, its spread over the particles, and the extra variance the association
    assumes against drift: ``gate_pose_floor``² plus ``gate_pose_growth``² per second since its last match (at
    most 120 s)."""
    pose, w = slam.pose[:, robot.index], slam.weights()
    pending = motion.pending_motion(robot, slam.config)  # FastSLAM 2.0 associates before it moves the particles
    if slam.config.compiled:
        delta, delta_cov = (np.zeros(3), np.zeros((3, 3))) if pending is None else pending
        mean, cov = kernels.pose_belief_kernel(np.ascontiguousarray(pose), w, delta, delta_cov, pending is not None)
    else:
        mean, cov = resampling.weighted_pose(pose, w)
        if pending is not None:
            jac = compose_jacobian(mean[2])
            mean = se2_compose(mean, pending[0])
            cov = cov + jac @ pending[1] @ jac.T
    blind = 0.0 if robot.last_match_stamp is None else min(max(robot.last_scan_stamp - robot.last_match_stamp, 0.0), 120.0)
    floor, growth = diagonal_variances(slam.config.gate_pose_floor), diagonal_variances(slam.config.gate_pose_growth)
    return mean, cov, floor + growth * blind


def associate(slam: FastSlam, robot: RobotState, z: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Landmark id of each detection ``(m, 2)``: an existing one, a new one (tentative), or −1 (ignored)."""
    m = z.shape[0]
    ids = np.full(m, -1, np.int64)
    pose, spread, drift = pose_belief(slam, robot)
    if slam.config.reacquire:
        pending = motion.pending_motion(robot, slam.config)
        step = reacquire.step(slam, robot, pose, z, lambda point, radius: confirmed_near(slam, point, radius),
                              None if pending is None else pending[0])
        if step == "hold":
            return ids
        if step == "corrected":
            pose, spread, drift = pose_belief(slam, robot)
    position, _ = robot.sensor.sensor_position(pose)
    reach = robot.info.sensor.max_range + 3.0 * math.sqrt(r[0, 0]) + 2.0
    known, slots, mean, cov = marginal_map(slam, (position, reach))
    if known.size:
        # tentative landmarks were seen from about the present drift: they are gated without it, so clutter
        # does not confirm them by falling into a gate widened for old landmarks
        tentative = ~confirmed_slots(slam, slots)
        zhat, h_x, own, nu, d2, gated, fresh, in_view = _gating(slam, robot, pose, mean, cov, tentative, spread, drift,
                                                                r, z)
        if slam.config.ambiguity_margin > 0.0:
            ambiguous = _ambiguous(slam, d2, gated, zhat, r)
            gated[ambiguous] = False
            fresh &= ~ambiguous
            slam.counts["detections_ambiguous"] += int(np.count_nonzero(ambiguous))
        rows, cols = _solve(slam, nu, gated, d2, h_x, own, spread + drift, r)
        ids[rows] = known[cols]
        if slam.config.silence:
            hit = np.zeros(known.size, bool)
            hit[cols] = True
            silence.observe(slam, robot, slots, ~tentative, hit, zhat, h_x, own, spread + drift, r)
        unmatched = ids < 0
        fresh &= unmatched
        unmatched_count = int(np.count_nonzero(unmatched))
        slam.counts["detections_ignored"] += unmatched_count - int(np.count_nonzero(fresh))  # fresh ⊆ unmatched
        _age_tentative(slam, known, slots, in_view, set(ids[rows].tolist()))
    else:
        fresh, unmatched_count = np.ones(m, bool), m
    if rows_matched := m - unmatched_count:
        robot.last_match_stamp = robot.last_scan_stamp
        if not slam.config.reacquire_drift_update:
            robot.drift = None
        elif robot.drift is not None and (pinned := cols[~tentative[cols]]).size:
            condition = kernels.drift_condition if slam.config.compiled else reacquire.condition
            robot.drift = condition(robot.drift, h_x[pinned], own[pinned] + r)
        slam.counts["detections_matched"] += rows_matched
    created = int(np.count_nonzero(fresh))
    ids[fresh] = slam.next_landmark_id + np.arange(created)
    slam.next_landmark_id += created
    return ids


def _gating(slam: FastSlam, robot: RobotState, pose, mean, cov, tentative, spread, drift, r, z) -> tuple:
    """(ẑ, H_x, H_m Σ H_mᵀ, ν, d², gated, fresh, in view) of the detections against the landmark mixtures,
    S = H_m Σ H_mᵀ + H_x P H_xᵀ + R (+ H_x D H_xᵀ for confirmed landmarks): a pair is gated within the gate, a
    detection fresh outside every landmark's new-landmark gate, and the tentative landmarks whose predicted
    detection lies in the sensor's view are those a scan may count a miss for. By the kernel, or by this numpy
    reference."""
    spec = robot.info.sensor
    if slam.config.compiled:
        a, b = robot.sensor.offset
        view = np.array([spec.min_range, spec.max_range, 0.5 * spec.fov])
        return kernels.shared_gating_kernel(pose, float(a), float(b), mean, cov, tentative, spread, drift, r, z,
                                            slam.gate, slam.new_gate, view)
    zhat = robot.sensor.observe(pose, mean)
    h_x, h_m = robot.sensor.jacobians(np.broadcast_to(pose, (mean.shape[0], 3)), mean)
    own = sandwich2(h_m, cov)
    s = own + sandwich(h_x, spread) + r + np.where(tentative[:, None, None], 0.0, sandwich(h_x, drift))
    nu = z[:, None, :] - zhat[None]
    nu[..., 1] = wrap_angle(nu[..., 1])
    d2 = quad2(nu, inv2(s)[0][None])
    in_view = (zhat[:, 0] < spec.max_range) & (zhat[:, 0] > spec.min_range) & (np.abs(zhat[:, 1]) < 0.5 * spec.fov)
    return zhat, h_x, own, nu, d2, d2 < slam.gate, d2.min(1) > slam.new_gate, in_view & tentative


def _ambiguous(slam: FastSlam, d2: np.ndarray, gated: np.ndarray, zhat: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Detections whose two best gated landmarks are distinct landmarks (predicted detections farther apart than
    the sensor's new-landmark gate) and nearly as likely (d² within ``ambiguity_margin``): left out rather than
    risk a wrong association, which every particle would share."""
    margin = slam.config.ambiguity_margin
    if gated.shape[1] < 2:
        return np.zeros(gated.shape[0], bool)
    order = np.argsort(np.where(gated, d2, np.inf), axis=1)[:, :2]
    rows = np.arange(gated.shape[0])
    first, second = order[:, 0], order[:, 1]
    both = gated[rows, first] & gated[rows, second]
    close = d2[rows, second] - d2[rows, first] < margin
    apart = zhat[first] - zhat[second]
    apart[:, 1] = wrap_angle(apart[:, 1])
    distinct = quad2(apart, inv2(2.0 * r)[0]) > slam.new_gate
    return both & close & distinct


def _solve(slam: FastSlam, nu, gated, d2, h_x, own, pose_cov, r) -> tuple[np.ndarray, np.ndarray]:
    """(detection, candidate) pairs by JCBB (joint compatibility, the pose error shared by the whole scan) or by
    the optimal one-to-one assignment of individually gated pairs."""
    if not gated.any():
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if slam.config.shared_solver == "exact":
        return solve_exact(np.where(gated, d2 - slam.gate, np.inf))
    # JCBB never looks at a landmark no detection gates: leave them out
    if slam.config.compiled:
        reach, joint = kernels.joint_blocks_kernel(gated, h_x, own, pose_cov)
    else:
        reach, joint = joint_blocks(gated, h_x, own, pose_cov)
    nu, gated, d2 = nu.take(reach, 1), gated.take(reach, 1), d2.take(reach, 1)
    result = solve_jcbb(nu, gated, d2, joint, r, slam.config.gate_probability)
    slam.counts["jcbb_truncated"] += int(result.truncated)
    rows, cols = result.rows, result.cols
    if slam.config.unique_pairs and rows.size:
        unique = ~jcbb_ambiguous(nu, gated, d2, joint, r, slam.config.gate_probability, result)
        slam.counts["detections_not_unique"] += int((~unique).sum())
        rows, cols = rows[unique], cols[unique]
    return rows, reach[cols]


def joint_blocks(gated: np.ndarray, h_x: np.ndarray, own: np.ndarray, pose_cov: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(reach, joint): the landmarks some detection gates, and the blocks ``(K, K, 2, 2)`` H_a P H_bᵀ of their
    predicted detections' joint covariance (P = ``pose_cov``) plus each one's own H_m Σ H_mᵀ on the diagonal; the
    reference of :func:`central.fastslam.kernels.joint_blocks_kernel`."""
    reach = np.flatnonzero(gated.any(0))
    h_x, own = h_x.take(reach, 0), own.take(reach, 0)
    count = own.shape[0]  # np.tensordot's own reshapes and product, without its checks
    joint = np.dot((h_x @ pose_cov).reshape(2 * count, 3), h_x.transpose(2, 0, 1).reshape(3, 2 * count))
    joint = joint.reshape(count, 2, count, 2).transpose(0, 2, 1, 3)
    diagonal = np.einsum("aaij->aij", joint)  # a writeable view of the blocks H_a P H_aᵀ
    diagonal += own
    return reach, joint


def _age_tentative(slam: FastSlam, ids: np.ndarray, slots: np.ndarray, in_view: np.ndarray, seen: set) -> None:
    """Count a miss for each tentative landmark in the sensor's view (``in_view``, :func:`_gating`) and not seen;
    drop those missed ``tentative_misses`` times."""
    for lid, slot in zip(ids[in_view].tolist(), slots[in_view].tolist()):
        if lid in seen:
            continue
        misses = slam.tentative_misses.get(lid, 0) + 1
        if misses < slam.config.tentative_misses:
            slam.tentative_misses[lid] = misses
            continue
        drop_landmarks(slam, np.array([slot]))
        slam.counts["landmarks_dropped_tentative"] += 1


def drop_landmarks(slam: FastSlam, slots: np.ndarray) -> None:
    """Remove the landmarks in map ``slots`` (a tentative one dropped, a confirmed one silenced): their ids leave the
    known-landmark table and the tentative misses, their slots are released for reuse."""
    for slot in slots.tolist():
        lid = int(slam.map.label[slot])
        slam.tentative_misses.pop(lid, None)
        del slam.known_slots[lid]
    slam.map.release(slots)


def confirmed_near(slam: FastSlam, point: np.ndarray, radius: float) -> np.ndarray:
    """Means ``(K, 2)`` of the confirmed landmarks whose mixture mean lies within ``radius`` of ``point``."""
    _, slots, mean, _ = marginal_map(slam, (point, radius))
    return mean[confirmed_slots(slam, slots)]


def confirmed_slots(slam: FastSlam, slots: np.ndarray) -> np.ndarray:
    """Which of the landmarks in ``slots`` are confirmed: associated ``confirm_hits`` times."""
    return slam.map.hits[slots] >= slam.config.confirm_hits


def confirmed(slam: FastSlam, ids: np.ndarray) -> np.ndarray:
    """Which of the landmark ``ids`` (already in the map) are confirmed (:func:`confirmed_slots`)."""
    slots = np.array([slam.known_slots[int(i)] for i in ids], np.int64)
    return confirmed_slots(slam, slots) if slots.size else np.zeros(0, bool)
