"""Multi-session mapping on MR.CLAM: a second session's robots, without start poses, join the first session's map.

Session 1: the robots of ``--first`` (default r1,r2), with their start poses (so the map is in the Vicon frame),
run through the central FastSLAM core as ``fleetslam run`` does, and the final map is saved with
:func:`schemas.mapfile.save_map`. Session 2: the robots of ``--second`` (default r3,r4,r5), with no start pose,
start from that file (``fleetslam run --map FILE --start-poses none``): no robot anchors a new frame, each is
placed by MCL against the map (:class:`services.placement.FleetPlacer`, landmark ids as signatures with known
association), and the map grows. Reference: session 2's robots from the same map with their start poses.

Reported per association: when and how each robot was placed (and the delay after its first scan), ATE per
robot (raw: the saved map's frame is Vicon's; and after one SE(2) transform for the whole fleet), the map
error (RMSE against the surveyed landmarks, matched / missed / spurious within ``--cutoff``) of the saved map
and of the map after session 2, landmarks before / after, and how far the saved landmarks moved in session 2
(known association: by id; unknown: to the nearest landmark of the new map).

    .venv/bin/python benchmarks/multi_session.py [--data mrclam:PATH] [--first r1,r2] [--second r3,r4,r5]
        [--associations known,unknown] [--particles 100] [--seed 0] [--first-duration S] [--maps DIR] [--out FILE]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from report import emit
from robots.loaders import load_dataset
from schemas.contract import MapView, RunOptions
from schemas.mapfile import load_map, save_map
from services.evaluation.metrics import Trajectory, ate, fleet_alignment, interpolate_poses, map_error
from services.maps import options_with_map
from services.offline import OfflineRun, run_estimator

DATA = "mrclam:../shared/data/utias_mrclam/MRCLAM_Dataset6"


def raw_ate(run: OfflineRun, dataset) -> dict[str, float | None]:
    """Each robot's ATE RMSE in the truth's frame, without alignment (m)."""
    out = {}
    for rid, path in run.trajectories.items():
        log = dataset.robots[rid]
        at = interpolate_poses(log.truth_stamp, log.truth_pose, path.stamps, 1.0)
        valid = np.all(np.isfinite(at[:, :2]), 1)
        out[rid] = ate(path.poses[valid, :2], at[valid, :2])["rmse_m"]
    return out


def scored(run: OfflineRun, dataset, cutoff: float) -> dict:
    """ATE raw and fleet-aligned per robot, map error, landmarks, wall time."""
    truth = {rid: Trajectory(log.truth_stamp, log.truth_pose) for rid, log in dataset.robots.items()}
    fleet = fleet_alignment(run.trajectories, truth)
    error = map_error(run.map_means, dataset.landmarks, cutoff)
    return {"ate_raw_m": raw_ate(run, dataset), "ate_fleet_aligned_m": fleet.get("ate_rmse_m"),
            "fleet_transform": fleet.get("transform"),
            "map": {k: error[k] for k in ("estimated", "matched", "missed", "spurious", "rmse_m")},
            "wall_s": round(run.wall_s, 2), "data_s": round(run.data_s, 1)}


def moved(saved: MapView, after: OfflineRun) -> dict:
    """How far the saved landmarks are in the map after session 2 (by id, or to the nearest new landmark)."""
    if not len(saved.means) or not len(after.map_means):
        return {}
    if saved.ids is not None and after.map_ids is not None:
        where = dict(zip(np.asarray(after.map_ids).tolist(), after.map_means))
        distance = np.array([np.linalg.norm(where[i] - m) for i, m in zip(saved.ids.tolist(), saved.means)
                             if i in where])
        how = "by id"
    else:
        distance = np.linalg.norm(saved.means[:, None] - after.map_means[None], axis=-1).min(1)
        how = "to the nearest landmark after"
    return {"how": how, "kept": int(distance.size), "median_m": float(np.median(distance)),
            "max_m": float(np.max(distance))}


def one_association(dataset, association: str, args, maps: Path) -> dict:
    first, second = args.first.split(","), args.second.split(",")
    options = RunOptions("fastslam", association, args.particles, args.seed)
    started = time.perf_counter()
    session1 = run_estimator(dataset, options, robots=first, duration=args.first_duration, start_poses="known")
    path = maps / f"session1_{association}.json"
    save_map(path, MapView(session1.map_means, session1.map_covs, session1.map_ids),
             {"estimator": "fastslam", "association": association, "particles": args.particles, "seed": args.seed,
              "dataset": args.data, "robots": first, "duration": args.first_duration})
    saved = load_map(path)
    view = saved.view()
    session2 = run_estimator(dataset, options_with_map(options, saved), robots=second, start_poses="none")
    reference = run_estimator(dataset, options_with_map(options, saved), robots=second, start_poses="known")
    placements = {rid: {k: record.get(k) for k in ("how", "placed_s", "first_scan_s", "placed_after_first_scan_s",
                                                    "scans_before", "reason")}
                  for rid, record in session2.extra.get("placement", {}).items()}
    return {
        "map_file": str(path), "landmarks_saved": len(saved.landmarks),
        "session1": scored(session1, dataset, args.cutoff),
        "session2": {**scored(session2, dataset, args.cutoff), "placement": placements,
                     "held_for_placement": session2.extra.get("held_for_placement")},
        "session2_with_start_poses": scored(reference, dataset, args.cutoff),
        "landmarks_before_after": [len(saved.landmarks), int(len(session2.map_means))],
        "saved_landmarks_moved": moved(view, session2),
        "wall_s": round(time.perf_counter() - started, 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=DATA, help="data set spec with robot truth (robots.loaders.load_dataset)")
    parser.add_argument("--first", default="r1,r2", help="session 1's robots (with start poses)")
    parser.add_argument("--second", default="r3,r4,r5", help="session 2's robots (no start poses)")
    parser.add_argument("--associations", default="known", help="comma-separated: known (barcodes), unknown")
    parser.add_argument("--particles", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--first-duration", type=float, default=None,
                        help="seconds of data for session 1 (default: all; less leaves more for session 2 to map)")
    parser.add_argument("--cutoff", type=float, default=1.0, help="map error: farther pairs are not matches (m)")
    parser.add_argument("--maps", default=None, help="folder for session 1's map files (default: a temporary one)")
    parser.add_argument("--out", help="also write the JSON here")
    args = parser.parse_args()
    dataset = load_dataset(args.data)
    unknown = [rid for rid in args.first.split(",") + args.second.split(",") if rid not in dataset.robots]
    if unknown:
        parser.error(f"robots {', '.join(unknown)} are not in {dataset.name} ({', '.join(dataset.robots)})")
    with tempfile.TemporaryDirectory() as scratch:
        maps = Path(args.maps or scratch)
        maps.mkdir(parents=True, exist_ok=True)
        results = {association: one_association(dataset, association, args, maps)
                   for association in args.associations.split(",")}
    emit({"benchmark": "multi_session", "dataset": dataset.name, "settings": vars(args), "results": results}, args.out)


if __name__ == "__main__":
    main()
