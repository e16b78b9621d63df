"""The local map of one robot in D-SLAM: a small EKF-SLAM in the frame of the pose where it was started.

D-SLAM's mapping measurement z_map (Wang, Huang, Dissanayake, "Implementation
Issues and Experimental Evaluation of D-SLAM", eq. 3) needs two mapped
features in one scan. A sensor that sees one beacon at a time (the ACFR car
park, a camera with a narrow field of view) rarely gives two, and the features
it sees then never reach the map. Following the idea of local maps in the
same authors' journal version of D-SLAM (Wang, Huang, Dissanayake, "D-SLAM: A
Decoupled Solution to Simultaneous Localization and Mapping", IJRR 2007; not
among the papers we work from, so this is our own form of it), several scans
are collected into a local map first: the features seen over a stretch of the
trajectory, with their joint covariance, in the frame of the robot's pose at
the stretch's start. That frame is the robot's own, so the local map's z_map
is as free of the robot's global pose as one scan's.

Observations of one feature key are fused (EKF update); a new key augments
the state. The robot's relative pose is part of the state, so the points are
correlated exactly as odometry and sensor noise make them.
"""

from __future__ import annotations

import numpy as np

from robots.gaussian import ekf_augment, ekf_predict_pose, ekf_update
from robots.models import MotionModel, RangeBearingSensor


class LocalMap:
    """Features (by key) in the frame of the robot's pose at the start, and the robot's pose in that frame."""

    def __init__(self, sensor: RangeBearingSensor):
        self.sensor = sensor
        self.x = np.zeros(3)
        self.P = np.zeros((3, 3))
        self.keys: list[int] = []
        self.scans = 0

    @property
    def size(self) -> int:
        return len(self.keys)

    def position_std(self) -> float:
        """Largest standard deviation (m) of the robot's position relative to the start."""
        return float(np.sqrt(max(np.linalg.eigvalsh(self.P[:2, :2]).max(), 0.0)))

    def predict(self, model: MotionModel, control: np.ndarray, control_cov: np.ndarray, dt: float) -> None:
        """Move the robot by one control; the features stay."""
        ekf_predict_pose(self.x, self.P, model, control, control_cov, dt)

    def observe(self, observations: np.ndarray, noise: np.ndarray, keys: np.ndarray) -> None:
        """Fuse one scan: rows with a key already held update it, new keys augment the state, key −1 is skipped."""
        self.scans += 1
        keys = np.asarray(keys, np.int64)
        held = {key: k for k, key in enumerate(self.keys)}
        seen = [(row, held[key]) for row, key in enumerate(keys.tolist()) if key in held]
        if seen:
            self._update(observations[[row for row, _ in seen]], noise, np.array([k for _, k in seen], np.int64))
        for row, key in enumerate(keys.tolist()):
            if key >= 0 and key not in held:
                self.x, self.P = ekf_augment(self.x, self.P, self.sensor, observations[row], noise)
                held[key] = len(self.keys)
                self.keys.append(key)

    def points(self, keys: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """Positions (m, 2) of the features ``keys`` in the local frame and their joint covariance (2m, 2m)."""
        slots = np.array([self.keys.index(key) for key in keys], np.int64)
        rows = (3 + np.stack([2 * slots, 2 * slots + 1], -1)).ravel()
        return self.x[rows].reshape(-1, 2), self.P[np.ix_(rows, rows)]

    def _update(self, observations: np.ndarray, noise: np.ndarray, slots: np.ndarray) -> None:
        """One batch EKF update with the observations of held features ``slots``."""
        k = slots.shape[0]
        landmarks = self.x[3:].reshape(-1, 2)[slots]
        h_pose, h_lm = self.sensor.jacobians(self.x[:3], landmarks)
        h = np.zeros((2 * k, self.x.shape[0]))
        for j, slot in enumerate(slots.tolist()):
            h[2 * j: 2 * j + 2, :3] = h_pose[j]
            h[2 * j: 2 * j + 2, 3 + 2 * slot: 5 + 2 * slot] = h_lm[j]
        nu = self.sensor.innovation(observations, self.sensor.observe(self.x[:3], landmarks)).ravel()
        self.x, self.P = ekf_update(self.x, self.P, nu, h, np.kron(np.eye(k), np.asarray(noise, float)))
