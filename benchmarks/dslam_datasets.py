"""D-SLAM on real data: MR.CLAM Dataset 6 (five robots feeding one map) and Victoria Park.

Each run goes through the offline path of ``fleetslam run`` (the same core as
the service, no Zenoh) and is scored by :mod:`services.evaluation.metrics`;
dead reckoning (``odometry``) is run beside it as the baseline.

- MR.CLAM Dataset 6: the five robots' scans (known barcodes → landmark ids)
  update one D-SLAM map; Vicon truth for the robots and the 15 landmarks.
- Victoria Park: one car, tree detections without ids, association by the
  ``auto`` method of :func:`services.association.core.associate`; the error is
  measured at the GPS fixes after SE(2) alignment.

    .venv/bin/python benchmarks/dslam_datasets.py --out reports/dslam/datasets.json
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
from pathlib import Path

from schemas.config import RunSettings
from services.offline import run
from report import emit

REPO = Path(__file__).resolve().parents[1]
KEEP = ("wall_s", "data_s", "realtime_factor", "events", "ate_rmse_m", "ate_aligned_rmse_m", "gps_rmse_m",
        "map_rmse_m", "landmarks", "nees", "timing", "dslam")


def data_root() -> Path:
    return Path(os.environ.get("FLEETSLAM_DATA", REPO.parent / "shared" / "data"))


def one(dataset: str, estimator: str, association: str, duration: float | None) -> dict:
    settings = RunSettings(dataset=dataset, estimator=estimator, association=association, duration=duration,
                           out=None, progress=False)
    output = run(settings)
    return {key: output[key] for key in KEEP if key in output}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mrclam-duration", type=float, default=None, help="seconds of MR.CLAM data (default: all)")
    parser.add_argument("--victoria-duration", type=float, default=None, help="seconds of Victoria Park data (default: all)")
    parser.add_argument("--skip", default="", help="comma-separated: mrclam, victoria")
    parser.add_argument("--out")
    args = parser.parse_args()
    root = data_root()
    skip = set(filter(None, args.skip.split(",")))
    result: dict = {"benchmark": "dslam_datasets", "data": str(root)}
    if "mrclam" not in skip:
        path = f"mrclam:{root / 'utias_mrclam' / 'MRCLAM_Dataset6'}"
        result["mrclam6"] = {"dslam": one(path, "dslam", "known", args.mrclam_duration),
                             "odometry": one(path, "odometry", "known", args.mrclam_duration)}
    if "victoria" not in skip:
        path = f"victoria-park:{root / 'victoria_park'}"
        result["victoria_park"] = {"dslam": one(path, "dslam", "auto", args.victoria_duration),
                                   "odometry": one(path, "odometry", "known", args.victoria_duration)}
    emit(result, args.out)


if __name__ == "__main__":
    main()
