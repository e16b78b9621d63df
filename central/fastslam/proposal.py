"""The FastSLAM 2.0 proposal (Montemerlo et al., "FastSLAM 2.0: An improved particle filtering algorithm for
simultaneous localization and mapping that provably converges").

Instead of sampling a robot's pose from the motion model alone (FastSLAM 1.0), each particle samples it from
the motion prior conditioned on the scan's detections of landmarks it already has, so few particles are
wasted where the scan says the robot is not.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from central.fastslam import association, kernels, motion, shared
from central.fastslam.lifecycle import RobotState
from robots.gaussian import LOG_2PI, sandwich, sandwich2, sqrt_psd
from robots.models import compose_jacobian, se2_compose, wrap_angle

if TYPE_CHECKING:
    from central.fastslam.core import FastSlam

# a unicycle's motion prior may have rank 2, and so the posterior: 1e-12 (1 µm, 1 µrad) on the diagonal keeps the
# draw's square root a Cholesky factor, which rounding cannot switch to eigenvectors (another valid draw)
POSTERIOR_JITTER = 1e-12


def propose(slam: FastSlam, robot: RobotState, z, r, ids) -> tuple[bool, np.ndarray]:
    """Apply the robot's buffered motion by sampling each particle's pose from the proposal.

    Matches are taken at the predicted mean pose (known ids, or the gated maximum-likelihood landmark). The
    proposal is the Kalman update of N(x̂, P) by every matched detection at once; the particle is weighted by
    the joint marginal N(ν; 0, H_x P H_xᵀ + Q), Q = H_m Σ H_mᵀ + R, of the detections that weigh (:func:`weighing`:
    with shared association, those of confirmed landmarks). Returns (whether the weights of matched detections
    were set here: the landmark updates must not add them again; the detections whose landmarks were updated
    here too). With ids given or chosen per scan the whole step, the matched landmarks' updates included, is one
    kernel (:func:`central.fastslam.kernels.propose`); the numpy code below, with
    :func:`central.fastslam.association.update_known` after it, is its reference.
    """
    pending = motion.take_pending(slam, robot)
    col = robot.index
    n = slam.pose.shape[0]
    if slam.config.compiled and slam.config.association in ("known", "shared"):
        det, slots = identified_matches(slam, ids)
        if det.size:
            delta, cov = (np.zeros(3), np.zeros((3, 3))) if pending is None else pending
            weighs = weighing(slam, slots)
            order = np.argsort(~weighs, kind="stable")  # the kernel weighs by the leading detections
            normals = slam.rng.standard_normal((n, 3))
            slam.logw += kernels.propose(slam.map, robot.sensor, slam.pose[:, col], delta, cov, slots[order],
                                         z[det[order]], r, int(np.count_nonzero(weighs)), normals, POSTERIOR_JITTER,
                                         slam.config.exist_hit, slam.config.exist_max, slam.workers)
            return True, det
    if pending is None:
        prior = np.zeros((n, 3, 3))
    else:
        delta, cov = pending
        jac = compose_jacobian(slam.pose[:, col, 2])
        slam.pose[:, col] = se2_compose(slam.pose[:, col], delta)
        prior = sandwich(jac, cov)
    p, i, slot = matches(slam, robot, z, r, ids)
    if p.size == 0:
        shift, post, log_weight = np.zeros((n, 3)), prior, np.zeros(n)
    else:
        counted = np.ones(z.shape[0], bool)
        if slam.config.association in ("known", "shared"):
            det = i[:p.size // n]
            counted[det[~weighing(slam, slot[:p.size // n])]] = False
        shift, post, log_weight = proposal_moments_reference(slam, robot, z, r, prior, p, i, slot, counted)
    post = post + POSTERIOR_JITTER * np.eye(3)
    slam.pose[:, col] += shift + (sqrt_psd(post) @ slam.rng.standard_normal((n, 3, 1)))[..., 0]
    slam.pose[:, col, 2] = wrap_angle(slam.pose[:, col, 2])
    slam.logw += log_weight
    return p.size > 0, np.zeros(0, np.int64)


def proposal_moments_reference(slam: FastSlam, robot: RobotState, z, r, prior, p, i, slot, counted=None
                               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(shift ``(P, 3)``, posterior ``(P, 3, 3)``, log weight ``(P,)``) of the proposal: the Kalman update of the
    prior N(x̂, P) by every matched detection (``p``, ``i``, ``slot``: particle, detection, landmark) at once,
    and the joint marginal N(ν; 0, H_x P H_xᵀ + Q), Q = H_m Σ H_mᵀ + R, of the detections ``counted`` ``(m,)``
    (default all); the numpy reference of :func:`central.fastslam.kernels.proposal_moments`, and the path of
    per-particle association."""
    n, m, col = slam.pose.shape[0], z.shape[0], robot.index
    pose = slam.pose[p, col]
    mu, sig = slam.map.gather(p, slot)
    zhat = robot.sensor.observe(pose, mu)
    h_x, h_m = robot.sensor.jacobians(pose, mu)
    h = np.zeros((n, m, 2, 3))
    nu = np.zeros((n, m, 2))
    q = np.broadcast_to(np.eye(2), (n, m, 2, 2)).copy()
    h[p, i], nu[p, i], q[p, i] = h_x, robot.sensor.innovation(z[i], zhat), sandwich2(h_m, sig) + r
    h = h.reshape(n, 2 * m, 3)
    q_big = np.zeros((n, 2 * m, 2 * m))
    for j in range(m):
        q_big[:, 2 * j:2 * j + 2, 2 * j:2 * j + 2] = q[:, j]
    s = sandwich(h, prior) + q_big
    s_inv = np.linalg.inv(s)
    gain = prior @ np.swapaxes(h, -1, -2) @ s_inv
    nu = nu.reshape(n, 2 * m)
    shift = (gain @ nu[..., None])[..., 0]
    post = prior - gain @ h @ prior
    rows = np.repeat(np.ones(m, bool) if counted is None else counted, 2)
    if not rows.all():  # the marginal of the counted detections: their rows and columns of S
        s, nu = s[:, rows][:, :, rows], nu[:, rows]
        s_inv = np.linalg.inv(s)
    _, logdet = np.linalg.slogdet(s)
    matched = np.bincount(p, rows[2 * i], minlength=n)
    return shift, post, -0.5 * np.einsum("pi,pij,pj->p", nu, s_inv, nu) - 0.5 * logdet - LOG_2PI * matched


