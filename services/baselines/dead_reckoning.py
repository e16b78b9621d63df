"""Dead reckoning: the baseline every estimator must beat (registered as ``odometry``).

Each robot's pose is the composition of its controls through its own motion
model from its start pose (the origin when unknown); the covariance grows as
the EKF prediction P ← F P Fᵀ + G Q Gᵀ step after step would make it. Controls
are buffered and applied in one vectorised batch when a pose is needed (a scan,
a query): x ← x ⊕ Δ̄, P ← J_x P J_xᵀ + J_Δ Σ_Δ J_Δᵀ with (Δ̄, Σ_Δ) from
:func:`robots.models.integrate_controls`, which is exactly the
step-by-step result. Scans never correct anything.
When scans carry true landmark ids (and the association is ``known``), the
landmarks are placed from the dead-reckoned poses, averaged per id: the map a
robot would draw with no SLAM at all.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from robots.models import RangeBearingSensor, compose_jacobian, integrate_controls, robot_models, se2_compose
from schemas.contract import CoreConfig, MapView, OdomEvent, RunOptions, ScanEvent, SettingsError
from schemas.messages import RobotInfo


class DeadReckoningConfig(CoreConfig):
    """The dead-reckoning baseline: nothing a user sets (``make_estimator`` derives ``map_known_ids``)."""

    map_known_ids: bool = Field(True, description="place landmarks by the scans' true ids (with association known)")


class DeadReckoning:
    """Dead-reckoning estimator for any number of robots (see the module docstring)."""

    def __init__(self, config: DeadReckoningConfig | None = None):
        self.config = config or DeadReckoningConfig()
        self._models: dict = {}
        self._sensors: dict[str, RangeBearingSensor] = {}
        self._pose: dict[str, np.ndarray] = {}
        self._cov: dict[str, np.ndarray] = {}
        self._pending: dict[str, list[OdomEvent]] = {}
        self._landmark_sum: dict[int, np.ndarray] = {}
        self._landmark_cov_sum: dict[int, np.ndarray] = {}
        self._landmark_count: dict[int, int] = {}

    def add_robot(self, info: RobotInfo) -> None:
        rid = info.robot_id
        self._models[rid], self._sensors[rid] = robot_models(info)
        self._pose[rid] = np.zeros(3) if info.start_pose is None else np.array(info.start_pose, float)
        self._cov[rid] = np.zeros((3, 3)) if info.start_pose_cov is None else np.array(info.start_pose_cov, float)
        self._pending[rid] = []

    def on_odometry(self, event: OdomEvent) -> None:
        self._pending[event.robot_id].append(event)

    def _flush(self, rid: str) -> None:
        """Apply the buffered controls of ``rid`` at once."""
        pending = self._pending[rid]
        if not pending:
            return
        controls = np.array([e.control for e in pending], float)
        dts = np.array([e.dt for e in pending], float)
        covs = np.array([e.control_cov for e in pending], float)
        delta, delta_cov = integrate_controls(self._models[rid], controls, dts, covs)
        pose = self._pose[rid]
        new_pose = se2_compose(pose, delta)
        j_pose = np.eye(3)
        j_pose[0, 2] = -(new_pose[1] - pose[1])
        j_pose[1, 2] = new_pose[0] - pose[0]
        j_delta = compose_jacobian(pose[2])
        cov = j_pose @ self._cov[rid] @ j_pose.T + j_delta @ delta_cov @ j_delta.T
        self._pose[rid], self._cov[rid] = new_pose, 0.5 * (cov + cov.T)
        pending.clear()

    def on_scan(self, event: ScanEvent) -> None:
        if not self.config.map_known_ids or event.landmark_ids is None or event.ranges.size == 0:
            return
        rid = event.robot_id
        self._flush(rid)
        sensor, pose, cov = self._sensors[rid], self._pose[rid], self._cov[rid]
        z = event.observations
        positions = sensor.inverse(pose, z)
        g_pose, g_obs = sensor.inverse_jacobians(pose, z)
        covs = g_pose @ cov @ np.swapaxes(g_pose, -1, -2) + g_obs @ event.noise_cov @ np.swapaxes(g_obs, -1, -2)
        for lid, position, lm_cov in zip(event.landmark_ids.tolist(), positions, covs):
            if lid < 0:
                continue
            self._landmark_sum[lid] = self._landmark_sum.get(lid, 0.0) + position
            self._landmark_cov_sum[lid] = self._landmark_cov_sum.get(lid, 0.0) + lm_cov
            self._landmark_count[lid] = self._landmark_count.get(lid, 0) + 1

    def poses(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        for rid in self._pending:
            self._flush(rid)
        return {rid: (self._pose[rid].copy(), self._cov[rid].copy()) for rid in self._pose}

    def landmark_map(self) -> MapView:
        ids = sorted(self._landmark_count)
        if not ids:
            return MapView.empty(with_ids=True)
        counts = np.array([self._landmark_count[i] for i in ids], float)
        means = np.array([self._landmark_sum[i] for i in ids]) / counts[:, None]
        covs = np.array([self._landmark_cov_sum[i] for i in ids]) / counts[:, None, None]
        return MapView(means, covs, np.array(ids, np.int64))

    def extra_metrics(self) -> dict:
        """No figures of its own."""
        return {}


def make_estimator(options: RunOptions, infos: list[RobotInfo]) -> DeadReckoning:
    """The dead-reckoning baseline; it maps landmarks by their true ids when the association is ``known``.
    It has no settings of its own (:class:`SettingsError` for any in ``options.settings``)."""
    if options.settings:
        unknown = sorted(options.settings)
        raise SettingsError(f"unknown odometry setting{'s' if len(unknown) > 1 else ''} {', '.join(unknown)} "
                            "(known: none)")
    estimator = DeadReckoning(DeadReckoningConfig(map_known_ids=options.association == "known"))
    for info in infos:
        estimator.add_robot(info)
    return estimator
