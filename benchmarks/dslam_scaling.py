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

Between two scans the benchmark does what the D-SLAM service does while it waits
for the next one (``--no-prefetch``: nothing): it solves the covariance columns
the robot will soon need (:meth:`DSlam.column_prefetch`, in the service a worker
thread) and takes them into the cache just before the next scan, in that scan's
time. Those solves are reported apart (``prefetch``: count, mean and longest,
against the 0.5 s between two scans); the five slowest scans are listed with the
columns each solved itself. The robot starts without a pose: as in the service,
its scans wait (``scans_deferred``) until the columns of the landmarks they see
are solved between scans, and the first scan with them all cached places it.

Reported per N: build time per scan, steady-state time per scan (median,
mean, p90, max), the cost of a first-sighting column solve, the information
matrix's non-zeros, the bytes of the filter's arrays and the process RSS, and
the exponents of power laws fitted to time and memory against N.

    .venv/bin/python benchmarks/dslam_scaling.py --sizes 1000,10000,100000 --out reports/dslam/scaling.json

``--columns explicit --check-every 1`` runs the reference recovery (full columns corrected in place, the mean
checked against I X = i every scan); ``--column-solver pcg`` the reference solve of the columns not cached
(block PCG preconditioned by a sparse LU factor made afresh when stale).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import json
import math
import time

import numpy as np
import scipy.linalg

from services.dslam.config import DslamConfig
from services.dslam.core import DSlam
from services.dslam.information_filter import InformationMap
from report import emit
from support.grid_world import CIRCLE_DT, FOV, NOISE, RANGE, SCANS_PER_LAP, SPACING, GridWorld, exponent, rss_mb

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


