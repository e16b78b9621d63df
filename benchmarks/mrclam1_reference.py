"""MR.CLAM Dataset 1, which has no robot truth: unknown association and placement scored against a run with ids.

The tuned figures of the other benchmarks come from MR.CLAM Dataset 6; Dataset 1 (other day, other paths, a
partial copy without Vicon truth) is how this repository sees data it was not tuned on. Its landmarks carry
barcodes, so a reference is at hand: FastSLAM with the barcodes (``--association known``), no start poses, seed 0,
whose map fits the survey within about 0.1 m (reported as ``reference``). Every run under test is a whole-fleet
run without start poses and without barcodes (``--association unknown --start-poses none``), scored by

- each robot's position error against the reference's, after one SE(2) transform for the whole fleet fitted to
  every robot's positions jointly (never one per robot, which would hide a misplaced robot;
  :func:`services.evaluation.metrics.fleet_alignment`): ``ate_robot_worst_m``, ``ate_robot_median_m``;
- its map registered to the survey from the map alone (:func:`services.evaluation.metrics.map_alignment`):
  surveyed landmarks within 0.3 m (``within_0_3m`` of 15), landmarks mapped, spurious (farther than 1 m from every
  surveyed one), RMSE of the matched ones.

The reference is an estimate, not truth: a robot's error here is its distance from where the run with barcodes put
it (where both are wrong together, as r1 after its 33 s without a detection at 439 s, the error is not seen).
Median and worst over the seeds, never the best.

    .venv/bin/python benchmarks/mrclam1_reference.py [--seeds 10] [--first-seed 0] [--estimators fastslam,dslam]
        [--association unknown|known] [--set KEY=VALUE ...] [--jobs 2] [--out FILE]
"""

from __future__ import annotations

import argparse
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from report import emit, over_seeds, setting
from robots.loaders import load_dataset
from schemas.contract import RunOptions
from services.evaluation.metrics import fleet_alignment, map_alignment
from services.offline import run_estimator

DATA = "mrclam:utias_mrclam/MRCLAM_Dataset1_partial"
DETERMINISTIC = {"dslam"}  # no random draws: one seed is every seed


def run(estimator: str, association: str, seed: int, particles: int, settings: dict):
    """One whole-fleet run of Dataset 1 without start poses: the data set and what the run produced."""
    dataset = load_dataset(DATA)
    return dataset, run_estimator(dataset, RunOptions(estimator, association, particles, seed, dict(settings)),
                                  start_poses="none")


def map_figures(dataset, means: np.ndarray) -> dict:
    """The map registered to the survey: surveyed landmarks within 0.3 m, mapped, spurious, RMSE."""
    fit = map_alignment(means, dataset.landmarks)
    marks = fit.get("landmarks", {})
    return {"within_0_3m": fit.get("within_inlier"), "landmarks_mapped": int(len(means)),
            "spurious": marks.get("spurious"), "map_rmse_m": fit.get("map_rmse_m")}


def one_run(estimator: str, seed: int, association: str, particles: int, settings: dict, reference: dict) -> dict:
    dataset, out = run(estimator, association, seed, particles, settings)
    fleet = fleet_alignment(out.trajectories, reference)
    errors = {rid: value for rid, value in fleet.get("ate_rmse_m", {}).items() if value is not None}
    unplaced = sorted(set(reference) - set(errors))
    return {"estimator": estimator, "seed": seed, "wall_s": round(out.wall_s, 1), "ate_rmse_m": errors,
            "unplaced": unplaced, "ate_robot_worst_m": None if unplaced else max(errors.values(), default=None),
            "ate_robot_median_m": float(np.median(list(errors.values()))) if errors else None,
            **map_figures(dataset, out.map_means)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10, help="how many seeds: FIRST..FIRST+N-1")
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--estimators", default="fastslam", help="comma-separated: fastslam, dslam")
    parser.add_argument("--association", default="unknown", choices=("unknown", "known"),
                        help="of the runs under test (known, from seed 1 on: how far the reference is from itself)")
    parser.add_argument("--particles", type=int, default=100)
    parser.add_argument("--set", dest="settings", type=setting, action="append", default=[],
                        help="KEY=VALUE of the estimator's settings for the runs under test (repeatable)")
    parser.add_argument("--jobs", type=int, default=2, help="runs in parallel (processes)")
    parser.add_argument("--out")
    args = parser.parse_args()
    estimators = args.estimators.split(",")
    unknown = [name for name in estimators if name not in ("fastslam", "dslam")]
    if unknown:
        parser.error(f"unknown estimators {unknown}; choose from fastslam, dslam")
    dataset, ref = run("fastslam", "known", 0, args.particles, {})
    reference = {rid: path for rid, path in ref.trajectories.items() if len(path)}
    settings = dict(args.settings)
    jobs = [(name, seed) for name in estimators
            for seed in range(args.first_seed, args.first_seed + (1 if name in DETERMINISTIC else args.seeds))]
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        runs = list(pool.map(one_run, *zip(*jobs), *([value] * len(jobs) for value in
                                                      (args.association, args.particles, settings, reference))))
    keys = ("ate_robot_worst_m", "ate_robot_median_m", "within_0_3m", "landmarks_mapped", "spurious", "map_rmse_m",
            "wall_s")
    report = {"settings": vars(args) | {"settings": settings},
              "reference": {"robots": sorted(reference), **map_figures(dataset, ref.map_means)}, "runs": runs,
              "summary": {name: {"seeds": sum(r["estimator"] == name for r in runs),
                                 "unplaced_runs": sum(bool(r["unplaced"]) for r in runs if r["estimator"] == name),
                                 **over_seeds([r for r in runs if r["estimator"] == name], keys, least=True)}
                          for name in estimators}}
    emit(report, args.out)


if __name__ == "__main__":
    main()
