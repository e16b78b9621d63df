"""D-SLAM cost against map size: time per scan and memory for worlds of 10³, 10⁴, 10⁵ landmarks.

For each size N: a square grid of N features at 3 m spacing (the D-SLAM
paper's geometry, grown), a 180° / 5 m range-bearing sensor. The map is first *built*
from a lawnmower sweep over the whole world (lanes 6 m apart, a scan every
metre, known ids), with the information filter alone (eq. 10 linearised at the
true positions, as a perfect recovery would; the mean solved once at the end by
a sparse LU solve) — the D-SLAM mapping needs no robot pose.
Then the full D-SLAM step is *timed*: a robot with an unknown start pose drives
a circle of radius 4 m in the middle of the map (a scan every 0.2 m, with
odometry), and every scan runs association (known ids), localization
(covariance columns of the features seen, CI), the z_map update with the
recovery of the mean and of the cached columns, exactly as the service does.
The first revolution fills the column cache (a column not cached is solved by
PCG): those scans are reported apart; the steady state is the rest.

Reported per N: build time per scan, steady-state time per scan (median,
mean, p90, max), the cost of a first-sighting column solve, the information
matrix's non-zeros, the bytes of the filter's arrays and the process RSS, and
the exponents of power laws fitted to time and memory against N.

    .venv/bin/python benchmarks/dslam_scaling.py --sizes 1000,10000,100000 --out reports/dslam/scaling.json
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
import scipy.linalg

from schemas.contract import OdomEvent, ScanEvent
from robots.models import RangeBearingSensor, UnicycleModel, in_field_of_view
from schemas.messages import RobotInfo, SensorSpec
from services.dslam.config import DslamConfig
from services.dslam.core import DSlam
from services.dslam.information_filter import InformationMap
from report import emit

SPACING, RANGE, FOV = 3.0, 5.0, math.pi
NOISE = np.diag([0.05**2, math.radians(1.0) ** 2])
CONTROL_COV = np.diag([0.01**2, math.radians(0.5) ** 2])


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


def lawnmower(width: float, lane: float = 6.0, step: float = 1.0) -> np.ndarray:
    poses = []
    y, forward = 1.0, True
    while y < width:
        xs = np.arange(1.0, width - 1.0, step)
        for x in xs if forward else xs[::-1]:
            poses.append((x, y, 0.0 if forward else math.pi))
        y += lane
        forward = not forward
    return np.array(poses)


def build(world: GridWorld, rng: np.random.Generator):
    """The map of the whole world from a lawnmower sweep, by the information filter alone (known ids).

    Every measurement is linearised at the true positions (what a perfect recovery
    would give), so the bulk build needs no recovery; the mean is solved once at the end.
    """
    m = InformationMap(track_columns=False)
    index_of: dict[int, int] = {}
    path = lawnmower(world.width)
    started = time.perf_counter()
    for k, pose in enumerate(path):
        z, ids = world.scan(pose, rng)
        if ids.size == 0:
            continue
        if not index_of:
            g_pose, g_obs = world.sensor.inverse_jacobians(pose, z)
            cov = scipy.linalg.block_diag(*(g_obs @ NOISE @ np.swapaxes(g_obs, 1, 2)))
            added = m.update_absolute([], np.zeros((0, 2)), world.sensor.inverse(pose, z), cov)
        else:
            known = np.array([i in index_of for i in ids.tolist()], bool)
            mapped, new = np.flatnonzero(known), np.flatnonzero(~known)
            done = m.update_scan(z, NOISE, mapped, [index_of[i] for i in ids[mapped].tolist()], new)
            if done is None:
                continue
            added = done[0]
            ids = ids[new]
        index_of.update(zip(ids.tolist(), added.tolist()))
        m.means[added] = world.landmarks[ids]  # the next updates linearise at the truth (an ideal recovery)
    build_s = time.perf_counter() - started
    final = time.perf_counter()
    m.solve_exactly()  # one sparse LU solve after the bulk build
    return m, index_of, {"scans": int(path.shape[0]), "build_ms_per_scan": 1e3 * build_s / path.shape[0],
                         "final_sparse_solve_s": time.perf_counter() - final}


def drive(world: GridWorld, dslam: DSlam, rng: np.random.Generator, scans: int, per_lap: int) -> tuple[np.ndarray, np.ndarray]:
    """A circle of radius 4 m around the world's centre; returns seconds per scan and columns solved per scan."""
    radius, step = 4.0, 0.2
    centre = np.array([world.width / 2, world.width / 2])
    model = UnicycleModel()
    pose = np.array([centre[0], centre[1] - radius, 0.0])
    dt, v = 0.5, step / 0.5
    w = v / radius
    seconds, solves = [], []
    seq = 0
    for k in range(scans):
        noisy = np.array([v, w]) + rng.standard_normal(2) * np.sqrt(np.diag(CONTROL_COV))
        dslam.on_odometry(OdomEvent("r1", seq, k * dt + dt, dt, noisy, CONTROL_COV))
        pose = model.step(pose, np.array([v, w]), dt)
        z, ids = world.scan(pose, rng)
        event = ScanEvent("r1", seq, k * dt + dt, z[:, 0].copy(), z[:, 1].copy(), ids.astype(np.int64), NOISE)
        before = dslam.map.column_solves
        tick = time.perf_counter()
        dslam.on_scan(event)
        seconds.append(time.perf_counter() - tick)
        solves.append(dslam.map.column_solves - before)
        seq += 1
    return np.array(seconds), np.array(solves)


def rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def one_size(n: int, seed: int, scans: int, cache: int) -> dict:
    rng = np.random.default_rng([seed, n])
    world = GridWorld(n)
    m, index_of, built = build(world, rng)
    keys = [0] * m.n
    for key, index in index_of.items():
        keys[index] = key
    dslam = DSlam(DslamConfig(association="known", column_cache=cache))
    dslam.adopt(m, keys)
    sensor = SensorSpec(max_range=RANGE, fov=FOV, noise_cov=NOISE)
    dslam.add_robot(RobotInfo(robot_id="r1", stamp=0.0, motion_model="unicycle", sensor=sensor, start_pose=None,
                              odom_rate_hz=2.0, scan_rate_hz=2.0))
    per_lap = int(round(2 * math.pi * 4.0 / 0.2))
    seconds, solves = drive(world, dslam, rng, scans, per_lap)
    steady = seconds[per_lap:]
    first = seconds[:per_lap][solves[:per_lap] > 0]
    error = dslam.map.means - world.landmarks[np.asarray(dslam.ids)]
    return {
        "landmarks": int(m.n), **built,
        "steady_ms_per_scan": {"median": 1e3 * float(np.median(steady)), "mean": 1e3 * float(np.mean(steady)),
                               "p90": 1e3 * float(np.percentile(steady, 90)), "max": 1e3 * float(np.max(steady)),
                               "scans": int(steady.size), "column_solves": int(solves[per_lap:].sum())},
        "first_lap_ms_per_scan_with_column_solves": 1e3 * float(np.mean(first)) if first.size else None,
        "first_lap_column_solves": int(solves[:per_lap].sum()),
        "info_nnz": int(m.matrix.nnz), "info_blocks": int(m.matrix.blocks),
        "filter_bytes": int(m.memory_bytes()), "column_cache_bytes": int(m.cache.data.nbytes), "rss_mb": rss_mb(),
        "map_rmse_m": float(np.sqrt(np.mean(np.sum(error**2, axis=1)))),
        "robot_placed": bool(dslam.counts["robots_placed"]),
    }


def exponent(sizes, values) -> float | None:
    sizes, values = np.asarray(sizes, float), np.asarray(values, float)
    if sizes.size < 2 or np.any(values <= 0):
        return None
    return float(np.polyfit(np.log(sizes), np.log(values), 1)[0])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="1000,10000,100000")
    parser.add_argument("--scans", type=int, default=376, help="timed scans (the first lap, 126 scans, fills the cache)")
    parser.add_argument("--cache", type=int, default=32, help="covariance columns kept (landmarks)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out")
    args = parser.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    runs = {}
    for n in sizes:
        runs[n] = one_size(n, args.seed, args.scans, args.cache)
        print(json.dumps({n: runs[n]}), flush=True)
    ns = [runs[n]["landmarks"] for n in sizes]
    result = {
        "benchmark": "dslam_scaling", "setup": {"spacing_m": SPACING, "range_m": RANGE, "fov_rad": FOV,
                                                "column_cache": args.cache, "timed_scans": args.scans, "seed": args.seed},
        "runs": {str(n): runs[n] for n in sizes},
        "fitted_exponent": {
            "steady_ms_per_scan_median": exponent(ns, [runs[n]["steady_ms_per_scan"]["median"] for n in sizes]),
            "steady_ms_per_scan_mean": exponent(ns, [runs[n]["steady_ms_per_scan"]["mean"] for n in sizes]),
            "build_ms_per_scan": exponent(ns, [runs[n]["build_ms_per_scan"] for n in sizes]),
            "filter_bytes": exponent(ns, [runs[n]["filter_bytes"] for n in sizes]),
            "info_nnz": exponent(ns, [runs[n]["info_nnz"] for n in sizes]),
        },
    }
    emit(result, args.out)


if __name__ == "__main__":
    main()
