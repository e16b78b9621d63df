"""Negative evidence and landmark existence (unknown association only).

A landmark's existence score rises with each association and falls, by ln(1 − P_D·v), each time the landmark
is near and not associated (v: its visibility, the chance its detection falls inside the sensor's limits);
below ``exist_min`` it is deleted, so landmarks born of clutter die, while landmarks associated
``permanent_hits`` times are kept. The same ln(1 − P_D·v) weights the particle (negative information), and a
confirmed landmark statistically identical to one just associated is merged away.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from scipy.special import ndtr

from central.fastslam import kernels
from central.fastslam.lifecycle import RobotState
from robots.gaussian import inv2, quad2

if TYPE_CHECKING:
    from central.fastslam.association import ScanState
    from central.fastslam.core import FastSlam


def view_limits(slam: FastSlam, robot: RobotState) -> tuple[float, float, float]:
    """(min range, max range, half field of view; inf when all round) of the robot's sensor as the filter uses it:
    ``max_obs_range`` caps the range."""
    spec, cap = robot.info.sensor, slam.config.max_obs_range
    max_range = spec.max_range if cap is None else min(spec.max_range, cap)
    return float(spec.min_range), float(max_range), 0.5 * spec.fov if spec.fov < 2.0 * np.pi else np.inf


def visibility(zhat: np.ndarray, sigma_r, sigma_b, min_range: float, max_range: float, half_fov: float) -> np.ndarray:
    """The chance that a detection predicted at ``zhat`` ``(..., 2)`` with σ ``sigma_r``, ``sigma_b`` (scalars or of
    zhat's leading shape) falls inside the range limits and the field of view (inf: all round): soft edges."""
    visible = ndtr((max_range - zhat[..., 0]) / sigma_r) * ndtr((zhat[..., 0] - min_range) / sigma_r)
    if np.isfinite(half_fov):
        visible *= ndtr((half_fov - np.abs(zhat[..., 1])) / sigma_b)
    return visible


def negative_evidence(slam: FastSlam, robot: RobotState, scan: ScanState, r: np.ndarray) -> None:
    """Weigh particles and age landmarks by the candidates near the robot that this scan did not associate.

    Each has a visibility v ∈ [0, 1]: the probability that its detection would fall inside the sensor's
    range limits and field of view, given the sensor noise (soft edges, no hard margin). The particle is
    weighted by (1 − P_D·v) for each (``miss_weight``: the price of a landmark that should have been seen;
    this is what makes duplicates and clutter-born landmarks lose), the landmark's existence score moves by
    ``exist_miss``·ln(1 − P_D·v), and landmarks below ``exist_min`` are deleted unless associated
    ``permanent_hits`` times (a map built over many scans is not erased because the pose is briefly wrong at
    a loop closure). With a sensor that often misses landmarks (a low P_D), a miss costs little.
    """
    config = slam.config
    k = scan.k_view
    if k == 0:
        return
    spec = robot.info.sensor
    sigma_r, sigma_b = np.sqrt(np.diag(r))
    p_detect = spec.detection_probability if config.detection_probability is None else config.detection_probability
    limits = np.array([*view_limits(slam, robot), sigma_r, sigma_b,
                       min(p_detect, config.max_detection_probability), config.exist_miss, config.exist_min,
                       np.inf if config.permanent_hits is None else config.permanent_hits])
    considered = scan.mask[:, :k] & ~scan.hit[:, :k]
    cand, zhat = np.ascontiguousarray(scan.cand[:, :k]), np.ascontiguousarray(scan.terms[0][:, :k])
    weigh = kernels.negative_evidence_kernel if config.compiled else negative_evidence_reference
    log_miss = weigh(cand, zhat, considered, limits, slam.map.exist, slam.map.hits, slam.map.valid)
    if config.miss_weight:
        slam.logw += log_miss[:-1]
    slam.counts["landmarks_deleted"] += int(log_miss[-1])


def negative_evidence_reference(cand: np.ndarray, zhat: np.ndarray, considered: np.ndarray, limits: np.ndarray,
                                exist: np.ndarray, hits: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """The numpy reference of :func:`central.fastslam.kernels.negative_evidence_kernel`.

    ``cand`` ``(P, k)``: the slots of the candidates in view, ``zhat`` ``(P, k, 2)`` their predicted detections,
    ``considered`` those neither masked out nor associated; ``limits``: (min range, max range, half field of view
    (inf: all round), σ_r, σ_φ, P_D, exist_miss, exist_min, permanent_hits (inf: none)). Ages ``exist`` and clears
    ``valid`` in place; returns ``(P + 1,)``: each particle's Σ ln(1 − P_D·v), then the number of landmarks deleted.
    """
    min_range, max_range, half_fov, sigma_r, sigma_b, p_detect, exist_miss, exist_min, permanent = limits
    visible = np.where(considered, visibility(zhat, sigma_r, sigma_b, min_range, max_range, half_fov), 0.0)
    log_miss = np.log1p(-p_detect * visible)
    rows, cols = np.nonzero(visible > 0.01)
    slots = cand[rows, cols]
    exist[rows, slots] += exist_miss * log_miss[rows, cols]
    dead = (exist[rows, slots] < exist_min) & (hits[rows, slots] < permanent)
    valid[rows[dead], slots[dead]] = False
    return np.append(log_miss.sum(1), dead.sum())


def merge_duplicates(slam: FastSlam, scan: ScanState) -> None:
    """Delete a confirmed landmark that is statistically the same as one associated in this scan.

    Suspects are the rivals: landmarks that a detection gated but did not pick. Two landmarks of one particle
    whose means differ by less than the χ² gate of Σ₁ + Σ₂ are one landmark seen twice (split hypotheses can
    leave both alive, each taking every other detection); the one with fewer associations goes. Two real
    landmarks that close cannot both be confirmed with covariances that small, so separate close beacons stay.
    """
    particle = np.arange(scan.cand.shape[0])[:, None]
    hits = slam.map.hits[particle, scan.cand]
    confirmed = scan.mask & (hits >= slam.config.confirm_hits)
    p, j = np.nonzero(scan.rival & confirmed & ~scan.hit)
    if p.size == 0:
        return
    rows, cols = np.nonzero(scan.hit & confirmed)
    if rows.size == 0:
        return
    rank = np.arange(rows.size) - np.searchsorted(rows, rows)
    hit_col = np.full((scan.cand.shape[0], int(rank.max()) + 1), -1, np.int64)
    hit_col[rows, rank] = cols
    pair_p = np.repeat(p, hit_col.shape[1])
    pair_j = np.repeat(j, hit_col.shape[1])
    pair_i = hit_col[p].ravel()
    keep = pair_i >= 0
    pair_p, pair_i, pair_j = pair_p[keep], pair_i[keep], pair_j[keep]
    slot_i, slot_j = scan.cand[pair_p, pair_i], scan.cand[pair_p, pair_j]
    fi, fj = slam.map.flat(pair_p, slot_i), slam.map.flat(pair_p, slot_j)
    means, covs = slam.map.mean_rows(), slam.map.cov_rows()
    close = quad2(means[fi] - means[fj], inv2(covs[fi] + covs[fj])[0]) < slam.gate
    hits_i, hits_j = hits[pair_p, pair_i], hits[pair_p, pair_j]
    drop = close & ((hits_j < hits_i) | ((hits_j == hits_i) & (slot_j > slot_i)))
    valid = slam.map.valid.reshape(-1)
    slam.counts["landmarks_merged"] += int(np.unique(fj[drop][valid[fj[drop]]]).size)
    valid[fj[drop]] = False
