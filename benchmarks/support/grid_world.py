"""The synthetic world of the scaling benchmarks: N landmarks on a 3 m grid (the D-SLAM paper's geometry,
grown), a 180° / 5 m range-bearing sensor, and a robot driving a 4 m circle in the middle of it."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from robots.models import RangeBearingSensor, UnicycleModel, in_field_of_view
from schemas.contract import OdomEvent, ScanEvent
from schemas.messages import RobotInfo, SensorSpec

SPACING, RANGE, FOV = 3.0, 5.0, math.pi
NOISE = np.diag([0.05**2, math.radians(1.0) ** 2])
CONTROL_COV = np.diag([0.01**2, math.radians(0.5) ** 2])
CIRCLE_RADIUS, CIRCLE_STEP, CIRCLE_DT = 4.0, 0.2, 0.5
SCANS_PER_LAP = int(round(2 * math.pi * CIRCLE_RADIUS / CIRCLE_STEP))


class GridWorld:
    """N features on a square grid; which ones a pose can see, in O(1) per scan."""

    def __init__(self, n: int):
        self.n = n
        self.side = math.ceil(math.sqrt(n))
        axis = SPACING / 2 + SPACING * np.arange(self.side)
        gx, gy = np.meshgrid(axis, axis)
        self.landmarks = np.stack([gx.ravel(), gy.ravel()], -1)[:n]
        self.width = self.side * SPACING
        self.sensor = RangeBearingSensor()

    def scan(self, pose: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        reach = int(math.ceil(RANGE / SPACING)) + 1
        ci, cj = int(pose[0] // SPACING), int(pose[1] // SPACING)
        ii = np.arange(max(0, ci - reach), min(self.side, ci + reach + 1))
        jj = np.arange(max(0, cj - reach), min(self.side, cj + reach + 1))
        ids = (jj[:, None] * self.side + ii[None, :]).ravel()
        ids = ids[ids < self.n]
        z = self.sensor.observe(pose, self.landmarks[ids])
        seen = in_field_of_view(z, RANGE, FOV)
        z = z[seen] + rng.standard_normal((int(seen.sum()), 2)) @ np.linalg.cholesky(NOISE).T
        return z, ids[seen]

    def circle_start(self) -> np.ndarray:
        return np.array([self.width / 2, self.width / 2 - CIRCLE_RADIUS, 0.0])

    def robot_info(self, start_pose: np.ndarray | None) -> RobotInfo:
        sensor = SensorSpec(max_range=RANGE, fov=FOV, noise_cov=NOISE)
        return RobotInfo(robot_id="r1", stamp=0.0, motion_model="unicycle", sensor=sensor, start_pose=start_pose,
                         odom_rate_hz=1 / CIRCLE_DT, scan_rate_hz=1 / CIRCLE_DT)

    def circle(self, rng: np.random.Generator, scans: int):
        """(odometry, scan, true pose) of each of ``scans`` steps around the circle, ids given, noisy controls."""
        model = UnicycleModel()
        pose = self.circle_start()
        v = CIRCLE_STEP / CIRCLE_DT
        w = v / CIRCLE_RADIUS
        for k in range(scans):
            stamp = (k + 1) * CIRCLE_DT
            noisy = np.array([v, w]) + rng.standard_normal(2) * np.sqrt(np.diag(CONTROL_COV))
            pose = model.step(pose, np.array([v, w]), CIRCLE_DT)
            z, ids = self.scan(pose, rng)
            yield (OdomEvent("r1", k, stamp, CIRCLE_DT, noisy, CONTROL_COV),
                   ScanEvent("r1", k, stamp, z[:, 0].copy(), z[:, 1].copy(), ids.astype(np.int64), NOISE), pose)


def rss_mb() -> float:
    """This process's resident memory now (MB)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def exponent(sizes, values) -> float | None:
    """Exponent of the power law fitted to ``values`` against ``sizes`` (log-log least squares)."""
    sizes, values = np.asarray(sizes, float), np.asarray(values, float)
    if sizes.size < 2 or np.any(values <= 0):
        return None
    return float(np.polyfit(np.log(sizes), np.log(values), 1)[0])
