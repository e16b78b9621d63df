"""MR.CLAM Dataset 6 with the central FastSLAM core: all five robots in one filter, against each robot alone.

For each association (``known``: the barcodes; ``nn`` and ``mht``: barcodes ignored) the five robots run in
one filter, and each robot runs alone in its own filter (same settings). Reported: per-robot ATE against
Vicon (raw: the start poses come from Vicon, so the frame is Vicon's), map RMSE against the surveyed
landmarks, and the dead-reckoning baseline. Robot-to-robot detections are not used unless
``--robot-detections``.

    .venv/bin/python benchmarks/fastslam_mrclam.py [--associations known,nn,mht] [--particles 100]
        [--duration S] [--no-alone] [--out FILE]
"""

from __future__ import annotations

import argparse

from report import emit
from robots.loaders import load_dataset
from schemas.contract import RunOptions
from support.fastslam_experiments import run_and_score


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default="mrclam:", help="data set spec (robots.loaders.load_dataset)")
    parser.add_argument("--associations", default="known,nn,mht")
    parser.add_argument("--particles", type=int, default=100)
    parser.add_argument("--duration", type=float, default=None, help="seconds of data (default: all)")
    parser.add_argument("--proposal", default=None, help="fastslam1 or fastslam2 (default: the core's)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--robot-detections", action="store_true")
    parser.add_argument("--no-alone", action="store_true", help="skip the single-robot runs")
    parser.add_argument("--out")
    args = parser.parse_args()
    dataset = load_dataset(args.data)
    robots = list(dataset.robots)
    settings = {"robot_detections": True} if args.robot_detections else {}
    if args.proposal:
        settings["proposal"] = args.proposal
    keys = ("ate_rmse_m", "map_rmse_m", "landmarks", "wall_s", "cpu_s")
    report: dict = {"settings": vars(args), "data": dataset.name}
    baseline = run_and_score(dataset, RunOptions("odometry"), duration=args.duration)
    report["dead_reckoning"] = {k: baseline[k] for k in ("ate_rmse_m", "map_rmse_m")}
    for association in args.associations.split(","):
        options = RunOptions("fastslam", association, args.particles, args.seed, settings)
        central = run_and_score(dataset, options, duration=args.duration)
        entry = {"central": {k: central[k] for k in keys}}
        if not args.no_alone:
            alone = {rid: run_and_score(dataset, options, robots=[rid], duration=args.duration) for rid in robots}
            entry["alone"] = {rid: {k: run[k] for k in keys} | {"ate_rmse_m": run["ate_rmse_m"][rid]}
                              for rid, run in alone.items()}
            entry["central_better_than_alone"] = {
                rid: central["ate_rmse_m"][rid] < alone[rid]["ate_rmse_m"][rid] for rid in robots}
        entry["central_better_than_dead_reckoning"] = {
            rid: central["ate_rmse_m"][rid] < baseline["ate_rmse_m"][rid] for rid in robots}
        report[association] = entry
    emit(report, args.out)


if __name__ == "__main__":
    main()
