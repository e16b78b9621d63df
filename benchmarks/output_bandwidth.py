"""What the map outputs cost on the wire against the map's size: central's estimate and D-SLAM's map at 10² and 10⁴
landmarks (issue 54: the steady cost the same within 20 %).

The worlds of :mod:`support.grid_world` (N landmarks on a 3 m grid, a 180° / 5 m sensor); every landmark is mapped
first (central: each particle's map holds them all, as :mod:`fastslam_scaling` prefills it; D-SLAM: the map of a
lawnmower sweep, as :mod:`dslam_scaling` builds it), then one robot drives two laps of a 4 m circle in the middle,
a scan every 0.5 s. The services' own message builders are called at their default rates (central:
:meth:`CentralService.estimate` at ``estimate_rate_hz``, D-SLAM: :meth:`DslamService.map_message` every
``map_period_s``, both with their default tiles and tolerances) and every message is encoded with the codec: the
payload bytes per second of data time, after the first (full) message and a first lap, against what the whole map
sent every time costs (the message a state query gets). Zenoh and TCP framing are left out: a few dozen bytes per
message, the same at every map size.

    .venv/bin/python benchmarks/output_bandwidth.py [--sizes 100,10000] [--laps 2] [--seed 0] [--out FILE]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse

import numpy as np

from central.service import CentralService
from dslam_scaling import mapped_world
from fastslam_scaling import prefilled
from report import emit
from schemas.codec import encode
from schemas.config import CentralSettings, DslamSettings
from schemas.maptiles import TileSender
from services.dslam.config import DslamConfig
from services.dslam.core import DSlam
from services.dslam.service import DslamService
from support.grid_world import CIRCLE_DT, SCANS_PER_LAP, GridWorld


def _cost(sizes: list[int], seconds: float) -> dict:
    steady = np.asarray(sizes, float)
    return {"bytes_per_s": float(steady.sum() / seconds), "messages": int(steady.size), "each": [int(b) for b in steady],
            "bytes_median": float(np.median(steady)), "bytes_max": float(steady.max())}


def _whole_map_bytes(service, full_message) -> int:
    """The bytes of the whole map sent every time (a state query's full reply), measured with a sender of its own so
    that the service's sender is not told of a reply nobody asked for."""
    own = service.map_tiles
    service.map_tiles = TileSender(own.tile_size, own.tolerance_m, own.cov_tolerance)
    try:
        return len(encode(full_message()))
    finally:
        service.map_tiles = own


def central_output(n: int, laps: int, seed: int, tile_m: float) -> dict:
    world = GridWorld(n)
    service = CentralService(CentralSettings(association="known", particles=100, seed=seed, map_tile_m=tile_m))
    service.slam = prefilled(world, 100, "known", seed)
    period = 1.0 / service.settings.estimate_rate_hz
    rng = np.random.default_rng([seed, n, 1])
    deltas, wholes, due, first = [], [], 0.0, None
    for odometry, scan, _ in world.circle(rng, laps * SCANS_PER_LAP):
        service.slam.on_odometry(odometry)
        service.slam.on_scan(scan)
        service.last_stamp = scan.stamp
        if scan.stamp + 1e-9 < due:
            continue
        due = scan.stamp + period
        message = service.estimate()
        if first is None:
            first = len(encode(message))
            continue
        if scan.stamp > SCANS_PER_LAP * CIRCLE_DT:  # after a lap: the steady state
            deltas.append(len(encode(message)))
            wholes.append(_whole_map_bytes(service, lambda: service.estimate(publish=False)))
    seconds = len(deltas) * period
    return {"landmarks": n, "rate_hz": service.settings.estimate_rate_hz, "first_full_bytes": first,
            "delta": _cost(deltas, seconds), "whole_map_every_time": _cost(wholes, seconds)}


def dslam_output(n: int, laps: int, seed: int, tile_m: float) -> dict:
    world, m, keys, _, rng = mapped_world(n, seed)
    service = DslamService(DslamSettings(association="known", map_tile_m=tile_m))
    service.core = DSlam(DslamConfig(association="known"))
    service.core.adopt(m, keys)
    service.core.add_robot(world.robot_info(world.circle_start()))
    period = service.settings.map_period_s
    deltas, wholes, due, first = [], [], 0.0, None
    for odometry, scan, _ in world.circle(rng, laps * SCANS_PER_LAP):
        service.core.on_odometry(odometry)
        service.core.on_scan(scan)
        if scan.stamp + 1e-9 < due:
            continue
        due = scan.stamp + period
        message = service.map_message()
        service._map_seq += 1
        if first is None:
            first = len(encode(message))
            continue
        if scan.stamp > SCANS_PER_LAP * CIRCLE_DT:
            deltas.append(len(encode(message)))
            wholes.append(_whole_map_bytes(service, lambda: service.map_message(publish=False)))
    seconds = len(deltas) * period
    return {"landmarks": n, "period_s": period, "first_full_bytes": first,
            "delta": _cost(deltas, seconds), "whole_map_every_time": _cost(wholes, seconds)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="100,10000", help="landmark counts, comma-separated (the first is the base)")
    parser.add_argument("--laps", type=int, default=2, help="laps of the circle (the first: warm-up)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--tile-m", type=float, default=CentralSettings.model_fields["map_tile_m"].default,
                        help="the services' map_tile_m (default: theirs)")
    parser.add_argument("--outputs", default="central,dslam", help="which outputs, comma-separated")
    parser.add_argument("--out")
    args = parser.parse_args()
    if args.laps < 2:
        parser.error("--laps must be at least 2 (the first lap is not counted)")
    sizes = [int(s) for s in args.sizes.split(",")]
    measure = {"central": central_output, "dslam": dslam_output}
    runs = {output: {n: measure[output](n, args.laps, args.seed, args.tile_m) for n in sizes}
            for output in args.outputs.split(",")}
    base = sizes[0]
    ratios = {output: {n: round(r[n]["delta"]["bytes_per_s"] / r[base]["delta"]["bytes_per_s"], 3) for n in sizes}
              for output, r in runs.items()}
    emit({"benchmark": "output_bandwidth", "settings": vars(args),
          "target": "each output's steady bytes/s at the largest map within 20 % of the smallest's",
          "runs": runs, "delta_bytes_per_s_ratio_to_smallest": ratios,
          "met": all(abs(r - 1.0) <= 0.2 for output in ratios.values() for r in output.values())}, args.out)


if __name__ == "__main__":
    main()