def drive(world: GridWorld, dslam: DSlam, rng: np.random.Generator, scans: int,
          prefetch: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The circle of radius 4 m around the world's centre; returns seconds per scan, columns solved per scan and
    the seconds of each column prefetch solve.

    With ``prefetch``, what the service does between two scans: the columns the robot will soon need are solved
    (:meth:`DSlam.column_prefetch`, the service's worker thread) and, just before the next scan, taken into the
    cache; that taking counts in the next scan's time (the service takes them under the map's lock, so a scan
    may wait for it)."""
    seconds, solves, prefetch_s = [], [], []
    pending = None
    for odometry, scan, _ in world.circle(rng, scans):
        dslam.on_odometry(odometry)
        before = dslam.map.column_solves
        tick = time.perf_counter()
        if pending is not None:
            dslam.take_prefetched(*pending)
            pending = None
        dslam.on_scan(scan)
        seconds.append(time.perf_counter() - tick)
        solves.append(dslam.map.column_solves - before)
        job = dslam.column_prefetch() if prefetch else None
        if job is not None:
            tick = time.perf_counter()
            pending = (job, job.run())
            prefetch_s.append(time.perf_counter() - tick)
    return np.array(seconds), np.array(solves), np.array(prefetch_s)


def mapped_world(n: int, seed: int):
    """The world of ``n`` landmarks, its map from the sweep (:func:`build`), each map index's landmark id, the build's
    figures and the random generator the sweep left (the drive goes on with it)."""
    rng = np.random.default_rng([seed, n])
    world = GridWorld(n)
    m, index_of, built = build(world, rng)
    keys = [0] * m.n
    for key, index in index_of.items():
        keys[index] = key
    return world, m, keys, built, rng


def one_size(n: int, seed: int, scans: int, cache: int, settings: dict, prefetch: bool) -> dict:
    world, m, keys, built, rng = mapped_world(n, seed)
    dslam = DSlam(DslamConfig(association="known", column_cache=cache, **settings))
    dslam.adopt(m, keys)
    dslam.prefetching = prefetch  # as the service: the scans of a robot without a pose wait for their columns
    dslam.add_robot(world.robot_info(None))
    per_lap = SCANS_PER_LAP
    factorisations = m.factorisations
    seconds, solves, prefetch_s = drive(world, dslam, rng, scans, prefetch)
    steady = seconds[per_lap:]
    first = seconds[:per_lap][solves[:per_lap] > 0]
    error = dslam.map.means - world.landmarks[np.asarray(dslam.ids)]
    return {
        "landmarks": int(m.n), **built,
        "steady_ms_per_scan": {"median": 1e3 * float(np.median(steady)), "mean": 1e3 * float(np.mean(steady)),
                               "p90": 1e3 * float(np.percentile(steady, 90)), "max": 1e3 * float(np.max(steady)),
                               "scans": int(steady.size), "column_solves": int(solves[per_lap:].sum())},
        "first_lap_ms_per_scan_with_column_solves": 1e3 * float(np.mean(first)) if first.size else None,
        "first_lap_max_ms": 1e3 * float(np.max(seconds[:per_lap])),
        "first_lap_column_solves": int(solves[:per_lap].sum()),
        "first_lap_max_ms_with_column_solves": 1e3 * float(np.max(first)) if first.size else None,
        "slowest_scans": [{"scan": int(k), "ms": 1e3 * float(seconds[k]), "column_solves": int(solves[k])}
                          for k in np.argsort(-seconds)[:5]],
        "prefetch": {"solves": int(prefetch_s.size), "columns": int(m.columns_prefetched),
                     "dropped": int(m.columns_prefetch_dropped),
                     "max_ms": 1e3 * float(prefetch_s.max()) if prefetch_s.size else None,
                     "mean_ms": 1e3 * float(prefetch_s.mean()) if prefetch_s.size else None,
                     "scan_period_ms": 1e3 * CIRCLE_DT},
        "timed_factorisations": int(m.factorisations - factorisations),
        "info_nnz": int(m.matrix.nnz), "info_blocks": int(m.matrix.blocks),
        "filter_bytes": int(m.memory_bytes()), "column_cache_bytes": int(m.cache.nbytes()), "rss_mb": rss_mb(),
        "map_rmse_m": float(np.sqrt(np.mean(np.sum(error**2, axis=1)))),
        "robot_placed": bool(dslam.counts["robots_placed"]),
        "scans_deferred": int(dslam.counts["scans_deferred"]),  # kept, without a pose, while their columns were solved
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="1000,10000,100000")
    parser.add_argument("--scans", type=int, default=376, help="timed scans (the first lap, 126 scans, fills the cache)")
    parser.add_argument("--cache", type=int, default=32, help="covariance columns kept (landmarks)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--columns", choices=["factored", "explicit"], default="factored",
                        help="DslamConfig.covariance_columns (explicit: the reference)")
    parser.add_argument("--check-every", type=int, default=DslamConfig().recovery_check_every,
                        help="DslamConfig.recovery_check_every (1: the reference)")
    parser.add_argument("--column-solver", choices=["corrected", "pcg"], default=DslamConfig().column_solver,
                        help="DslamConfig.column_solver (pcg: the reference)")
    parser.add_argument("--no-prefetch", dest="prefetch", action="store_false",
                        help="solve every column a scan lacks in that scan (without the service's solves between scans)")
    parser.add_argument("--out")
    args = parser.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    runs = {}
    for n in sizes:
        runs[n] = one_size(n, args.seed, args.scans, args.cache,
                           {"covariance_columns": args.columns, "recovery_check_every": args.check_every,
                            "column_solver": args.column_solver}, args.prefetch)
        print(json.dumps({n: runs[n]}), flush=True)
    ns = [runs[n]["landmarks"] for n in sizes]
    result = {
        "benchmark": "dslam_scaling", "setup": {"spacing_m": SPACING, "range_m": RANGE, "fov_rad": FOV,
                                                "column_cache": args.cache, "timed_scans": args.scans, "seed": args.seed,
                                                "covariance_columns": args.columns, "recovery_check_every": args.check_every,
                                                "column_solver": args.column_solver, "prefetch": args.prefetch},
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
