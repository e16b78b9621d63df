"""FastSLAM's per-particle kernels on one worker and on several, in the same run: time per scan, CPU use, same results.

The FastSLAM 2.0 step (shared association) and the EKF updates with ids (known association) run one particle per
iteration of numba's parallel loop when ``workers`` > 1 (:func:`central.fastslam.kernels.propose_parallel_kernel`,
:func:`~central.fastslam.kernels.known_update_parallel_kernel`). Each target runs the same data with the same seed
once per worker count, the counts alternating within every repeat, so a load change of the shared machine falls on
both; the figure is the ratio of the two runs' time per scan (median and worst over the repeats: the worst is the
largest ratio, the least speed-up), never an absolute time alone. CPU use is the process CPU time over the wall time
of the event loop (above 1: more than one core worked). Every repeat also checks that the trajectories and the map
are bit-identical between the worker counts (``identical``).

Targets (``--targets``): ``mrclam`` (MR.CLAM Dataset 6, five robots, ``--duration`` s, barcodes ignored: shared
association and FastSLAM 2.0) and ``sim`` (a simulated fleet of ``--sim-robots`` robots in the arena, with its
landmark ids: known association and FastSLAM 1.0), each at every ``--particles`` count.

    .venv/bin/python benchmarks/fastslam_workers.py [--targets mrclam,sim] [--particles 100,1000] [--workers 1,2]
        [--repeats 3] [--duration 300] [--sim-robots 10] [--seed 0] [--out FILE]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import time

import numpy as np

from report import emit
from robots.loaders import data_root, load_dataset
from schemas.contract import RunOptions
from services.compiled import warm_up
from services.offline import run_estimator


def dataset_of(target: str, args):
    """(data set, association) of a target name."""
    if target == "mrclam":
        return load_dataset("mrclam:"), "unknown"
    if target == "sim":
        return load_dataset("sim:arena", robots=args.sim_robots, seed=args.seed, duration=args.duration), "known"
    raise SystemExit(f"unknown target {target!r} (known: mrclam, sim)")


def timed_run(data, association: str, particles: int, workers: int, args) -> dict:
    """One run: the event loop's wall and CPU time, the scans' summed time, and what it estimated."""
    options = RunOptions(estimator="fastslam", association=association, particles=particles, seed=args.seed,
                         settings={"workers": workers})
    wall, cpu = time.perf_counter(), time.process_time()
    run = run_estimator(data, options, None, args.duration)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    scan = run.timing["scan"]
    return {"scans": scan["count"], "scan_total_s": scan["mean_ms"] * scan["count"] / 1000.0,
            "scan_ms_median": scan["median_ms"], "wall_s": wall, "cpu_per_wall": cpu / wall,
            "poses": {rid: t.poses for rid, t in run.trajectories.items()}, "map": run.map_means}


def same_results(a: dict, b: dict) -> bool:
    """Bit-identical trajectories and map (NaN where NaN)."""
    if a["poses"].keys() != b["poses"].keys():
        return False
    pairs = [(a["poses"][rid], b["poses"][rid]) for rid in a["poses"]] + [(a["map"], b["map"])]
    return all(x.shape == y.shape and np.array_equal(x, y, equal_nan=True) for x, y in pairs)


def spread(values: list[float], worst) -> dict:
    """Median and worst (``worst``: max or min) of ``values``, rounded."""
    return {"median": round(float(np.median(values)), 3), "worst": round(float(worst(values)), 3)}


def measure(target: str, particles: int, args) -> dict:
    """Alternating runs per worker count, ``--repeats`` times; the ratios to the first count's run of each repeat."""
    data, association = dataset_of(target, args)
    counts = [int(w) for w in args.workers.split(",")]
    runs: dict[int, list[dict]] = {w: [] for w in counts}
    identical = True
    for repeat in range(args.repeats):
        order = counts if repeat % 2 == 0 else counts[::-1]  # alternate which count runs first
        done = {w: timed_run(data, association, particles, w, args) for w in order}
        identical &= all(same_results(done[counts[0]], done[w]) for w in counts[1:])
        for w in counts:
            runs[w].append(done[w])
    base = runs[counts[0]]
    out = {"target": target, "association": association, "particles": particles, "scans": base[0]["scans"],
           "identical": identical, "workers": {}}
    for w in counts:
        ratios = [run["scan_total_s"] / ref["scan_total_s"] for run, ref in zip(runs[w], base)]
        out["workers"][str(w)] = {
            "scan_ms_mean": spread([1000 * run["scan_total_s"] / run["scans"] for run in runs[w]], max),
            "scan_ms_median": spread([run["scan_ms_median"] for run in runs[w]], max),
            "scan_time_ratio": spread(ratios, max),
            "cpu_per_wall": spread([run["cpu_per_wall"] for run in runs[w]], min),
            "wall_s": spread([run["wall_s"] for run in runs[w]], max),
        }
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--targets", default="mrclam,sim", help="mrclam, sim (comma-separated)")
    parser.add_argument("--particles", default="100,1000", help="particle counts, comma-separated")
    parser.add_argument("--workers", default="1,2", help="worker counts, comma-separated; ratios are to the first")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--duration", type=float, default=300.0, help="seconds of data per run")
    parser.add_argument("--sim-robots", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out")
    args = parser.parse_args()
    targets = args.targets.split(",")
    if "mrclam" in targets and data_root() is None:
        targets.remove("mrclam")  # the data set is not here: the simulated fleet only
    warm_up(("fastslam", "association"))
    results = [measure(target, int(p), args) for target in targets for p in args.particles.split(",")]
    emit({"benchmark": "fastslam_workers", "settings": vars(args), "cores": len(os.sched_getaffinity(0)),
          "results": results}, args.out)


if __name__ == "__main__":
    main()
