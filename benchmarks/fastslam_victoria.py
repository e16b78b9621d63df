"""Victoria Park with the central FastSLAM core: unknown association, 100 particles, all 1549 s of data.

Reports the error at the GPS fixes (after SE(2) alignment: the GPS frame is only roughly the vehicle's start
frame), the number of trees in the published map, wall and CPU time, and the dead-reckoning baseline. Runs
go through the offline runner of ``fleetslam run`` (event iteration and pose sampling included in the wall
time). ``--configs`` lists runs as NAME=JSON of FastSLAM settings (``central/fastslam/config.py``).

    .venv/bin/python benchmarks/fastslam_victoria.py [--duration 1549] [--particles 100]
        [--association nn] [--configs 'default={};range40={"max_obs_range": 40}'] [--out FILE]
"""

from __future__ import annotations

import argparse
import json

from report import emit
from robots.loaders import load_dataset
from schemas.contract import RunOptions
from support.fastslam_experiments import run_and_score

DEFAULT_CONFIGS = 'default={};range40={"max_obs_range": 40}'


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default="victoria-park:", help="data set spec (robots.loaders.load_dataset)")
    parser.add_argument("--duration", type=float, default=None, help="seconds of data (default: all)")
    parser.add_argument("--particles", type=int, default=100)
    parser.add_argument("--association", default="nn")
    parser.add_argument("--proposal", default=None, help="fastslam1 or fastslam2 (default: the core's)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--configs", default=DEFAULT_CONFIGS)
    parser.add_argument("--no-baseline", action="store_true")
    parser.add_argument("--out")
    args = parser.parse_args()
    dataset = load_dataset(args.data)
    report: dict = {"settings": vars(args), "data": dataset.name}
    if not args.no_baseline:
        run = run_and_score(dataset, RunOptions("odometry"), duration=args.duration)
        report["dead_reckoning"] = {k: run[k] for k in ("gps_rmse_m", "wall_s", "data_s")}
    for entry in args.configs.split(";"):
        name, _, text = entry.partition("=")
        settings = ({"proposal": args.proposal} if args.proposal else {}) | json.loads(text or "{}")
        options = RunOptions("fastslam", args.association, args.particles, args.seed, settings)
        run = run_and_score(dataset, options, duration=args.duration)
        report[name] = {k: run[k] for k in ("settings", "gps_rmse_m", "landmarks_mapped", "wall_s", "cpu_s", "data_s",
                                            "scan_ms_median", "scan_ms_p99")}
        report[name]["realtime_factor"] = round(run["data_s"] / run["wall_s"], 1)
    emit(report, args.out)


if __name__ == "__main__":
    main()
