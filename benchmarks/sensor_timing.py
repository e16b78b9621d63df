"""Timing offsets between detections, odometry and truth in the real data sets, measured without any filter.

How far in time each robot's detections sit from its odometry, and (where there is truth) both from the truth:

- **detections against odometry** (every data set; no truth, no ids): each detection is placed in the world
  from the dead-reckoned pose at its stamp + δ. Landmarks stand still, so the detections of scans a few seconds
  apart (``--window``) coincide best at the δ that puts each scan where the robot was when it was taken: the
  score is the mean distance of detection pairs from different scans closer than ``--gate`` m. Dead reckoning
  drifts little over a few seconds; a δ error turns a whole scan by ω·δ and shifts it by v·δ.
- **detections against truth** (MR.CLAM: ids and Vicon): the median distance of each identified detection,
  placed from the true pose at stamp + δ, to its surveyed landmark.
- **odometry against truth** (MR.CLAM): the mean squared difference of the odometry's turn rate stamped t and
  Vicon's at t + δ (both smoothed over 0.25 s).

Every δ says when what was stamped s happened: at s + δ. Negative: before its stamp (a scan stamped on
arrival); positive: after it (odometry that announces a turn before the robot makes it). The stamps are measured
as they are in the files: the car park is loaded with ``scan_delay_s=0`` (its loader moves the scans back by the
−0.047 s measured here; the other loaders keep the stamps). docs/data.md says what shifting the stamps did.
"""

from __future__ import annotations

import argparse

import numpy as np

from report import emit
from robots.loaders import load_dataset
from support.timing import best_shift, detection_scatter, detection_truth_error, odometry_truth_lag

DATA = {
    "mrclam": "mrclam:",  # the loaders' default folders under the shared data (MR.CLAM: Dataset 6)
    "car-park": "car-park:",
    "victoria-park": "victoria-park:",
}
AS_STAMPED = {"car-park": {"scan_delay_s": 0.0}}  # loader options that give the files' stamps


def measure(name: str, spec: str, shifts: np.ndarray, window: float, gate: float) -> dict:
    dataset = load_dataset(spec, **AS_STAMPED.get(name, {}))
    robots = {}
    for rid, log in dataset.robots.items():
        scatter = detection_scatter(log, shifts, window, gate)
        entry = {"detections_vs_odometry_s": round(best_shift(shifts, scatter), 3),
                 "scatter_m": {"at_0": round(float(scatter[np.argmin(np.abs(shifts))]), 4),
                               "at_best": round(float(scatter.min()), 4)}}
        has_angle = log.truth_pose.size and np.isfinite(log.truth_pose[:, 2]).all()
        if log.det_id is not None and dataset.landmarks is not None and has_angle:
            error = detection_truth_error(log, dataset.landmarks, np.asarray(dataset.landmark_ids), shifts)
            entry["detections_vs_truth_s"] = round(best_shift(shifts, error), 3)
            entry["detection_error_m"] = {"at_0": round(float(error[np.argmin(np.abs(shifts))]), 4),
                                          "at_best": round(float(error.min()), 4)}
            entry["odometry_vs_truth_s"] = round(best_shift(shifts, odometry_truth_lag(log, shifts)), 3)
        robots[rid] = entry
        print(f"{name} {rid}: {entry}", flush=True)
    return {"data": spec, "robots": robots}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=",".join(DATA), help=f"comma-separated, of: {', '.join(DATA)}")
    parser.add_argument("--window", type=float, default=2.0, help="detections of scans this close in time (s) are compared")
    parser.add_argument("--gate", type=float, default=1.0, help="detection pairs closer than this (m) are compared")
    parser.add_argument("--out", help="also write the JSON here")
    args = parser.parse_args()
    shifts = np.round(np.arange(-0.5, 0.3001, 0.025), 4)
    names = [name for name in args.data.split(",") if name]
    unknown = [name for name in names if name not in DATA]
    if unknown:
        parser.error(f"unknown data set(s) {', '.join(unknown)}: use {', '.join(DATA)}")
    emit({"window_s": args.window, "gate_m": args.gate,
          "data": {name: measure(name, DATA[name], shifts, args.window, args.gate) for name in names}}, args.out)


if __name__ == "__main__":
    main()
