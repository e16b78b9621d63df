"""Centralised multi-robot FastSLAM with per-particle data association (paper 001).

Each particle holds the pose of every robot that has joined and one shared
landmark map with an EKF per landmark (paper 001, eq. 6-8). Robots' streams
arrive in time order; a robot's controls are buffered and integrated once per
scan (:func:`robots.models.integrate_controls`), then the scan updates every particle:

- ``known``: landmark ids given; every particle updates the same landmarks.
- ``nn``: per particle, the maximum-likelihood landmark inside the χ² gate
  (eq. 10); a detection outside the wider new-landmark gate of every landmark
  starts a new one; one in between is ignored. Detections of one scan are
  processed with sequential semantics (a detection sees the landmarks the
  earlier ones of the same scan created or updated) but in vectorised rounds:
  a detection waits for the next round only if an earlier one in the same
  particle picked the same landmark or started a new landmark near it.
- ``mht``: paper 001's split: each particle becomes one child per gated
  landmark, one for a new landmark and one for a spurious detection (n+2),
  weighted by their likelihoods; children far below their parent's best are
  pruned, and the set goes back to N particles by systematic resampling (at
  the end of the scan, or sooner when it grows past ``mht_max_factor``·N).

Weights: an update contributes its innovation likelihood N(ν; 0, S), S = H Σ Hᵀ
+ R (the cost ½ νᵀS⁻¹ν + ½ ln|2πS| of DESIGN §4, with the right sign). A new or
ignored detection contributes the likelihood at the new-landmark gate of a
landmark known to sensor precision, −½ χ²_new − ½ ln|2πR|: a particle never
gains by calling a detection new rather than matching it.
MHT shares that weight between its new-landmark and spurious children in the
ratio of expected new landmarks to false detections per scan.

Landmark existence (unknown association only): a score that rises with each
association and falls, by ln(1 − P_D·v), each time the landmark is near and
not associated (v: its visibility, the chance its detection falls inside the
sensor's limits); below ``exist_min`` it is deleted, so landmarks born of
clutter die. Landmarks associated ``permanent_hits`` times are kept. The same
ln(1 − P_D·v) weights the particle (negative information), and a confirmed
landmark statistically identical to one just associated is merged away.

Robot-to-robot detections are ignored unless ``robot_detections``: they then
weight each particle by the likelihood of the detection given the two robots'
poses in that particle (no map update).
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field

import numpy as np
from scipy.special import ndtr
from scipy.stats import chi2

from central.fastslam.config import FastSlamConfig
from central.fastslam.gaussian import LOG_2PI, inv2, quad2, sandwich, sandwich2, sqrt_psd, systematic_resample, valid_cov2
from central.fastslam.landmarks import LandmarkMap
from robots.dataset import OdomEvent, ScanEvent
from robots.models import (MotionModel, RangeBearingSensor, compose_jacobian, integrate_controls, motion_model,
                           se2_compose, wrap_angle)
from schemas.messages import RobotInfo
from services.estimator import MapView


@dataclass
class RobotSlot:
    """A robot inside the filter: its column in the pose array, models, and buffered controls."""

    index: int
    info: RobotInfo
    model: MotionModel
    sensor: RangeBearingSensor
    controls: list = field(default_factory=list)
    dts: list = field(default_factory=list)
    covs: list = field(default_factory=list)
    pending_s: float = 0.0
    pose_time: float | None = None
    last_control: np.ndarray | None = None
    last_cov: np.ndarray | None = None
    last_odom_stamp: float = -np.inf
    last_scan_stamp: float = -np.inf
    checked_cov: object = None  # the control covariance last validated (by identity) and its scaled copy
    scaled_cov: np.ndarray | None = None

    @property
    def robot_id(self) -> str:
        return self.info.robot_id


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


def _sensor(info: RobotInfo) -> RangeBearingSensor:
    return RangeBearingSensor((float(info.sensor.offset[0]), float(info.sensor.offset[1])))


def _model(info: RobotInfo) -> MotionModel:
    if info.motion_model == "ackermann" and info.wheelbase > 0:
        return motion_model("ackermann", info.wheelbase, info.encoder_offset)
    return motion_model(info.motion_model)


def _valid_cov3(cov: np.ndarray) -> bool:
    return (cov.shape == (3, 3) and bool(np.all(np.isfinite(cov))) and np.allclose(cov, cov.T, atol=1e-9, rtol=1e-6)
            and bool(np.all(np.linalg.eigvalsh(cov) >= -1e-12)))


class FastSlam:
    """The central filter: ``add_robot``/``place_robot``, ``on_odometry``, ``on_scan``, ``poses``, ``landmark_map``.

    Bad input (wrong shapes, NaN, negative ranges, time going backwards, robots
    never announced or not yet placed) is counted in :attr:`rejected` and leaves
    the state untouched.
    """

    def __init__(self, config: FastSlamConfig, infos=()):
        self.config = config
        self.rng = np.random.default_rng(config.seed)
        n = config.particles
        self.pose = np.zeros((n, 0, 3))
        self.logw = np.zeros(n)
        self.map = LandmarkMap(n)
        self.robots: dict[str, RobotSlot] = {}
        self.parked: dict[str, RobotInfo] = {}
        self.known_slots: dict[int, int] = {}
        self.rejected: Counter = Counter()
        self.counts: Counter = Counter()
        self.gate = float(chi2.ppf(config.gate_probability, 2))
        self.new_gate = float(chi2.ppf(config.new_landmark_probability, 2))
        self.best_hint = 0
        self._scan: ScanState | None = None
        for info in infos:
            self.add_robot(info)

    # ------------------------------------------------------------------ robots
    def add_robot(self, info: RobotInfo) -> bool:
        """Take a robot with a known start pose in; park one without (see :meth:`place_robot`).

        Returns True when the robot joined the particles now. A robot already known is left as it is
        (robots republish their RobotInfo).
        """
        rid = info.robot_id
        if rid in self.robots or rid in self.parked:
            return False
        if info.start_pose is None:
            self.parked[rid] = info
            return False
        cov = np.zeros((3, 3)) if info.start_pose_cov is None else np.asarray(info.start_pose_cov, float)
        self._take_in(info, np.asarray(info.start_pose, float), cov)
        return True

    def place_robot(self, robot_id: str, pose, cov, stamp: float | None = None) -> bool:
        """Take a parked robot in at ``pose`` (3,), spreading the particles by ``cov`` (3, 3) (the localisation hook).

        ``stamp`` is the time the pose holds at: later controls move the robot from there, and its pose is
        reported at that time until they do (without it, from its next control's start)."""
        pose, cov = np.asarray(pose, float), np.asarray(cov, float)
        if robot_id not in self.parked:
            self.rejected["place_unknown_robot"] += 1
            return False
        if (pose.shape != (3,) or not np.all(np.isfinite(pose)) or not _valid_cov3(cov)
                or (stamp is not None and not math.isfinite(stamp))):
            self.rejected["bad_placement"] += 1
            return False
        self._take_in(self.parked.pop(robot_id), pose, cov)
        self.robots[robot_id].pose_time = None if stamp is None else float(stamp)
        return True

    def unplace(self, robot_id: str) -> RobotInfo | None:
        """Park a robot that has not moved in the filter yet (no control or scan applied): it waits for
        :meth:`place_robot`. Returns its RobotInfo, or None if it is unknown or already in use."""
        robot = self.robots.get(robot_id)
        if robot is None or robot.pose_time is not None:
            return None
        self.parked[robot_id] = self.remove_robot(robot_id)
        return robot.info

    def remove_robot(self, robot_id: str) -> RobotInfo | None:
        """Take a robot out of the filter, placed or parked (the landmarks it mapped stay); its RobotInfo."""
        if robot_id in self.parked:
            return self.parked.pop(robot_id)
        robot = self.robots.pop(robot_id, None)
        if robot is None:
            return None
        keep = [i for i in range(self.pose.shape[1]) if i != robot.index]
        self.pose = self.pose[:, keep]
        for other in self.robots.values():
            other.index = keep.index(other.index)
        return robot.info

    def _take_in(self, info: RobotInfo, pose: np.ndarray, cov: np.ndarray) -> None:
        n = self.pose.shape[0]
        start = pose + self.rng.standard_normal((n, 3)) @ sqrt_psd(cov).T
        start[:, 2] = wrap_angle(start[:, 2])
        self.pose = np.concatenate([self.pose, start[:, None, :]], 1)
        slot = RobotSlot(index=self.pose.shape[1] - 1, info=info, model=_model(info), sensor=_sensor(info))
        self.robots[info.robot_id] = slot

    def _robot(self, robot_id: str) -> RobotSlot | None:
        robot = self.robots.get(robot_id)
        if robot is None:
            self.rejected["robot_not_placed" if robot_id in self.parked else "unknown_robot"] += 1
        return robot

    # ------------------------------------------------------------------ motion
    def on_odometry(self, event: OdomEvent) -> bool:
        """Buffer one control; it is integrated with the others at the robot's next scan (or every ``max_batch_s``)."""
        robot = self._robot(event.robot_id)
        if robot is None:
            return False
        control = np.asarray(event.control, float)
        stamp, dt = float(event.stamp), float(event.dt)
        if (control.shape != (2,) or not (math.isfinite(control[0]) and math.isfinite(control[1]))
                or not (math.isfinite(dt) and 0.0 < dt <= 10.0) or not math.isfinite(stamp)):
            self.rejected["bad_odometry"] += 1
            return False
        if event.control_cov is not robot.checked_cov:  # a log passes one covariance object for all its controls
            cov = np.asarray(event.control_cov, float)
            if not valid_cov2(cov):
                self.rejected["bad_odometry"] += 1
                return False
            robot.checked_cov, robot.scaled_cov = event.control_cov, cov * self.config.motion_noise_scale
        if stamp < robot.last_odom_stamp:
            self.rejected["time_backwards"] += 1
            return False
        robot.last_odom_stamp = stamp
        start = stamp - dt
        if robot.pose_time is None:
            robot.pose_time = start
        if start - robot.pose_time > self.config.max_extrapolation_s:
            self.counts["odometry_gaps"] += 1
        span = min(stamp - robot.pose_time, dt + self.config.max_extrapolation_s)
        cov = robot.scaled_cov
        if span > 0.0:
            self._buffer(robot, control, span, cov)
        robot.pose_time = max(robot.pose_time, stamp)
        robot.last_control, robot.last_cov = control, cov
        if robot.pending_s >= self.config.max_batch_s:
            self._flush(robot)
        return True

    def _buffer(self, robot: RobotSlot, control: np.ndarray, span: float, cov: np.ndarray) -> None:
        robot.controls.append(control)
        robot.dts.append(span)
        robot.covs.append(cov)
        robot.pending_s += span

    def _pending_motion(self, robot: RobotSlot) -> tuple[np.ndarray, np.ndarray] | None:
        """(Δ̄, Σ_Δ) of the buffered controls in the start frame, or None if nothing is buffered."""
        if not robot.controls:
            return None
        delta, cov = integrate_controls(robot.model, np.array(robot.controls), np.array(robot.dts), np.array(robot.covs))
        cov = cov + np.diag(np.square(self.config.pose_noise_per_s)) * robot.pending_s
        return delta, cov

    def _clear(self, robot: RobotSlot) -> None:
        robot.controls, robot.dts, robot.covs, robot.pending_s = [], [], [], 0.0

    def _flush(self, robot: RobotSlot) -> None:
        """Apply the buffered controls: one draw per particle from N(Δ̄, Σ_Δ), composed onto its pose."""
        motion = self._pending_motion(robot)
        self._clear(robot)
        if motion is None:
            return
        delta, cov = motion
        noise = self.rng.standard_normal((self.pose.shape[0], 3)) @ sqrt_psd(cov).T
        self.pose[:, robot.index] = se2_compose(self.pose[:, robot.index], delta + noise)

    # ------------------------------------------------------------------ scans
    def on_scan(self, event: ScanEvent) -> bool:
        """Update every particle with one scan of one robot."""
        robot = self._robot(event.robot_id)
        if robot is None:
            return False
        ranges, bearings = np.asarray(event.ranges, float).ravel(), np.asarray(event.bearings, float).ravel()
        ids = None if event.landmark_ids is None else np.asarray(event.landmark_ids).ravel()
        noise = np.asarray(event.noise_cov, float)
        stamp = float(event.stamp)
        reason = self._check_scan(ranges, bearings, ids, noise, stamp)
        if reason is None and stamp < robot.last_scan_stamp:
            reason = "time_backwards"
        if reason is not None:
            self.rejected[reason] += 1
            return False
        robot.last_scan_stamp = stamp
        self._advance_to(robot, stamp)
        keep = ranges > 1e-6
        if self.config.max_obs_range is not None:
            keep &= ranges <= self.config.max_obs_range
        self.counts["detections_dropped"] += int((~keep).sum())
        z = np.stack([ranges[keep], wrap_angle(bearings[keep])], -1)
        ids = None if ids is None else ids[keep].astype(np.int64)
        r = noise * self.config.sensor_noise_scale
        self.counts["scans"] += 1
        self.counts["detections"] += z.shape[0]
        weigh_updates = True
        if self.config.proposal == "fastslam2" and z.shape[0]:
            weigh_updates = not self._propose(robot, z, r, ids)
        else:
            self._flush(robot)
        if self.config.association == "known":
            self._update_known(robot, z, r, ids, weigh_updates)
        elif z.shape[0]:
            self._update_unknown(robot, z, r, ids, weigh_updates)
        if self.config.robot_detections and len(event.robot_ids):
            self._weigh_robot_detections(robot, event, r)
        self._normalise_and_resample()
        return True

    def _check_scan(self, ranges, bearings, ids, noise, stamp) -> str | None:
        if ranges.shape != bearings.shape or (ids is not None and ids.shape != ranges.shape):
            return "bad_scan_shape"
        if not (np.all(np.isfinite(ranges)) and np.all(np.isfinite(bearings)) and np.isfinite(stamp)):
            return "bad_scan_values"
        if np.any(ranges < 0):
            return "negative_range"
        if ids is not None and ids.dtype.kind not in "iu":
            return "bad_scan_ids"
        if not valid_cov2(noise) or noise[0, 0] * noise[1, 1] - noise[0, 1] ** 2 <= 0:
            return "bad_scan_noise"
        return None

    def _advance_to(self, robot: RobotSlot, stamp: float) -> None:
        """Extend the last control up to the scan stamp (by at most ``max_extrapolation_s``)."""
        if robot.pose_time is None:
            robot.pose_time = stamp
            return
        if stamp > robot.pose_time and robot.last_control is not None:
            span = min(stamp - robot.pose_time, self.config.max_extrapolation_s)
            self._buffer(robot, robot.last_control, span, robot.last_cov)
        robot.pose_time = max(robot.pose_time, stamp)

    # ---------------------------------------------------------- EKF per landmark
    def _ekf_terms(self, robot: RobotSlot, p: np.ndarray, slot: np.ndarray, r: np.ndarray) -> tuple:
        """(ẑ, H, S, S⁻¹, |S|) of landmark ``slot`` seen from particle ``p`` (broadcast over any leading shape)."""
        pose = self.pose[p, robot.index]
        flat = self.map.flat(p, slot)
        zhat, h = robot.sensor.observe_with_jacobian(pose, self.map.mean_rows()[flat])
        s = sandwich2(h, self.map.cov_rows()[flat]) + r
        s_inv, det = inv2(s)
        return zhat, h, s, s_inv, det

    def _ekf_update(self, robot: RobotSlot, p: np.ndarray, z: np.ndarray, slot: np.ndarray, r: np.ndarray,
                    terms: tuple | None = None) -> np.ndarray:
        """Update landmark ``slot`` of particle ``p`` with detection ``z`` (one pair per row); returns log N(ν; 0, S).

        ``terms`` are the (ẑ, H, S, S⁻¹, |S|) of these pairs if already computed by the association.
        """
        zhat, h, s, s_inv, det = terms if terms is not None else self._ekf_terms(robot, p, slot, r)
        flat = self.map.flat(p, slot)
        means, covs = self.map.mean_rows(), self.map.cov_rows()
        exist, hits = self.map.exist.reshape(-1), self.map.hits.reshape(-1)
        sig = covs[flat]
        nu = robot.sensor.innovation(z, zhat)
        gain = sig @ np.swapaxes(h, -1, -2) @ s_inv
        means[flat] += (gain @ nu[..., None])[..., 0]
        covs[flat] = sig - sandwich2(gain, s)
        exist[flat] = np.minimum(exist[flat] + self.config.exist_hit, self.config.exist_max)
        hits[flat] += 1
        return -0.5 * quad2(nu, s_inv) - 0.5 * np.log(np.maximum(det, 1e-300)) - LOG_2PI

    def _create(self, robot: RobotSlot, p: np.ndarray, z: np.ndarray, r: np.ndarray, label: np.ndarray) -> np.ndarray:
        """New landmarks at the inverse observation of ``z`` from particle ``p``'s pose (``p`` sorted); returns slots."""
        pose = self.pose[p, robot.index]
        mean = robot.sensor.inverse(pose, z)
        _, g = robot.sensor.inverse_jacobians(pose, z)
        self.counts["landmarks_created"] += p.size
        return self.map.append(p, mean, sandwich2(g, r), self.config.exist_init, label)

    # ------------------------------------------------------- known association
    def _update_known(self, robot: RobotSlot, z, r, ids, weigh: bool) -> None:
        if ids is None:
            self.counts["scans_without_ids"] += 1
            return
        identified = ids >= 0
        self.counts["detections_unidentified"] += int((~identified).sum())
        z, ids = z[identified], ids[identified]
        if not ids.size:
            return
        order = np.argsort(ids, kind="stable")
        first = np.searchsorted(ids[order], ids[order])
        occurrence = np.empty(ids.size, np.int64)
        occurrence[order] = np.arange(ids.size) - first
        n = self.pose.shape[0]
        for k in range(int(occurrence.max()) + 1):
            zk, idk = z[occurrence == k], ids[occurrence == k]
            known = np.array([int(i) in self.known_slots for i in idk], bool)
            if known.any():
                slots = np.array([self.known_slots[int(i)] for i in idk[known]])
                m = slots.size
                p = np.repeat(np.arange(n), m)
                ll = self._ekf_update(robot, p, np.tile(zk[known], (n, 1)), np.tile(slots, n), r)
                if weigh:
                    self.logw += ll.reshape(n, m).sum(1)
            if (~known).any():
                fresh_ids, fresh_z = idk[~known], zk[~known]
                self.map.reserve(fresh_ids.size, compact=False)
                base = int(self.map.used[0])
                for j, lid in enumerate(fresh_ids):
                    self.known_slots[int(lid)] = base + j
                p = np.repeat(np.arange(n), fresh_ids.size)
                self._create(robot, p, np.tile(fresh_z, (n, 1)), r, np.tile(fresh_ids, n))

    # ----------------------------------------------------- unknown association
    def _candidates(self, robot: RobotSlot, extra: int, r: np.ndarray) -> ScanState:
        """Landmarks each particle could see now (within reach of the sensor's range and field of view, with a
        margin for the noise), padded to a common width."""
        pose = self.pose[:, robot.index]
        width = int(self.map.used.max(initial=0))
        position, _ = robot.sensor.sensor_position(pose)
        delta = self.map.mean[:, :width] - position[:, None, :]
        reach = robot.info.sensor.max_range if self.config.max_obs_range is None else self.config.max_obs_range
        reach = reach + 3.0 * float(np.sqrt(r[0, 0])) + 1.0
        distance2 = np.einsum("pkj,pkj->pk", delta, delta)
        near = self.map.valid[:, :width] & (distance2 < reach * reach)
        half_view = 0.5 * robot.info.sensor.fov + 3.0 * float(np.sqrt(r[1, 1])) + 0.2
        if half_view < np.pi:
            ahead = delta[..., 0] * np.cos(pose[:, 2])[:, None] + delta[..., 1] * np.sin(pose[:, 2])[:, None]
            near &= (ahead >= np.cos(half_view) * np.sqrt(distance2)) | (distance2 < 1.0)
        rows, cols = np.nonzero(near)
        k_view = int(near.sum(1).max(initial=0))
        n = self.pose.shape[0]
        cand = np.zeros((n, k_view + extra), np.int64)
        mask = np.zeros((n, k_view + extra), bool)
        position_in_row = np.arange(rows.size) - np.searchsorted(rows, rows)
        cand[rows, position_in_row] = cols
        mask[rows, position_in_row] = True
        return ScanState(cand, mask, np.zeros_like(mask), np.zeros_like(mask), k_view)

    def _score(self, robot: RobotSlot, scan: ScanState, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(d² ``(P, m, K)``, log N(ν; 0, S) ``(P, m, K)``) of detections ``z (m, 2)`` against every candidate.

        Call after :meth:`_prepare`, which computed the candidates' (ẑ, H, S, S⁻¹, |S|).
        """
        zhat, _, _, s_inv, det = scan.terms
        nu = z[None, :, None, :] - zhat[:, None, :, :]
        nu[..., 1] = wrap_angle(nu[..., 1])
        d2 = quad2(nu, s_inv[:, None])
        ll = -0.5 * d2 - 0.5 * np.log(np.maximum(det, 1e-300))[:, None, :] - LOG_2PI
        return d2, ll

    def _prepare(self, robot: RobotSlot, scan: ScanState, r: np.ndarray) -> None:
        """Compute (ẑ, H, S, S⁻¹, |S|) of every candidate at the current poses and landmark estimates."""
        rows = np.arange(scan.cand.shape[0])[:, None]
        scan.terms = self._ekf_terms(robot, rows, scan.cand, r)

    def _new_log_likelihood(self, r: np.ndarray) -> float:
        """Weight of a new (or ignored) detection: the likelihood at the new-landmark gate of a landmark known to
        sensor precision (so no particle gains by calling a detection new rather than matching it)."""
        return -0.5 * self.new_gate - 0.5 * float(np.log(np.linalg.det(r))) - LOG_2PI

    def _unexplained_split(self, robot: RobotSlot, r: np.ndarray) -> tuple[float, float]:
        """MHT weights of the new-landmark and spurious children of one detection.

        Together they carry the weight of an unexplained detection (:meth:`_new_log_likelihood`, as in NN), shared
        in the ratio of the expected new landmarks per scan λ_n to the expected false detections per scan λ_c.
        Clutter that does become a landmark is removed later by the existence score.
        """
        clutter = robot.info.sensor.clutter_rate if self.config.clutter_rate is None else self.config.clutter_rate
        fresh = self.config.new_landmark_rate
        unexplained = self._new_log_likelihood(r)
        spurious = unexplained + np.log(clutter / (clutter + fresh)) if clutter > 0 else -np.inf
        return unexplained + float(np.log(fresh / (clutter + fresh))), float(spurious)

    def _update_unknown(self, robot: RobotSlot, z, r, ids, weigh: bool) -> None:
        n = z.shape[0]
        self.map.reserve(n)
        self._scan = scan = self._candidates(robot, n, r)
        labels = np.full(n, -1, np.int64) if ids is None else ids
        try:
            if self.config.association == "nn":
                self._nearest_neighbour(robot, scan, z, r, labels, weigh)
            else:
                self._multiple_hypotheses(robot, scan, z, r, labels)
            self._negative_evidence(robot, scan, r)
            if self.config.merge_duplicates:
                self._merge_duplicates(scan)
            if self.pose.shape[0] != self.config.particles:
                self._resample(self.config.particles)
        finally:
            self._scan = None

    def _near_pairs(self, robot: RobotSlot, scan: ScanState, z: np.ndarray, r: np.ndarray, available: np.ndarray):
        """(particle, detection, candidate, d², log N) of the pairs that may pass the new-landmark gate.

        A cheap Cartesian pre-test keeps the work O(pairs) instead of O(P·m·K): with y the detection projected
        from the particle's pose, d² ≥ |y − μ|² / (tr Σ + σ_r² + r²σ_φ²) (the largest eigenvalue of the
        innovation covariance in the landmark plane), so pairs farther than that bound (×1.5 for the
        linearisation) cannot pass; the rest get the exact d² from the candidates' (ẑ, S⁻¹, |S|).
        """
        pose = self.pose[:, robot.index]
        particle = np.arange(pose.shape[0])[:, None]
        flat = self.map.flat(particle, scan.cand)
        mean = self.map.mean_rows()[flat]
        spread = np.einsum("pkii->pk", self.map.cov_rows()[flat])
        y = robot.sensor.inverse(pose[:, None, :], z[None])
        dx = y[:, :, None, 0] - mean[:, None, :, 0]
        dy = y[:, :, None, 1] - mean[:, None, :, 1]
        sensor_var = r[0, 0] + z[:, 0] ** 2 * r[1, 1]
        bound = 1.5 * self.new_gate * (spread[:, None, :] + sensor_var[None, :, None])
        p, i, k = np.nonzero(available[:, None, :] & (dx * dx + dy * dy < bound))
        zhat, _, _, s_inv, det = scan.terms
        nu = z[i] - zhat[p, k]
        nu[:, 1] = wrap_angle(nu[:, 1])
        d2 = quad2(nu, s_inv[p, k])
        ll = -0.5 * d2 - 0.5 * np.log(np.maximum(det[p, k], 1e-300)) - LOG_2PI
        return p, i, k, d2, ll

    def _nearest_neighbour(self, robot: RobotSlot, scan: ScanState, z, r, labels, weigh: bool) -> None:
        n_particles, n = self.pose.shape[0], z.shape[0]
        ll_new = self._new_log_likelihood(r)
        dz = z[:, None, :] - z[None, :, :]
        dz[..., 1] = wrap_angle(dz[..., 1])
        close = quad2(dz, inv2(2.0 * r)[0]) < self.new_gate
        pending = np.ones((n_particles, n), bool)
        while pending.any():
            self.counts["nn_rounds"] += 1
            cols = np.flatnonzero(pending.any(0))
            m = cols.size
            self._prepare(robot, scan, r)
            available = scan.mask & ~scan.used if self.config.exclusive else scan.mask
            p, i, k, d2, ll = self._near_pairs(robot, scan, z[cols], r, available)
            gated = d2 < self.gate
            key = p * m + i
            order = np.lexsort((-ll, ~gated, key))
            first = order[np.flatnonzero(np.r_[True, key[order][1:] != key[order][:-1]])] if key.size else order
            first = first[gated[first]]
            best = np.full((n_particles, m), -1, np.int64)
            best[p[first], i[first]] = k[first]
            has = best >= 0
            near = np.zeros((n_particles, m), bool)
            near[p[d2 < self.new_gate], i[d2 < self.new_gate]] = True
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
            ll_u = self._ekf_update(robot, p_u, z[cols[c_u]], scan.cand[p_u, k_u], r, scan.terms_at(p_u, k_u))
            scan.used[p_u, k_u] = scan.hit[p_u, k_u] = True
            p_n, c_n = np.nonzero(act & fresh)
            column = scan.k_view + cols[c_n]
            scan.cand[p_n, column] = self._create(robot, p_n, z[cols[c_n]], r, labels[cols[c_n]])
            scan.mask[p_n, column] = scan.used[p_n, column] = scan.hit[p_n, column] = True
            unexplained = (act & ~has).sum(1)
            self.counts["detections_ignored"] += int((act & ~has & ~fresh).sum())
            if weigh:
                self.logw += np.bincount(p_u, ll_u, n_particles)
            self.logw += ll_new * unexplained
            pending[:, cols] &= ~act

    def _multiple_hypotheses(self, robot: RobotSlot, scan: ScanState, z, r, labels) -> None:
        """Paper 001's MHT: per detection, split every particle into its gated, new and spurious children."""
        n = self.config.particles
        ll_new, ll_spurious = self._unexplained_split(robot, r)
        log_prune = float(np.log(self.config.mht_prune))
        for i in range(z.shape[0]):
            self._prepare(robot, scan, r)
            d2, ll = self._score(robot, scan, z[i:i + 1])
            d2, ll = d2[:, 0], ll[:, 0]
            available = scan.mask & ~scan.used if self.config.exclusive else scan.mask
            width = scan.cand.shape[1]
            hyp = np.empty((self.pose.shape[0], width + 2))
            gated = available & (d2 < self.gate)
            hyp[:, :width] = np.where(gated, ll, -np.inf)
            hyp[:, width], hyp[:, width + 1] = ll_new, ll_spurious
            best = hyp.max(1)
            keep = hyp >= (best + log_prune)[:, None]
            if np.all(keep.sum(1) == 1):
                choice = np.argmax(hyp, 1)
                self.logw += best
            else:
                parent, choice = np.nonzero(keep)
                child_logw = self.logw[parent] + hyp[parent, choice]
                gated = gated[parent]
                self._select(parent)
                self.logw = child_logw
                self.counts["mht_splits"] += 1
            p_u = np.flatnonzero(choice < width)
            k_u = choice[p_u]
            rivals = gated[p_u]
            rivals[np.arange(p_u.size), k_u] = False
            scan.rival[p_u] |= rivals
            self._ekf_update(robot, p_u, np.broadcast_to(z[i], (p_u.size, 2)), scan.cand[p_u, k_u], r,
                             scan.terms_at(p_u, k_u))
            scan.used[p_u, k_u] = scan.hit[p_u, k_u] = True
            p_n = np.flatnonzero(choice == width)
            column = scan.k_view + i
            scan.cand[p_n, column] = self._create(robot, p_n, np.broadcast_to(z[i], (p_n.size, 2)), r,
                                                  np.full(p_n.size, labels[i]))
            scan.mask[p_n, column] = scan.used[p_n, column] = scan.hit[p_n, column] = True
            self.counts["detections_spurious"] += int((choice == width + 1).sum())
            if self.pose.shape[0] > self.config.mht_max_factor * n:
                self._resample(n)

    def _negative_evidence(self, robot: RobotSlot, scan: ScanState, r: np.ndarray) -> None:
        """Landmarks near the robot and not associated in this scan.

        Each has a visibility v ∈ [0, 1]: the probability that its detection would fall inside the sensor's
        range limits and field of view, given the sensor noise (soft edges, no hard margin). The particle is
        weighted by (1 − P_D·v) for each (``miss_weight``: the price of a landmark that should have been seen;
        this is what makes duplicates and clutter-born landmarks lose), the landmark's existence score moves
        by ``exist_miss``·ln(1 − P_D·v), and landmarks below ``exist_min`` are deleted unless they have been
        associated ``permanent_hits`` times (a map built over many scans is not erased because the pose is
        briefly wrong at a loop closure). With a sensor that often misses landmarks (a low P_D), a miss costs little.
        """
        k = scan.k_view
        if k == 0:
            return
        spec = robot.info.sensor
        cand = scan.cand[:, :k]
        zhat = scan.terms[0][:, :k]
        max_range = spec.max_range if self.config.max_obs_range is None else min(spec.max_range, self.config.max_obs_range)
        sigma_r, sigma_b = np.sqrt(np.diag(r))
        visible = ndtr((max_range - zhat[..., 0]) / sigma_r) * ndtr((zhat[..., 0] - spec.min_range) / sigma_r)
        if spec.fov < 2.0 * np.pi:
            visible *= ndtr((0.5 * spec.fov - np.abs(zhat[..., 1])) / sigma_b)
        visible = np.where(scan.mask[:, :k] & ~scan.hit[:, :k], visible, 0.0)
        p_detect = spec.detection_probability if self.config.detection_probability is None else self.config.detection_probability
        log_miss = np.log1p(-min(p_detect, self.config.max_detection_probability) * visible)
        if self.config.miss_weight:
            self.logw += log_miss.sum(1)
        rows, cols = np.nonzero(visible > 0.01)
        slots = cand[rows, cols]
        self.map.exist[rows, slots] += self.config.exist_miss * log_miss[rows, cols]
        dead = self.map.exist[rows, slots] < self.config.exist_min
        if self.config.permanent_hits is not None:
            dead &= self.map.hits[rows, slots] < self.config.permanent_hits
        self.map.valid[rows[dead], slots[dead]] = False
        self.counts["landmarks_deleted"] += int(dead.sum())

    def _merge_duplicates(self, scan: ScanState) -> None:
        """Delete a confirmed landmark that is statistically the same as one associated in this scan.

        Suspects are the rivals: landmarks that a detection gated but did not pick. Two landmarks of one
        particle whose means differ by less than the χ² gate of Σ₁ + Σ₂ are one landmark seen twice (split
        hypotheses can leave both alive, each taking every other detection); the one with fewer associations
        goes. Two real landmarks that close cannot both be confirmed with covariances that small, so separate
        close beacons stay.
        """
        particle = np.arange(scan.cand.shape[0])[:, None]
        hits = self.map.hits[particle, scan.cand]
        confirmed = scan.mask & (hits >= self.config.confirm_hits)
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
        fi, fj = self.map.flat(pair_p, slot_i), self.map.flat(pair_p, slot_j)
        means, covs = self.map.mean_rows(), self.map.cov_rows()
        close = quad2(means[fi] - means[fj], inv2(covs[fi] + covs[fj])[0]) < self.gate
        hits_i, hits_j = hits[pair_p, pair_i], hits[pair_p, pair_j]
        drop = close & ((hits_j < hits_i) | ((hits_j == hits_i) & (slot_j > slot_i)))
        valid = self.map.valid.reshape(-1)
        self.counts["landmarks_merged"] += int(np.unique(fj[drop][valid[fj[drop]]]).size)
        valid[fj[drop]] = False

    # ------------------------------------------------------- FastSLAM 2.0
    def _propose(self, robot: RobotSlot, z, r, ids) -> bool:
        """FastSLAM 2.0: sample each particle's pose from the motion prior conditioned on this scan's matches.

        Matches are taken at the predicted mean pose (known ids, or the gated maximum-likelihood landmark).
        The proposal is the Kalman update of N(x̂, P) by every matched detection at once; the particle is
        weighted by the joint marginal N(ν; 0, H_x P H_xᵀ + Q), Q = H_m Σ H_mᵀ + R (Montemerlo et al. 2003).
        Returns True when the weights of matched detections were set here (the updates must not add them again).
        """
        motion = self._pending_motion(robot)
        self._clear(robot)
        col = robot.index
        n = self.pose.shape[0]
        if motion is None:
            prior = np.zeros((n, 3, 3))
        else:
            delta, cov = motion
            jac = compose_jacobian(self.pose[:, col, 2])
            self.pose[:, col] = se2_compose(self.pose[:, col], delta)
            prior = sandwich(jac, cov)
        p, i, slot = self._matches(robot, z, r, ids)
        if p.size == 0:
            self.pose[:, col] += (sqrt_psd(prior) @ self.rng.standard_normal((n, 3, 1)))[..., 0]
            self.pose[:, col, 2] = wrap_angle(self.pose[:, col, 2])
            return False
        m = z.shape[0]
        pose = self.pose[p, col]
        mu, sig = self.map.mean[p, slot], self.map.cov[p, slot]
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
        self.pose[:, col] += shift + (sqrt_psd(post) @ self.rng.standard_normal((n, 3, 1)))[..., 0]
        self.pose[:, col, 2] = wrap_angle(self.pose[:, col, 2])
        _, logdet = np.linalg.slogdet(s)
        matched = np.bincount(p, minlength=n)
        self.logw += -0.5 * np.einsum("pi,pij,pj->p", nu, s_inv, nu) - 0.5 * logdet - LOG_2PI * matched
        return True

    def _matches(self, robot: RobotSlot, z, r, ids) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(particle, detection, slot) of the detections that match an existing landmark at the current poses."""
        n = self.pose.shape[0]
        if self.config.association == "known":
            if ids is None:
                return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64)
            _, first = np.unique(ids, return_index=True)
            det = np.array([j for j in np.sort(first) if ids[j] >= 0 and int(ids[j]) in self.known_slots], np.int64)
            slots = np.array([self.known_slots[int(ids[j])] for j in det], np.int64)
            return np.repeat(np.arange(n), det.size), np.tile(det, n), np.tile(slots, n)
        self.map.reserve(z.shape[0])
        scan = self._candidates(robot, 0, r)
        if scan.k_view == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64)
        self._prepare(robot, scan, r)
        d2, ll = self._score(robot, scan, z)
        gated = scan.mask[:, None, :] & (d2 < self.gate)
        best = np.argmax(np.where(gated, ll, -np.inf), 2)
        p, i = np.nonzero(gated.any(2))
        k = best[p, i]
        slot = scan.cand[p, k]
        unique = np.ones(p.size, bool)
        key = p * scan.cand.shape[1] + k
        _, first = np.unique(key, return_index=True)
        unique[:] = False
        unique[first] = True
        return p[unique], i[unique], slot[unique]

    # ------------------------------------------------------- robot detections
    def _weigh_robot_detections(self, robot: RobotSlot, event: ScanEvent, r: np.ndarray) -> None:
        """Weight particles by robot-to-robot detections: N(z; h(x_i, x_j), R + H_j Σ_j H_jᵀ), no map update."""
        pose = self.pose[:, robot.index]
        for other_id, rng_, brg in zip(event.robot_ids, np.asarray(event.robot_ranges, float),
                                       np.asarray(event.robot_bearings, float)):
            other = self.robots.get(other_id)
            if other is None or other is robot or other.pose_time is None:
                self.counts["robot_detections_unused"] += 1
                continue
            if abs(other.pose_time - float(event.stamp)) > self.config.robot_detection_max_dt:
                self.counts["robot_detections_unused"] += 1
                continue
            target = self.pose[:, other.index]
            spread = np.zeros((self.pose.shape[0], 3, 3))
            motion = self._pending_motion(other)
            if motion is not None:
                spread = sandwich(compose_jacobian(target[:, 2]), motion[1])
                target = se2_compose(target, motion[0])
            zhat = robot.sensor.observe(pose, target[:, :2])
            _, h_lm = robot.sensor.jacobians(pose, target[:, :2])
            s = sandwich2(h_lm, spread[:, :2, :2]) + r
            s_inv, det = inv2(s)
            nu = robot.sensor.innovation(np.array([rng_, brg]), zhat)
            self.logw += -0.5 * quad2(nu, s_inv) - 0.5 * np.log(np.maximum(det, 1e-300)) - LOG_2PI
            self.counts["robot_detections_used"] += 1

    # ------------------------------------------------------- weights
    def _select(self, index: np.ndarray) -> None:
        self.pose = self.pose[index]
        self.logw = self.logw[index]
        self.map.select(index)
        if self._scan is not None:
            self._scan.select(index)

    def weights(self) -> np.ndarray:
        """Normalised particle weights."""
        finite = np.isfinite(self.logw)
        if not finite.any():
            return np.full(self.logw.size, 1.0 / self.logw.size)
        w = np.where(finite, np.exp(self.logw - self.logw[finite].max()), 0.0)
        return w / w.sum()

    def effective_particles(self) -> float:
        w = self.weights()
        return float(1.0 / np.sum(w * w))

    def _resample(self, count: int) -> None:
        w = self.weights()
        index = systematic_resample(w, count, self.rng)
        best = int(np.argmax(w))
        self._select(index)
        self.logw = np.zeros(count)
        hits = np.flatnonzero(index == best)
        self.best_hint = int(hits[0]) if hits.size else 0
        self.counts["resamples"] += 1

    def _normalise_and_resample(self) -> None:
        finite = np.isfinite(self.logw)
        if not finite.any():
            self.logw = np.zeros(self.logw.size)
            self.counts["degenerate_weights"] += 1
            return
        self.logw = np.where(finite, self.logw - self.logw[finite].max(), -np.inf)
        if self.effective_particles() < self.config.resample_ess * self.logw.size:
            self._resample(self.config.particles)

    # ------------------------------------------------------- estimates
    def best_particle(self) -> int:
        """The highest-weight particle (after a resampling: a child of the heaviest particle before it)."""
        w = self.weights()
        if w.max() - w.min() < 1e-12:
            return min(self.best_hint, w.size - 1)
        return int(np.argmax(w))

    def poses(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Every placed robot's weighted mean pose and covariance (buffered controls included, no draw)."""
        w = self.weights()
        out = {}
        for rid, robot in self.robots.items():
            pose = self.pose[:, robot.index]
            extra = np.zeros((3, 3))
            motion = self._pending_motion(robot)
            if motion is not None:
                extra = np.einsum("p,pij->ij", w, sandwich(compose_jacobian(pose[:, 2]), motion[1]))
                pose = se2_compose(pose, motion[0])
            theta = np.arctan2(w @ np.sin(pose[:, 2]), w @ np.cos(pose[:, 2]))
            mean = np.array([w @ pose[:, 0], w @ pose[:, 1], theta])
            resid = pose - mean
            resid[:, 2] = wrap_angle(resid[:, 2])
            cov = np.einsum("p,pi,pj->ij", w, resid, resid) + extra
            out[rid] = (mean, 0.5 * (cov + cov.T))
        return out

    def landmark_map(self):
        """Known association: the weighted mixture per landmark; otherwise the best particle's confirmed landmarks
        (associated at least ``confirm_hits`` times, and either permanent or with an existence score at least
        its initial value)."""
        if self.config.association == "known":
            if not self.known_slots:
                return MapView(np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros(0, np.int64))
            ids = np.array(list(self.known_slots.keys()), np.int64)
            slots = np.array(list(self.known_slots.values()), np.int64)
            w = self.weights()
            mu, sig = self.map.mean[:, slots], self.map.cov[:, slots]
            mean = np.einsum("p,pkj->kj", w, mu)
            resid = mu - mean
            cov = np.einsum("p,pkij->kij", w, sig) + np.einsum("p,pki,pkj->kij", w, resid, resid)
            return MapView(mean, cov, ids)
        p = self.best_particle()
        hits = self.map.hits[p]
        settled = self.map.exist[p] >= self.config.exist_init
        if self.config.permanent_hits is not None:
            settled |= hits >= self.config.permanent_hits
        keep = self.map.valid[p] & (hits >= self.config.confirm_hits) & settled
        return MapView(self.map.mean[p, keep].copy(), self.map.cov[p, keep].copy(), None)

    def extra_metrics(self) -> dict:
        """Figures ``fleetslam run`` adds to its JSON: the filter's counters and particle statistics."""
        return {"fastslam": self.stats()}

    def stats(self) -> dict[str, float]:
        """Counters and particle statistics (for the service's stats and the benchmarks)."""
        counts = self.map.counts()
        out = {
            "particles": float(self.pose.shape[0]),
            "effective_particles": self.effective_particles(),
            "robots": float(len(self.robots)),
            "robots_waiting": float(len(self.parked)),
            "landmarks_mean": float(counts.mean()) if counts.size else 0.0,
            "landmarks_best": float(counts[self.best_particle()]) if counts.size else 0.0,
            "map_capacity": float(self.map.capacity),
        }
        out.update({k: float(v) for k, v in self.counts.items()})
        out.update({f"rejected_{k}": float(v) for k, v in self.rejected.items()})
        return out
