"""EKF-SLAM, the "traditional SLAM" baseline (single robot, full covariance) of the association study (Zhang,
Xie, Adams, "An Efficient Data Association Approach to Simultaneous Localization and Map Building"; paper 000)
and of D-SLAM (Wang, Huang, Dissanayake, "Implementation Issues and Experimental Evaluation of D-SLAM").

State [x, y, θ, l1x, l1y, ...] with one dense covariance. Odometry predicts the
pose block and its cross-covariances; each scan is associated by
:func:`services.association.core.associate` (``options.association`` in
known, nn, greedy, ihgr, exact, jcbb, auto) on the predicted observations of
the landmarks near the sensor's view, with their joint covariance H P Hᵀ;
associated measurements update the state in one batch (Joseph form), and
measurements labelled NEW start landmarks by augmenting the state.

Where the data carries true landmark ids, every decision is scored (a
landmark remembers the true id of the measurement that started it):
:meth:`EkfSlam.extra_metrics` reports ``association_accuracy`` and, on
``sim:paper000``, ``success`` (paper 000 §IV-A) with the criterion
:data:`SUCCESS_CRITERION`.
"""

from __future__ import annotations

import logging

import numpy as np
from pydantic import Field

from robots.gaussian import ekf_augment, ekf_predict_pose, ekf_update
from robots.models import robot_models
from schemas.association import CLUTTER, NEW, AssociationRequest
from schemas.contract import CoreConfig, MapView, OdomEvent, RunOptions, ScanEvent, SettingsError, build_config
from schemas.messages import RobotInfo
from services.association.core import associate
from services.evaluation.metrics import association_accuracy

log = logging.getLogger(__name__)

SUCCESS_CRITERION = (
    "no wrong association during the run: no measurement of true landmark A is fused into a landmark started "
    "from a measurement of another landmark (or of clutter), and no landmark is started twice"
)
ASSOCIATIONS = ("known", "nn", "greedy", "ihgr", "exact", "jcbb", "auto")


class EkfConfig(CoreConfig):
    """Settings of the EKF-SLAM baseline (``fleetslam run --estimator ekf --set NAME=VALUE``)."""

    gate_probability: float = Field(0.999, gt=0, lt=1, description="chi-square gate of the association")
    new_feature_gate_probability: float = Field(0.999999, gt=0, lt=1, description="start a landmark only outside this gate of all")
    new_feature_density: float = Field(1e-3, gt=0, description="new landmarks per m·rad of measurement space")
    detection_probability_max: float = Field(0.99, gt=0, lt=1, description="cap on the sensor's detection probability")
    view_margin_m: float = Field(1.0, ge=0, description="landmarks this far beyond the maximum range are still candidates")
    view_margin_rad: float = Field(0.3, ge=0, description="and this far outside the field of view")


