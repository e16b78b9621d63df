"""FastSLAM cost against map size: time per scan and memory with 10³, 10⁴, 10⁵ landmarks, 100 particles.

Paper 001 (Nieto, Guivant, Nebot, Thrun, "Real Time Data Association for FastSLAM") claims an update in time
logarithmic in the number of landmarks, from per-particle maps that share unchanged landmarks in a tree.
This measures ours (known and shared association: :class:`central.fastslam.aligned_map.AlignedMap`, copy-on-write
blocks). The world of :mod:`support.grid_world` (N landmarks on a 3 m grid, a 180° / 5 m sensor,
about 8 landmarks per scan) is put whole into every particle's map first (the truth plus the sensor's
noise, as if mapped, the same in every particle), then a robot with a known start drives a 4 m circle in the middle of it, with its
scans' ids (``--association known``) or without them (``--association shared``: the method of ``fleetslam run
--association unknown``, its candidate search through the map's spatial index included), and every scan is
timed (wall and CPU) after a first lap of warm-up.

Reported per N: time per scan (median, mean, p90, max), the bytes of the particles' landmark arrays (pool,
block tables, per-slot data, spatial index; ``table_bytes``: the block tables alone, the part that is per
particle) and the blocks in use, the process RSS, the ratio of each figure to the previous decade's (target
≤ 1.5) and the exponents of power laws fitted against N.

    .venv/bin/python benchmarks/fastslam_scaling.py [--sizes 1000,10000,100000] [--association known|shared]
        [--particles 100] [--scans 250] [--seed 0] [--out FILE]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import time

import numpy as np

from central.fastslam.aligned_map import SlotTable
from central.fastslam.config import FastSlamConfig
from central.fastslam.core import FastSlam
from report import emit
from support.grid_world import NOISE, SCANS_PER_LAP, GridWorld, exponent, rss_mb

LANDMARK_STD = 0.05  # m: the prior every landmark enters the particles' maps with


def prefilled(world: GridWorld, particles: int, association: str, seed: int) -> FastSlam:
    """A filter whose every particle already holds every landmark of the world (ids = grid indices), the same
    Gaussians in every particle: a map the particles agree on, as their lineages merge after many resamplings
    (stored once, in blocks every particle shares)."""
    slam = FastSlam(FastSlamConfig(particles=particles, association=association, seed=seed),
                    [world.robot_info(world.circle_start())])
    rng = np.random.default_rng([seed, world.n])
    means = world.landmarks + rng.normal(0.0, LANDMARK_STD, world.landmarks.shape)
    ids = np.arange(world.n)
    slots = slam.map.add(means, np.broadcast_to(np.eye(2) * LANDMARK_STD**2, (world.n, 2, 2)), slam.config.exist_max,
                         slam.config.confirm_hits, ids)  # every landmark confirmed
    slam.known_slots = SlotTable(zip(ids.tolist(), slots.tolist()))
    slam.next_landmark_id = world.n
    return slam


def one_size(n: int, particles: int, association: str, scans: int, seed: int) -> dict:
    world = GridWorld(n)
    started = time.perf_counter()
    slam = prefilled(world, particles, association, seed)
    fill_s = time.perf_counter() - started
    rng = np.random.default_rng([seed, n, 1])
    wall, cpu, detections = [], [], []
    truth = world.circle_start()
    for odometry, scan, truth in world.circle(rng, scans):
        if association != "known":
            scan.landmark_ids = None
        slam.on_odometry(odometry)
        tick, tock = time.perf_counter(), time.process_time()
        slam.on_scan(scan)
        wall.append(time.perf_counter() - tick)
        cpu.append(time.process_time() - tock)
        detections.append(scan.ranges.size)
    steady = np.array(wall[SCANS_PER_LAP:]) * 1e3
    steady_cpu = np.array(cpu[SCANS_PER_LAP:]) * 1e3
    pose, _ = slam.poses()["r1"]
    return {
        "landmarks": n, "particles": particles, "fill_s": round(fill_s, 3),
        "ms_per_scan": {"median": float(np.median(steady)), "mean": float(np.mean(steady)),
                        "p90": float(np.percentile(steady, 90)), "max": float(np.max(steady)), "scans": int(steady.size)},
        "cpu_ms_per_scan_median": float(np.median(steady_cpu)),
        "detections_per_scan": float(np.mean(detections)),
        "map_bytes": slam.map.nbytes, "table_bytes": int(slam.map.table.nbytes),
        "map_capacity": int(slam.map.capacity), "rss_mb": round(rss_mb(), 1),
        "blocks_in_use": slam.map.blocks_in_use(), "block_slots": slam.map.block,
        "landmarks_in_map": int(len(slam.known_slots)),
        "final_pose_error_m": float(np.hypot(*(pose[:2] - truth[:2]))),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="1000,10000,100000", help="landmark counts, comma-separated")
    parser.add_argument("--association", default="known", choices=("known", "shared"),
                        help="known: the scans' ids; shared: --association unknown's method")
    parser.add_argument("--particles", type=int, default=100)
    parser.add_argument("--scans", type=int, default=2 * SCANS_PER_LAP,
                        help=f"scans per size (the first {SCANS_PER_LAP}: warm-up)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out")
    args = parser.parse_args()
    if args.scans <= SCANS_PER_LAP:
        parser.error(f"--scans must exceed the warm-up lap ({SCANS_PER_LAP})")
    sizes = [int(s) for s in args.sizes.split(",")]
    runs = {n: one_size(n, args.particles, args.association, args.scans, args.seed) for n in sizes}
    decades = {f"{a}->{b}": {"ms_per_scan_median": runs[b]["ms_per_scan"]["median"] / runs[a]["ms_per_scan"]["median"],
                             "ms_per_scan_mean": runs[b]["ms_per_scan"]["mean"] / runs[a]["ms_per_scan"]["mean"],
                             "map_bytes": runs[b]["map_bytes"] / runs[a]["map_bytes"],
                             "table_bytes": runs[b]["table_bytes"] / runs[a]["table_bytes"],
                             "rss_mb": runs[b]["rss_mb"] / runs[a]["rss_mb"]}
               for a, b in zip(sizes, sizes[1:])}
    emit({"benchmark": "fastslam_scaling", "settings": vars(args), "noise_cov": NOISE.tolist(),
          "target": "each decade of landmarks at most 1.5x the previous in time per scan and memory",
          "runs": runs, "ratio_to_previous": decades,
          "fitted_exponent": {"ms_per_scan_median": exponent(sizes, [runs[n]["ms_per_scan"]["median"] for n in sizes]),
                              "map_bytes": exponent(sizes, [runs[n]["map_bytes"] for n in sizes])}}, args.out)


if __name__ == "__main__":
    main()
