"""Speed anchor: GTSAM iSAM2 on the Victoria Park graph and fleetslam's FastSLAM on Victoria Park, in one run.

iSAM2 (M. Kaess et al., "iSAM2: Incremental Smoothing and Mapping Using the Bayes Tree", IJRR 2012) is the
reference incremental smoother; timed in the same process and run as fleetslam, it gives a CPU ratio far
less sensitive to the machine and its load than either time alone. Both use the Victoria Park run of
J. Guivant and E. Nebot (ACFR, University of Sydney), in two forms:

- iSAM2: the graph form (``victoria_park_graph/victoria_park_isam.txt``, GTSAM's ``victoria_park.txt``):
  keyframe odometry and tree sightings with their landmark ids already given. One ``ISAM2.update`` per pose
  node: the pose (initialised from the previous pose's estimate composed with the odometry), its
  ``BetweenFactorPose2`` and the ``BearingRangeFactor2D`` of its sightings (a landmark is initialised from
  its first sighting); a prior on the first pose. Noise as ``gtsam.load2D`` reads this file: the six
  numbers of an ``ODOMETRY`` line are a covariance (its AUTO format detection picks COV for this
  layout), and a ``LANDMARK`` line's x-y variance v becomes sigma_range = sqrt(v), sigma_bearing = sqrt(v/10).
- fleetslam: FastSLAM on the raw data (odometry, laser tree detections without ids: ``--association
  unknown``) through the offline runner of ``fleetslam run``; the error at the GPS fixes is reported.

CPU is ``time.process_time()`` around the incremental loop (iSAM2, with the final full estimate) and around
the estimator run (fleetslam, :func:`support.fastslam_experiments.run_and_score`); parsing and data loading
are timed separately and left out, and so is the compilation of the numba kernels (``warm_up_s``: compiled, or
loaded from numba's cache, before the first round, as a service does before it subscribes). Wall time: the same
span for iSAM2, the event loop for fleetslam.
``ratio_cpu`` is fleetslam's CPU over iSAM2's, per particle count.
``--duration`` cuts the fleetslam run only: the graph has no timestamps, iSAM2 always runs all of it.
``--repeats N`` runs N rounds (iSAM2, then fleetslam at each particle count): each figure is then the median
round's, and ``ratio_cpu`` the median of the rounds' ratios (``ratio_cpu_rounds``), since the load of a shared
machine swings within minutes.

    .venv/bin/python benchmarks/isam2_anchor.py [--particles 100,1000] [--seed 0] [--duration S] [--repeats N]
        [--workers 1] [--skip-fleetslam] [--skip-isam2] [--graph FILE] [--out FILE]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import importlib.metadata
import importlib.util
import math
import sys
import time
from pathlib import Path

import numpy as np

from report import emit
from robots.loaders import data_root, load_dataset
from schemas.contract import RunOptions
from services.compiled import warm_up
from support.fastslam_experiments import run_and_score

GRAPH = Path("victoria_park_graph") / "victoria_park_isam.txt"
PRIOR_SIGMAS = (0.01, 0.01, 0.01)  # first pose: m, m, rad
RELINEARIZE_THRESHOLD, RELINEARIZE_SKIP = 0.1, 10  # GTSAM's defaults, set explicitly


def parse_graph(path: Path) -> list[dict]:
    """The graph as one step per pose node, in file order: ``{"pose", "odometry", "sightings"}``.

    ``odometry`` is ``(previous pose, dx, dy, dtheta, covariance upper triangle)`` (None for the first pose);
    ``sightings`` are ``(landmark, x, y, variance)`` in the robot frame. Raises ValueError on anything else.
    """
    steps: list[dict] = [{"pose": 0, "odometry": None, "sightings": []}]
    for number, line in enumerate(path.read_text().splitlines(), 1):
        fields = line.split()
        if not fields:
            continue
        if fields[0] == "ODOMETRY" and len(fields) == 12:
            i, j = int(fields[1]), int(fields[2])
            if i != steps[-1]["pose"]:
                raise ValueError(f"{path}:{number}: odometry from {i}, expected from the last pose {steps[-1]['pose']}")
            steps.append({"pose": j, "odometry": (i, *map(float, fields[3:12])), "sightings": []})
        elif fields[0] == "LANDMARK" and len(fields) == 8:
            i, landmark = int(fields[1]), int(fields[2])
            x, y, c11, c12, c22 = map(float, fields[3:8])
            if i != steps[-1]["pose"] or c12 != 0.0 or abs(c11 - c22) > 1e-4:
                raise ValueError(f"{path}:{number}: sighting not from the last pose or not isotropic: {line}")
            steps[-1]["sightings"].append((landmark, x, y, c11))
        else:
            raise ValueError(f"{path}:{number}: unknown line: {line[:60]}")
    return steps


def run_isam2(steps: list[dict]) -> dict:
    """Feed the steps to iSAM2, one update per pose; CPU and wall time of the loop and the final estimate."""
    import gtsam
    from gtsam.symbol_shorthand import L, X
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(RELINEARIZE_THRESHOLD)
    params.relinearizeSkip = RELINEARIZE_SKIP
    isam = gtsam.ISAM2(params)
    known: set[int] = set()
    factors = 0
    cpu0, wall0 = time.process_time(), time.perf_counter()
    for step in steps:
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if step["odometry"] is None:
            pose = gtsam.Pose2(0.0, 0.0, 0.0)
            graph.add(gtsam.PriorFactorPose2(X(step["pose"]), pose, gtsam.noiseModel.Diagonal.Sigmas(PRIOR_SIGMAS)))
        else:
            i, dx, dy, dth, c11, c12, c13, c22, c23, c33 = step["odometry"]
            odometry = gtsam.Pose2(dx, dy, dth)
            cov = [[c11, c12, c13], [c12, c22, c23], [c13, c23, c33]]
            graph.add(gtsam.BetweenFactorPose2(X(i), X(step["pose"]), odometry, gtsam.noiseModel.Gaussian.Covariance(cov)))
            pose = isam.calculateEstimatePose2(X(i)).compose(odometry)
        values.insert(X(step["pose"]), pose)
        for landmark, x, y, variance in step["sightings"]:
            noise = gtsam.noiseModel.Diagonal.Sigmas([math.sqrt(variance / 10.0), math.sqrt(variance)])
            graph.add(gtsam.BearingRangeFactor2D(X(step["pose"]), L(landmark), gtsam.Rot2(math.atan2(y, x)),
                                                 math.hypot(x, y), noise))
            if landmark not in known:
                known.add(landmark)
                values.insert(L(landmark), pose.transformFrom(gtsam.Point2(x, y)))
        factors += graph.size()
        isam.update(graph, values)
    estimate = isam.calculateEstimate()
    cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
    return {"cpu_s": round(cpu, 2), "wall_s": round(wall, 2), "poses": len(steps), "landmarks": len(known),
            "factors": factors, "updates": len(steps), "final_error": round(isam.getFactorsUnsafe().error(estimate), 3),
            "relinearize_threshold": RELINEARIZE_THRESHOLD, "relinearize_skip": RELINEARIZE_SKIP}


def load_victoria_park() -> tuple:
    """(the raw Victoria Park data set, its loading's ``load_s`` and ``load_cpu_s``): loaded once per run."""
    cpu0, wall0 = time.process_time(), time.perf_counter()
    dataset = load_dataset("victoria-park:")
    return dataset, {"load_s": round(time.perf_counter() - wall0, 2), "load_cpu_s": round(time.process_time() - cpu0, 2)}


def run_fleetslam(dataset, load: dict, particles: list[int], seed: int, duration: float | None,
                  workers: int = 1) -> dict:
    """FastSLAM, unknown association, on raw Victoria Park (``load``: its loading's figures), one run per particle
    count, its per-particle kernels on ``workers`` threads (1: one core, as iSAM2)."""
    out: dict = {}
    for count in particles:
        run = run_and_score(dataset, RunOptions("fastslam", "unknown", count, seed, {"workers": workers}), duration=duration)
        gps = [v for v in run.get("gps_rmse_m", {}).values() if v is not None]
        out[str(count)] = {"cpu_s": run["cpu_s"], "wall_s": run["wall_s"], **load, "data_s": run["data_s"],
                           "gps_rmse_m": gps[0] if len(gps) == 1 else None,
                           "landmarks_mapped": run["landmarks_mapped"]}
    return out


def median_round(rounds: list[dict]) -> dict:
    """The round whose CPU time is the median of ``rounds`` (each a run's figures), with every round's CPU time."""
    ordered = sorted(rounds, key=lambda run: run["cpu_s"])
    return ordered[(len(ordered) - 1) // 2] | {"cpu_s_rounds": [run["cpu_s"] for run in rounds]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--particles", default="100", help="comma-separated particle counts, one run each")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--duration", type=float, default=None,
                        help="seconds of Victoria Park data for fleetslam (default: all)")
    parser.add_argument("--repeats", type=int, default=1,
                        help="rounds of iSAM2 then fleetslam, one after the other, so that a change in the machine's "
                             "load falls on both; the ratio reported is the median of the rounds' ratios")
    parser.add_argument("--workers", type=int, default=1,
                        help="threads of FastSLAM's per-particle kernels (1: one core, as iSAM2)")
    parser.add_argument("--graph", default=None, help=f"iSAM graph file (default: <data>/{GRAPH})")
    parser.add_argument("--skip-fleetslam", action="store_true")
    parser.add_argument("--skip-isam2", action="store_true")
    parser.add_argument("--out")
    args = parser.parse_args()
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")
    particles = [int(p) for p in args.particles.split(",") if p]
    result: dict = {"benchmark": "isam2_anchor", "settings": vars(args)}
    steps = path = None
    if not args.skip_isam2:
        if importlib.util.find_spec("gtsam") is None:
            print("isam2_anchor: gtsam is not installed; install it with: pip install -e '.[bench]'", file=sys.stderr)
            sys.exit(2)
        path = Path(args.graph) if args.graph else (data_root() or Path("../shared/data")) / GRAPH
        tick = time.perf_counter()
        steps = parse_graph(path)
        parse_s = time.perf_counter() - tick
    dataset, load = (None, {}) if args.skip_fleetslam else load_victoria_park()
    if dataset is not None:  # compile (or load from numba's cache) before any timed round, as a service does
        result["warm_up_s"] = round(warm_up(("association", "fastslam")), 2)
    isam2_rounds, fleetslam_rounds = [], []
    for _ in range(args.repeats):
        if steps is not None:
            isam2_rounds.append(run_isam2(steps))
        if dataset is not None:
            fleetslam_rounds.append(run_fleetslam(dataset, load, particles, args.seed, args.duration, args.workers))
    if isam2_rounds:
        result["isam2"] = {"graph": str(path), "gtsam": importlib.metadata.version("gtsam"),
                           "parse_s": round(parse_s, 2)} | median_round(isam2_rounds)
    if fleetslam_rounds:
        result["fleetslam"] = {count: median_round([run[count] for run in fleetslam_rounds])
                               for count in fleetslam_rounds[0]}
    if isam2_rounds and fleetslam_rounds:
        ratios = {count: [round(run[count]["cpu_s"] / max(isam["cpu_s"], 1e-9), 3)
                          for isam, run in zip(isam2_rounds, fleetslam_rounds)] for count in fleetslam_rounds[0]}
        result["ratio_cpu"] = {count: round(float(np.median(values)), 2) for count, values in ratios.items()}
        result["ratio_cpu_rounds"] = ratios
    emit(result, args.out)


if __name__ == "__main__":
    main()
