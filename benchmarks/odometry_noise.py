"""Whether each data set's noise model (odometry and sensor covariances the loader gives) fits its own data,
measured without truth and without a filter.

Each detection is placed in the world from dead reckoning; two detections from different scans closer than
``--gate`` m are taken for the same landmark (landmarks stand still). Their distance comes from the odometry's
error between the two scans and from the two detections' own errors. Over pairs binned by the time between their
scans, the measured RMS distance is set against the one the model predicts: the odometry's part by dead reckonings
with controls drawn from the model's covariance (``--draws``, the same pairs), the sensor's part from each
detection's range and bearing variances. A model that fits predicts what is measured; a model too loose predicts
more at every interval (the car park's ACFR example noise, σ 0.7 m/s and 7° per reading, predicts 2–5 times the
measured scatter: docs/data.md). The gate keeps far pairs out, so a model that fits predicts a little more than is
measured at the longest intervals; where the predicted scatter reaches the gate (Victoria Park's sensor model, σ
0.5 m and 2°, predicts more than a 1 m gate lets through at every interval) the measured RMS is set against the
model's RMS within the gate ("within the gate": the pairs' predicted distances, cut at the gate), and a model much
too loose predicts about gate/√2 there, an even disc. Where landmarks stand closer than the gate (Victoria Park's
trees), pairs of neighbouring landmarks add to the measured scatter: compare gates (``--gate 0.5``).

    .venv/bin/python benchmarks/odometry_noise.py [--data car-park] [--odom-scale 1.0] [--sensor-scale 1.0]
        [--gate 1.0] [--out FILE]
"""

from __future__ import annotations

import argparse

import numpy as np

from report import emit
from robots.loaders import load_dataset
from support.noise_check import pair_scatter

DATA = {"car-park": "car-park:", "victoria-park": "victoria-park:", "mrclam": "mrclam:"}
BINS = np.array([0.0, 1.0, 2.0, 4.0, 8.0, 16.0, 40.0])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default="car-park", help=f"comma-separated, of: {', '.join(DATA)}")
    parser.add_argument("--gate", type=float, default=1.0, help="detection pairs closer than this (m) are compared")
    parser.add_argument("--draws", type=int, default=30, help="dead reckonings drawn from the odometry model")
    parser.add_argument("--odom-scale", type=float, default=1.0, help="multiplies the odometry covariance")
    parser.add_argument("--sensor-scale", type=float, default=1.0, help="multiplies the sensor covariance")
    parser.add_argument("--out", help="also write the JSON here")
    args = parser.parse_args()
    report: dict = {"gate_m": args.gate, "draws": args.draws, "odom_scale": args.odom_scale,
                    "sensor_scale": args.sensor_scale, "data": {}}
    for name in filter(None, args.data.split(",")):
        dataset = load_dataset(DATA[name])
        report["data"][name] = {rid: pair_scatter(log, BINS, args.gate, args.draws, odom_scale=args.odom_scale,
                                                          sensor_scale=args.sensor_scale)
                                for rid, log in dataset.robots.items()}
        for rid, rows in report["data"][name].items():
            for row in rows:
                print(f"{name} {rid} {row['from_s']:g}-{row['to_s']:g} s: {row['pairs']} pairs, measured "
                      f"{row['measured_m']:.3f} m, predicted {row['predicted_m']:.3f} m (odometry "
                      f"{row['odometry_m']:.3f}, sensor {row['sensor_m']:.3f}), within the gate "
                      f"{row['gated_m']:.3f} m", flush=True)
    emit(report, args.out)


if __name__ == "__main__":
    main()
