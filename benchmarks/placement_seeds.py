"""Fleet placement without start poses, and MCL with signatures, on MR.CLAM over seeds (median and worst).

Cases (FastSLAM, 100 particles, unless said):

- ``known-known``: barcodes, every start pose given (the reference);
- ``known-none``: barcodes, no start pose: the first robot to scan anchors the frame, MCL with signatures
  places the others;
- ``known-first``: barcodes, only the first robot's start pose;
- ``unknown-none``: barcodes ignored (``--association unknown``), no start pose;
- ``mcl-signatures``: MCL alone against the surveyed map, every robot from no pose, barcodes as signatures;
- ``mcl-unknown``: the same without barcodes (unknown correspondence); ``mcl-unknown-no-history``: poses drawn
  from a scan need not explain the scans before it (``history_scans=0``);
- ``known-known-turn-slip``, ``known-none-turn-slip``: the same with the robots' announced turn slip in
  FastSLAM's motion (``turn_slip``; D-SLAM models it by default);
- ``dslam-known-known``, ``dslam-known-none``, ``dslam-unknown-known``, ``dslam-unknown-none``: D-SLAM, with
  barcodes or without (``--association unknown``), with every start pose or none (D-SLAM draws nothing at
  random: the seed is MCL's);
- ``unknown-none-no-meetings``, ``known-none-no-meetings``, ``dslam-unknown-none-no-meetings``: the placement
  without the robots' detections of each other (``--no-robot-meetings``; on by default since they were added);
- ``unknown-none-no-prior``, ``unknown-none-rigid-only``: ``unknown-none`` with FastSLAM's re-acquisition
  without the drift's prior on its corrections, and with the rigid correction alone (the default before);
- ``unknown-none-no-by-robots``, ``dslam-unknown-none-no-by-robots``: FastSLAM's or D-SLAM's re-acquisition
  without the robots' say (``reacquire_by_robots=false``, the default before).

The data bound the placement delays stand against (``data_bound_s``, no estimator): after its first scan,
how long each robot takes to have seen two distinct landmarks that the anchor (the first robot to scan) had
seen before. Landmark signatures cannot place a robot earlier against the anchor's map; robots placed in
between can make it earlier by mapping more.

Per run: every robot's ATE after one SE(2) transform for the whole fleet (raw for the ``mcl-`` cases: their
frame is the survey's), and for placement cases the delay from each robot's first scan to its placement
(the anchor: 0); for the ``mcl-`` cases the time to first localized. Per case: median and worst over seeds of
the worst robot's ATE and of the longest delay.

    .venv/bin/python benchmarks/placement_seeds.py [--cases known-none,unknown-none] [--seeds 10] [--first-seed 0] [--jobs 2]
        [--data mrclam:] [--out FILE]
"""

from __future__ import annotations

import argparse
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from report import emit, over_seeds
from robots.loaders import load_dataset
from schemas.contract import RunOptions
from services.evaluation.metrics import Trajectory, fleet_alignment
from services.offline import run_estimator

CASES: dict[str, tuple] = {  # estimator, association, start poses[, settings]
    "known-known": ("fastslam", "known", "known"),
    "known-none": ("fastslam", "known", "none"),
    "known-first": ("fastslam", "known", "first"),
    "unknown-none": ("fastslam", "unknown", "none"),
    "unknown-none-robot-sd-0": ("fastslam", "unknown", "none", {"robot_detection_position_sd": 0.0}),
    "unknown-none-no-by-robots": ("fastslam", "unknown", "none", {"reacquire_by_robots": False}),
    "unknown-none-no-meetings": ("fastslam", "unknown", "none", {"robot_meetings": False}),
    "unknown-none-no-prior": ("fastslam", "unknown", "none", {"reacquire_prior_weight": 0.0}),
    "unknown-none-rigid-only": ("fastslam", "unknown", "none", {"reacquire_prior_weight": 0.0,
                                                                "reacquire_confirm_sigmas": 0.0}),
    "known-none-no-meetings": ("fastslam", "known", "none", {"robot_meetings": False}),
    "mcl-signatures": ("mcl", "known", "none"),
    "mcl-unknown": ("mcl", "unknown", "none"),
    "mcl-unknown-no-history": ("mcl", "unknown", "none", {"history_scans": 0}),
    "known-known-turn-slip": ("fastslam", "known", "known", {"turn_slip": True}),
    "known-none-turn-slip": ("fastslam", "known", "none", {"turn_slip": True}),
    "dslam-known-known": ("dslam", "known", "known"),
    "dslam-known-none": ("dslam", "known", "none"),
    "dslam-unknown-known": ("dslam", "unknown", "known"),
    "dslam-unknown-none": ("dslam", "unknown", "none"),
    "dslam-unknown-none-no-meetings": ("dslam", "unknown", "none", {"robot_meetings": False}),
    "dslam-unknown-none-no-by-robots": ("dslam", "unknown", "none", {"reacquire_by_robots": False}),
}