def matches(slam: FastSlam, robot: RobotState, z, r, ids) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(particle, detection, slot) of the detections that match an existing landmark at the current poses
    (at most one detection per landmark and particle)."""
    n = slam.pose.shape[0]
    if slam.config.association in ("known", "shared"):
        det, slots = identified_matches(slam, ids)
        return np.repeat(np.arange(n), det.size), np.tile(det, n), np.tile(slots, n)
    slam.map.reserve(z.shape[0])
    scan = association.candidates(slam, robot, 0, r)
    if scan.k_view == 0:
        return _no_matches()
    association.prepare(slam, robot, scan, r)
    d2, ll = association.score(scan, z)
    gated = scan.mask[:, None, :] & (d2 < slam.gate)
    best = np.argmax(np.where(gated, ll, -np.inf), 2)
    p, i = np.nonzero(gated.any(2))
    k = best[p, i]
    slot = scan.cand[p, k]
    key = p * scan.cand.shape[1] + k
    _, first = np.unique(key, return_index=True)
    unique = np.zeros(p.size, bool)
    unique[first] = True
    return p[unique], i[unique], slot[unique]


def identified_matches(slam: FastSlam, ids) -> tuple[np.ndarray, np.ndarray]:
    """(detection, slot) of the scan's first detection of each landmark already in the map, with ids given or chosen
    by the shared association (the same in every particle)."""
    if ids is None:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    seen, det, slots = set(), [], []
    for j, lid in enumerate(ids.tolist()):  # a few detections: plain Python beats np.unique's set-up
        if lid in seen:
            continue
        seen.add(lid)
        if lid >= 0 and lid in slam.known_slots:
            det.append(j)
            slots.append(slam.known_slots[lid])
    return np.array(det, np.int64), np.array(slots, np.int64)


def weighing(slam: FastSlam, slots: np.ndarray) -> np.ndarray:
    """Which matched detections (of the landmarks in ``slots``) weigh the particles: all with known ids; with shared
    association only those of confirmed landmarks. A tentative landmark (Wang, Huang and Dissanayake, "Implementation issues and
    experimental evaluation of D-SLAM", §3.1) still conditions the proposal, so the draw follows it, but weighs
    nothing until confirmed: clutter it was born of cannot select particles."""
    if slam.config.association != "shared" or not slots.size:
        return np.ones(slots.size, bool)
    return shared.confirmed_slots(slam, slots)


def _no_matches() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64)
