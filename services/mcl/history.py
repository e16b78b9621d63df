"""The robot's recent scans, tied together by its odometry: evidence a pose drawn from one scan must also explain.

A pose drawn from a scan of one to three detections (sensor resetting, Lenser
and Veloso 2000) fits that scan as well as the true pose does, often better:
on MR.CLAM a pose 6.5 m off scored e^104 above the truth over 10 s of such
draws, while the truth beat its half-turn twin in 84–93 % of the scans. What
tells them apart is the scans just before, which a pose must explain too once
it is carried back along the odometry.

:class:`ScanHistory` keeps the last scans with detections, each with the
dead-reckoned pose it was taken at. For a candidate pose x at the current
scan, the pose at an earlier scan k is x ⊕ (⊖o_t ⊕ o_k), o the dead-reckoned
poses; the history's log-likelihood of x is the sum of the earlier scans'
log-likelihoods at those poses. Dead reckoning drifts, mostly in turns, so
the history stops at ``max_scans`` scans or once the robot has turned
``max_turn`` radians since, whichever comes first.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Callable

import numpy as np

from robots.models import se2_between, se2_compose, wrap_angle

LogLikelihood = Callable[[np.ndarray, np.ndarray, np.ndarray | None], np.ndarray]


@dataclass
class PastScan:
    """One earlier scan: its observations, the landmarks of its signed detections (or None), where dead
    reckoning put the robot when it was taken, and how far the robot had turned in all by then."""

    observations: np.ndarray
    targets: np.ndarray | None
    odometry: np.ndarray
    turned: float


class ScanHistory:
    """The last scans with detections, and the dead-reckoned pose that links them."""

    def __init__(self, max_scans: int, max_turn: float):
        self.max_scans = int(max_scans)
        self.max_turn = float(max_turn)
        self.odometry = np.zeros(3)  # dead-reckoned pose in an arbitrary frame
        self.turned = 0.0  # radians turned in all (absolute), the drift's main source
        self.scans: deque[PastScan] = deque(maxlen=max(self.max_scans, 1))

    def __len__(self) -> int:
        return len(self.scans)

    def move(self, pose: np.ndarray) -> None:
        """The dead-reckoned pose after one odometry reading."""
        self.turned += abs(float(wrap_angle(pose[2] - self.odometry[2])))
        self.odometry = np.asarray(pose, float).copy()

    def clear(self) -> None:
        """Forget every scan (after a kidnapping the odometry no longer links them to the pose)."""
        self.scans.clear()

    def usable(self) -> list[PastScan]:
        """The scans still within ``max_turn`` radians turned of now, newest first."""
        out = []
        for scan in reversed(self.scans):
            if self.turned - scan.turned > self.max_turn:
                break
            out.append(scan)
        return out

    def log_likelihood(self, poses: np.ndarray, likelihood: LogLikelihood) -> np.ndarray:
        """Sum over the usable scans of ``likelihood(poses_then, observations, targets)`` for candidate poses
        ``(n, 3)`` at the present; zeros when there is no usable scan."""
        total = np.zeros(poses.shape[0])
        for scan in self.usable():
            back = se2_between(self.odometry, scan.odometry)
            total += likelihood(se2_compose(poses, back), scan.observations, scan.targets)
        return total

    def add(self, observations: np.ndarray, targets: np.ndarray | None) -> None:
        """Remember a scan taken at the present dead-reckoned pose (scans without detections are not kept)."""
        if self.max_scans <= 0 or len(observations) == 0:
            return
        self.scans.append(PastScan(np.array(observations, float), None if targets is None else np.array(targets, float),
                                   self.odometry.copy(), self.turned))