def one_run(spec: str, case: str, seed: int) -> dict:
    estimator, association, start_poses, *settings = CASES[case]
    dataset = load_dataset(spec)
    settings = dict(settings[0]) if settings else {}
    meetings = settings.pop("robot_meetings", True)  # the placer's, not the estimator's
    options = RunOptions(estimator, association, None, seed, settings)
    if estimator == "mcl":
        options.landmarks, options.landmark_ids = dataset.landmarks, dataset.landmark_ids
    run = run_estimator(dataset, options, start_poses=start_poses, robot_meetings=meetings)
    truth = {rid: Trajectory(log.truth_stamp, log.truth_pose) for rid, log in dataset.robots.items()}
    if estimator == "mcl":
        errors = {}
        for rid, path in run.trajectories.items():
            at = dataset.robots[rid].truth_at(path.stamps)
            valid = np.all(np.isfinite(at[:, :2]), 1)
            errors[rid] = float(np.sqrt(np.mean(np.sum((path.poses[valid, :2] - at[valid, :2]) ** 2, 1))))
        delays = {rid: robot["localized_s"] for rid, robot in run.extra["mcl"]["robots"].items()}
    else:
        errors = fleet_alignment(run.trajectories, truth)["ate_rmse_m"]
        delays = {rid: record.get("placed_after_first_scan_s", 0.0 if record["how"] == "start pose" else None)
                  for rid, record in run.extra.get("placement", {}).items()} or {rid: 0.0 for rid in dataset.robots}
    return {"case": case, "seed": seed, "ate_m": errors, "delay_s": delays,
            "worst_robot_ate_m": max(errors.values()), "longest_delay_s": max(
                (d for d in delays.values() if d is not None), default=None),
            "unplaced": sorted(rid for rid, d in delays.items() if d is None)}


def data_bound(dataset) -> dict[str, float | None]:
    """Per robot but the anchor: seconds from its first scan until it has seen two distinct landmarks the
    anchor saw before (None: never)."""
    logs = {rid: log for rid, log in dataset.robots.items() if log.det_id is not None and len(log.det_id)}
    scans = {rid: [(log.scan_stamp[k], log.det_id[log.scan_offsets[k]:log.scan_offsets[k + 1]])
                   for k in range(len(log.scan_stamp)) if log.scan_offsets[k + 1] > log.scan_offsets[k]]
             for rid, log in logs.items()}
    anchor = min(scans, key=lambda rid: scans[rid][0][0])
    anchor_first: dict[int, float] = {}
    for stamp, ids in scans[anchor]:
        for i in ids.tolist():
            anchor_first.setdefault(int(i), float(stamp))
    bound: dict[str, float | None] = {}
    for rid, mine in scans.items():
        if rid == anchor:
            continue
        seen: set[int] = set()
        bound[rid] = None
        for stamp, ids in mine:
            seen |= {int(i) for i in ids.tolist() if anchor_first.get(int(i), np.inf) < stamp}
            if len(seen) >= 2:
                bound[rid] = round(float(stamp - mine[0][0]), 3)
                break
    return bound


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default="mrclam:", help="data set spec (needs robot truth)")
    parser.add_argument("--cases", default=",".join(CASES), help=f"comma-separated, of: {', '.join(CASES)}")
    parser.add_argument("--seeds", type=int, default=10, help="seeds first..first+N-1")
    parser.add_argument("--first-seed", type=int, default=0, help="the first seed")
    parser.add_argument("--jobs", type=int, default=2, help="runs in parallel (processes)")
    parser.add_argument("--out")
    args = parser.parse_args()
    cases = args.cases.split(",")
    unknown = [c for c in cases if c not in CASES]
    if unknown:
        parser.error(f"unknown cases {unknown}; choose from {', '.join(CASES)}")
    jobs = [(args.data, case, seed) for case in cases for seed in range(args.first_seed, args.first_seed + args.seeds)]
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        runs = list(pool.map(one_run, *zip(*jobs)))
    summary = {}
    for case in cases:
        mine = [r for r in runs if r["case"] == case]
        summary[case] = {"seeds": len(mine), "never_placed_or_localized": sum(bool(r["unplaced"]) for r in mine),
                         **over_seeds(mine, ("worst_robot_ate_m", "longest_delay_s"))}
    emit({"settings": vars(args), "data_bound_s": data_bound(load_dataset(args.data)), "runs": runs,
          "summary": summary}, args.out)


if __name__ == "__main__":
    main()