class EkfSlam:
    """Single-robot EKF-SLAM with pluggable data association."""

    def __init__(self, association: str = "known", config: EkfConfig | None = None):
        if association not in ASSOCIATIONS:
            raise SettingsError(f"unknown association {association!r}; choose from {', '.join(ASSOCIATIONS)}")
        self.method = association
        self.config = config or EkfConfig()
        self.info: RobotInfo | None = None
        self.x = np.zeros(3)
        self.P = np.zeros((3, 3))
        self.origin: list[int] = []  # true id of the measurement that started each landmark (-1 unknown)
        self.decisions = self.wrong = self.duplicates = self.rejected = 0
        self.true_ids: list[np.ndarray] = []  # per scored scan: true id of each detection
        self.labels: list[np.ndarray] = []  # and the landmark it went to (-1: rejected)
        self.scans = 0
        self.assoc_ms = 0.0

    # --- Estimator protocol ---------------------------------------------------------------

    def add_robot(self, info: RobotInfo) -> None:
        if self.info is not None:
            raise ValueError("the EKF-SLAM baseline is single-robot")
        self.info = info
        self.motion, self.sensor = robot_models(info)
        self.x = np.array(info.start_pose if info.start_pose is not None else np.zeros(3), float)
        self.P = np.array(info.start_pose_cov if info.start_pose_cov is not None else np.zeros((3, 3)), float)
        spec = info.sensor
        volume = max(spec.max_range - spec.min_range, 1e-6) * spec.fov
        self.clutter_density = spec.clutter_rate / volume
        self.detection_probability = min(max(spec.detection_probability, 0.01), self.config.detection_probability_max)

    def on_odometry(self, event: OdomEvent) -> None:
        if event.robot_id != self.info.robot_id:
            return
        ekf_predict_pose(self.x, self.P, self.motion, event.control, event.control_cov, event.dt)

    def on_scan(self, event: ScanEvent) -> None:
        z = event.observations
        if event.robot_id != self.info.robot_id or z.shape[0] == 0:
            return
        self.scans += 1
        noise = np.asarray(event.noise_cov, float)
        expected = self.sensor.observe(self.x[:3], self.x[3:].reshape(-1, 2))
        candidates = self._candidates(expected)
        if self.method == "known":
            assignment, candidates = self._known(event, candidates)
        predicted, h = expected[candidates], self._jacobian(candidates)
        if self.method != "known":
            assignment = self._associate(z, noise, predicted, h)
        labels = np.where(assignment >= 0, candidates[np.maximum(assignment, 0)] if candidates.size else -1, -1)
        if event.landmark_ids is not None:
            self._score(assignment, labels, event.landmark_ids)
        pairs = np.flatnonzero(assignment >= 0)
        if pairs.size:
            rows = (2 * assignment[pairs][:, None] + np.arange(2)).ravel()
            self._update(self.sensor.innovation(z[pairs], predicted[assignment[pairs]]).ravel(), h[rows], noise)
        for m in np.flatnonzero(assignment == NEW):
            origin = int(event.landmark_ids[m]) if event.landmark_ids is not None else -1
            labels[m] = self.landmark_count
            self._add_landmark(z[m], noise, origin)
        if event.landmark_ids is not None:
            self.true_ids.append(np.asarray(event.landmark_ids, np.int64))
            self.labels.append(labels)

    def poses(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        return {self.info.robot_id: (self.x[:3].copy(), self.P[:3, :3].copy())} if self.info else {}

    def landmark_map(self) -> MapView:
        n = self.landmark_count
        means = self.x[3:].reshape(n, 2).copy()
        covs = np.stack([self.P[3 + 2 * i:5 + 2 * i, 3 + 2 * i:5 + 2 * i] for i in range(n)]) if n else np.zeros((0, 2, 2))
        ids = np.asarray(self.origin, np.int64) if n else np.zeros(0, np.int64)
        return MapView(means=means, covs=covs, ids=ids)

    def extra_metrics(self) -> dict:
        """Association accuracy (where true ids exist) and, on sim:paper000, the study's success flag."""
        out: dict = {
            "association": self.method,
            "association_accuracy": self._accuracy(),
            "association_decisions": self.decisions,
            "wrong_associations": self.wrong,
            "duplicate_landmarks": self.duplicates,
            "rejected_measurements": self.rejected,
            "association_ms_per_scan": self.assoc_ms / self.scans if self.scans else 0.0,
        }
        if self.info is not None and self.info.source == "sim:paper000" and self.decisions:
            out["success"] = self.wrong == 0 and self.duplicates == 0
            out["success_criterion"] = SUCCESS_CRITERION
        return out

    def _accuracy(self) -> float | None:
        """Fraction of detections sent to the right landmark (majority-vote labels, :func:`association_accuracy`)."""
        if not self.true_ids:
            return None
        return association_accuracy(np.concatenate(self.true_ids), np.concatenate(self.labels))["accuracy"]

    # --- internals --------------------------------------------------------------------------

    @property
    def landmark_count(self) -> int:
        return (self.x.shape[0] - 3) // 2

    def _candidates(self, expected: np.ndarray) -> np.ndarray:
        """Indices of the landmarks whose predicted observations ``expected`` lie near the sensor's view."""
        spec = self.info.sensor
        near = (expected[:, 0] <= spec.max_range + self.config.view_margin_m) & (
            np.abs(expected[:, 1]) <= 0.5 * spec.fov + self.config.view_margin_rad
        )
        return np.flatnonzero(near)

    def _jacobian(self, landmarks: np.ndarray) -> np.ndarray:
        """The stacked Jacobian (2k, state) of the observations of the given landmarks."""
        k = landmarks.size
        h_pose, h_lm = self.sensor.jacobians(self.x[:3], self.x[3:].reshape(-1, 2)[landmarks])
        h = np.zeros((k, 2, self.x.shape[0]))
        h[:, :, :3] = h_pose
        cols = 3 + 2 * landmarks[:, None] + np.arange(2)
        h[np.arange(k)[:, None, None], np.arange(2)[None, :, None], cols[:, None, :]] = h_lm
        return h.reshape(2 * k, self.x.shape[0])

    def _associate(self, z: np.ndarray, noise: np.ndarray, predicted: np.ndarray, h: np.ndarray) -> np.ndarray:
        """Assignment (M,) of local candidate indices / NEW / CLUTTER from :func:`associate`.

        The joint covariance H P Hᵀ of the predicted observations goes with the
        request only for the methods that use it (jcbb, auto).
        """
        joint = h @ self.P @ h.T
        k = predicted.shape[0]
        blocks = joint.reshape(k, 2, k, 2)[np.arange(k), :, np.arange(k), :] if k else np.zeros((0, 2, 2))
        s = self.config
        request = AssociationRequest.model_construct(  # this filter's own well-formed arrays: no validation pass
            measurements=z, noise=noise, predicted=predicted, innovation_covs=blocks + noise,
            joint_cov=0.5 * (joint + joint.T) if self.method in ("jcbb", "auto") else None,
            gate_probability=s.gate_probability, new_feature_gate_probability=s.new_feature_gate_probability,
            clutter_density=self.clutter_density, new_feature_density=s.new_feature_density,
            detection_probability=self.detection_probability,
        )
        reply = associate(request, self.method)
        self.assoc_ms += reply.solve_time_ms
        return reply.assignment

    def _known(self, event: ScanEvent, candidates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(assignment, candidates) from the true ids: a mapped id is its landmark, an unmapped one NEW, -1 clutter."""
        if event.landmark_ids is None:
            raise ValueError("association 'known' needs true landmark ids in the scans")
        where = {o: j for j, o in enumerate(self.origin)}
        mapped = [where[int(t)] for t in event.landmark_ids if int(t) in where]
        candidates = np.union1d(candidates, np.asarray(mapped, np.int64))
        local = {int(j): k for k, j in enumerate(candidates)}
        assignment = np.full(event.landmark_ids.shape[0], CLUTTER, np.int64)
        for m, true_id in enumerate(event.landmark_ids.tolist()):
            if true_id >= 0:
                assignment[m] = local[where[true_id]] if true_id in where else NEW
        return assignment, candidates

    def _score(self, assignment: np.ndarray, labels: np.ndarray, true_ids: np.ndarray) -> None:
        """Count wrong associations and duplicate landmarks against the true ids (see :data:`SUCCESS_CRITERION`)."""
        mapped = set(self.origin)
        started: set[int] = set()
        for decision, label, true_id in zip(assignment.tolist(), labels.tolist(), true_ids.tolist()):
            self.decisions += 1
            if decision >= 0:
                self.wrong += true_id < 0 or self.origin[label] != true_id
            elif decision == NEW:
                self.wrong += true_id < 0
                self.duplicates += true_id >= 0 and (true_id in mapped or true_id in started)
                started.add(true_id)
            else:
                self.rejected += 1

    def _update(self, nu: np.ndarray, h: np.ndarray, noise: np.ndarray) -> None:
        """One batch EKF update with the stacked innovations ``nu`` and Jacobian rows ``h``."""
        self.x, self.P = ekf_update(self.x, self.P, nu, h, np.kron(np.eye(nu.shape[0] // 2), noise))

    def _add_landmark(self, z: np.ndarray, noise: np.ndarray, origin: int) -> None:
        """Augment the state with the landmark seen as ``z`` (its covariance from the pose and the noise)."""
        self.x, self.P = ekf_augment(self.x, self.P, self.sensor, z, noise)
        self.origin.append(origin)


def make_estimator(options: RunOptions, infos: list[RobotInfo]) -> EkfSlam:
    """Build the EKF-SLAM baseline for the first robot (``options.association`` picks the association method,
    ``options.settings`` are :class:`EkfConfig`'s).

    It is single-robot: given a fleet, it follows ``infos[0]`` and ignores the other robots' events.
    """
    if not infos:
        raise ValueError("the EKF-SLAM baseline needs one robot")
    if len(infos) > 1:
        log.warning("EKF-SLAM is single-robot: following %s, ignoring %s", infos[0].robot_id,
                    ", ".join(i.robot_id for i in infos[1:]))
    config = build_config(EkfConfig, options.settings, owner="ekf", given=set(options.settings))
    estimator = EkfSlam(options.association, config)
    estimator.add_robot(infos[0])
    return estimator

