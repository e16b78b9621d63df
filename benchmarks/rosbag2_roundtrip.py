"""ROS 2 bags round trip: a data set exported with ``fleetslam export rosbag2`` and loaded back as ``rosbag2:``.

1. MR.CLAM 6 (all of it): FastSLAM without barcodes (``--association unknown``), same seed, on the native data
   set and on its bag; ATE and map figures side by side. The native data set is run without what a PoseArray
   cannot carry (landmark ids, detections of other robots), so both runs see the same inputs. With ``--one-ulp``
   a third run takes the native data set with every range one ulp (≈ 1e-15 m) farther: the spread a FastSLAM
   run shows for differences as small as the round trip's float rounding.
2. Victoria Park: wall time of the export and of the import (target < 30 s together), and the largest
   difference of the controls and detections (the steering of the vehicle standing still is not carried).

    .venv/bin/python benchmarks/rosbag2_roundtrip.py [--particles 100] [--seed 0] [--duration S] [--storage mcap]
        [--one-ulp] [--skip-mrclam] [--skip-victoria] [--out FILE]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from report import emit
from robots.dataset import Dataset
from robots.loaders import load_dataset
from schemas.contract import RunOptions
from services.export import export_rosbag2
from support.fastslam_experiments import run_and_score

FIGURES = ("ate_rmse_m", "ate_aligned_rmse_m", "map_rmse_m", "landmarks", "landmarks_mapped", "wall_s")


def without_ids_and_robot_detections(dataset: Dataset) -> Dataset:
    """The data set as a bag carries it: no landmark ids, no detections of other robots (changed in place)."""
    for log in dataset.robots.values():
        log.det_id, log.robot_det_offsets, log.robot_det_ids = None, None, []
        log.robot_det_range, log.robot_det_bearing = np.zeros(0), np.zeros(0)
    return dataset


def timed_round_trip(spec: str, folder: Path, storage: str, duration: float | None) -> tuple[Dataset, Dataset, dict]:
    """(native, loaded back, wall times and message counts) of one data set's export and import."""
    native = load_dataset(spec)
    wall = time.perf_counter()
    written = export_rosbag2(native, folder, storage=storage, duration=duration)
    export_s = time.perf_counter() - wall
    wall = time.perf_counter()
    loaded = load_dataset(f"rosbag2:{folder}")
    import_s = time.perf_counter() - wall
    size = sum(p.stat().st_size for p in folder.iterdir())
    return native, loaded, {"export_s": round(export_s, 2), "import_s": round(import_s, 2),
                            "total_s": round(export_s + import_s, 2), "messages": sum(written["messages"].values()),
                            "bag_mb": round(size / 1e6, 1), "rejected": loaded.meta["rejected"]}


def largest_differences(native: Dataset, loaded: Dataset, duration: float | None) -> dict:
    """Largest |difference| of controls (moving and standing still), dt, ranges and bearings per robot."""
    out = {}
    for rid, log in native.robots.items():
        back = loaded.robots[rid]
        k = back.odom_stamp.size
        moving = np.abs(log.odom_control[:k, 0]) > 1e-9
        diff = np.abs(log.odom_control[:k] - back.odom_control)
        d = back.det_range.size
        out[rid] = {"control_moving": float(diff[moving].max(initial=0.0)),
                    "control_standing": float(diff[~moving].max(initial=0.0)),
                    "dt": float(np.abs(log.odom_dt[:k] - back.odom_dt).max(initial=0.0)),
                    "range": float(np.abs(log.det_range[:d] - back.det_range).max(initial=0.0)),
                    "bearing": float(np.abs(log.det_bearing[:d] - back.det_bearing).max(initial=0.0))}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--particles", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--duration", type=float, default=None, help="seconds of MR.CLAM data (default: all)")
    parser.add_argument("--storage", default="mcap", choices=("mcap", "sqlite3"))
    parser.add_argument("--one-ulp", action="store_true", help="also run the native data set with ranges one ulp off")
    parser.add_argument("--skip-mrclam", action="store_true")
    parser.add_argument("--skip-victoria", action="store_true")
    parser.add_argument("--out")
    args = parser.parse_args()
    report: dict = {"settings": vars(args)}
    with tempfile.TemporaryDirectory(prefix="rosbag2-") as scratch:
        if not args.skip_mrclam:
            native, loaded, timing = timed_round_trip("mrclam:", Path(scratch) / "mrclam6", args.storage, args.duration)
            differences = largest_differences(native, loaded, None)
            options = RunOptions("fastslam", "unknown", args.particles, args.seed)
            runs = {"native": run_and_score(without_ids_and_robot_detections(native), options, duration=args.duration),
                    "rosbag2": run_and_score(loaded, options, duration=args.duration)}
            if args.one_ulp:
                for log in native.robots.values():
                    log.det_range = np.nextafter(log.det_range, np.inf)
                runs["native_one_ulp"] = run_and_score(native, options, duration=args.duration)
            report["mrclam6"] = {"round_trip": timing, "largest_difference": differences,
                                 **{name: {k: run.get(k) for k in FIGURES} for name, run in runs.items()},
                                 "map_means_max_difference_m": float(np.abs(runs["native"]["map_means"]
                                                                            - runs["rosbag2"]["map_means"]).max())
                                 if runs["native"]["map_means"].shape == runs["rosbag2"]["map_means"].shape else None}
        if not args.skip_victoria:
            native, loaded, timing = timed_round_trip("victoria-park:", Path(scratch) / "victoria", args.storage, None)
            report["victoria_park"] = {"round_trip": timing, "target_total_s": 30.0,
                                       "met": timing["total_s"] < 30.0,
                                       "largest_difference": largest_differences(native, loaded, None)}
    emit(report, args.out)


if __name__ == "__main__":
    main()
