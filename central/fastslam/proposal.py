"""The FastSLAM 2.0 proposal (Montemerlo et al., "FastSLAM 2.0: An improved particle filtering algorithm for
simultaneous localization and mapping that provably converges").

Instead of sampling a robot's pose from the motion model alone (FastSLAM 1.0), each particle samples it from
the motion prior conditioned on the scan's detections of landmarks it already has, so few particles are
wasted where the scan says the robot is not.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from central.fastslam import association, motion
from central.fastslam.lifecycle import RobotState
from robots.gaussian import LOG_2PI, sandwich, sandwich2, sqrt_psd
from robots.models import compose_jacobian, se2_compose, wrap_angle

if TYPE_CHECKING:
    from central.fastslam.core import FastSlam

def propose(slam: FastSlam, robot: RobotState, z, r, ids) -> bool:
    """Apply the robot's buffered motion by sampling each particle's pose from the proposal.

    Matches are taken at the predicted mean pose (known ids, or the gated maximum-likelihood landmark). The
    proposal is the Kalman update of N(x̂, P) by every matched detection at once; the particle is weighted by
    the joint marginal N(ν; 0, H_x P H_xᵀ + Q), Q = H_m Σ H_mᵀ + R. Returns True when the weights of matched
    detections were set here (the landmark updates must not add them again).
    """
    pending = motion.pending_motion(robot, slam.config)
    motion.clear(robot)
    col = robot.index
    n = slam.pose.shape[0]
    if pending is None:
        prior = np.zeros((n, 3, 3))
    else:
        delta, cov = pending
        jac = compose_jacobian(slam.pose[:, col, 2])
        slam.pose[:, col] = se2_compose(slam.pose[:, col], delta)
        prior = sandwich(jac, cov)
    p, i, slot = matches(slam, robot, z, r, ids)
    if p.size == 0:
        slam.pose[:, col] += (sqrt_psd(prior) @ slam.rng.standard_normal((n, 3, 1)))[..., 0]
        slam.pose[:, col, 2] = wrap_angle(slam.pose[:, col, 2])
        return False
    m = z.shape[0]
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
    slam.pose[:, col] += shift + (sqrt_psd(post) @ slam.rng.standard_normal((n, 3, 1)))[..., 0]
    slam.pose[:, col, 2] = wrap_angle(slam.pose[:, col, 2])
    _, logdet = np.linalg.slogdet(s)
    matched = np.bincount(p, minlength=n)
    slam.logw += -0.5 * np.einsum("pi,pij,pj->p", nu, s_inv, nu) - 0.5 * logdet - LOG_2PI * matched
    return True


def matches(slam: FastSlam, robot: RobotState, z, r, ids) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(particle, detection, slot) of the detections that match an existing landmark at the current poses
    (at most one detection per landmark and particle)."""
    n = slam.pose.shape[0]
    if slam.config.association in ("known", "shared"):
        if ids is None:
            return _no_matches()
        _, first = np.unique(ids, return_index=True)
        det = np.array([j for j in np.sort(first) if ids[j] >= 0 and int(ids[j]) in slam.known_slots], np.int64)
        slots = np.array([slam.known_slots[int(ids[j])] for j in det], np.int64)
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


def _no_matches() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64)
