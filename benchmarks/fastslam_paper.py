"""Howard's multi-robot FastSLAM simulations with the central core: close beacons, four beacons, two robots.

The paper: Howard, "Multi-robot simultaneous localization and mapping using particle filters" (paper 001).

- ``two-beacons`` (Fig. 2-3): two beacons 18 cm apart at (4, 6.8), 15 cm range noise, three laps. A run
  *separates* them when the published map has exactly two landmarks within 0.4 m of the pair, each within
  half the separation (9 cm) of its own beacon after aligning the map on the six anchor beacons. Compared:
  ``nn-paper`` (per-detection nearest neighbour, no one-detection-per-landmark rule: the paper's NNF),
  ``nn`` (with that rule), ``mht`` and ``mht-paper`` (the split, with and without the rule).
- ``four-beacons`` (Fig. 13): four beacons 1-1.5 m apart, ``mht`` with 200 particles: final error of the
  four beacons (raw, and after aligning on the anchors).
- ``two-robots`` (Fig. 14): two robots on neighbouring circles; each alone (500 particles, as in the
  paper) and both in one filter (800 particles): position error RMSE of each robot.

    .venv/bin/python benchmarks/fastslam_paper.py [--parts two-beacons,four-beacons,two-robots]
        [--seeds 5] [--laps 3] [--bearing-std-deg 1] [--out FILE]
"""

from __future__ import annotations

import argparse

import numpy as np

from report import emit
from robots.simulator import simulate
from schemas.contract import RunOptions
from services.evaluation.metrics import map_error
from support.fastslam_experiments import aligned_map_error, run_and_score
from support.paper001 import ANCHORS, four_beacons, two_beacons, two_robots

LAP_S = 2 * np.pi / 0.1  # one lap of the 5 m circle at 0.1 rad/s
METHODS = {"nn-paper": ("nn", {"exclusive": False}), "nn": ("nn", {}), "mht": ("mht", {}),
           "mht-paper": ("mht", {"exclusive": False})}


def two_beacons_run(method: str, seed: int, laps: float, particles: int, bearing_std_deg: float) -> dict:
    world = two_beacons(bearing_std_deg=bearing_std_deg)
    data = simulate(world, seed=seed, duration=laps * LAP_S)
    association, settings = METHODS[method]
    run = run_and_score(data, RunOptions("fastslam", association, particles, seed, settings))
    pair = world.landmarks[:2]
    _, aligned = aligned_map_error(run["map_means"], world.landmarks, ANCHORS)
    near = aligned[np.linalg.norm(aligned - pair.mean(0), axis=1) < 0.4]
    separation = float(np.linalg.norm(pair[0] - pair[1]))
    separated = False
    errors = None
    if len(near) == 2:
        d = np.linalg.norm(near[:, None] - pair[None], axis=-1)
        errors = sorted([d[0, 0], d[1, 1]] if d[0, 0] + d[1, 1] <= d[0, 1] + d[1, 0] else [d[0, 1], d[1, 0]])
        separated = errors[1] < separation / 2
    return {"method": method, "seed": seed, "landmarks_near_pair": int(len(near)), "separated": bool(separated),
            "pair_errors_m": None if errors is None else [round(float(e), 3) for e in errors],
            "ate_rmse_m": run["ate_rmse_m"]["r1"], "cpu_s": run["cpu_s"]}


def four_beacons_run(seed: int, laps: float, particles: int) -> dict:
    world = four_beacons()
    data = simulate(world, seed=seed, duration=laps * LAP_S)
    run = run_and_score(data, RunOptions("fastslam", "mht", particles, seed))
    quad = world.landmarks[:4]
    raw = map_error(run["map_means"], quad, 0.5)
    aligned, _ = aligned_map_error(run["map_means"], quad, ANCHORS, cutoff=0.5)
    return {"seed": seed, "beacon_rmse_m": _round(raw["rmse_m"]), "beacon_rmse_aligned_m": _round(aligned["rmse_m"]),
            "beacons_found": raw["matched"], "landmarks_mapped": run["landmarks_mapped"],
            "ate_rmse_m": run["ate_rmse_m"]["r1"], "cpu_s": run["cpu_s"]}


def _round(value: float | None) -> float | None:
    return None if value is None else round(value, 3)


def two_robots_run(seed: int, laps: float, alone: int, together: int, association: str) -> dict:
    data = simulate(two_robots(), robots=2, seed=seed, duration=laps * LAP_S)
    row = {"seed": seed}
    for rid in data.robots:
        run = run_and_score(data, RunOptions("fastslam", association, alone, seed), robots=[rid])
        row[f"{rid}_alone_m"] = run["ate_rmse_m"][rid]
    run = run_and_score(data, RunOptions("fastslam", association, together, seed))
    for rid, value in run["ate_rmse_m"].items():
        row[f"{rid}_central_m"] = value
    row["map_rmse_central_m"] = run.get("map_rmse_m")
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", default="two-beacons,four-beacons,two-robots")
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--laps", type=float, default=3.0)
    parser.add_argument("--particles", type=int, default=100, help="particles of the two-beacon runs")
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--bearing-std-deg", type=float, default=1.0, help="bearing noise of the two-beacon world")
    parser.add_argument("--association", default="nn", help="association of the two-robot runs")
    parser.add_argument("--out")
    args = parser.parse_args()
    parts = args.parts.split(",")
    report: dict = {"settings": vars(args)}
    if "two-beacons" in parts:
        rows = [two_beacons_run(m, s, args.laps, args.particles, args.bearing_std_deg)
                for m in args.methods.split(",") for s in range(args.seeds)]
        report["two_beacons"] = {
            "summary": {m: {"separated": sum(r["separated"] for r in rows if r["method"] == m),
                            "runs": sum(r["method"] == m for r in rows)} for m in args.methods.split(",")},
            "runs": rows}
    if "four-beacons" in parts:
        rows = [four_beacons_run(s, args.laps, 200) for s in range(args.seeds)]
        values = [r["beacon_rmse_aligned_m"] for r in rows if r["beacon_rmse_aligned_m"] is not None]
        raw = [r["beacon_rmse_m"] for r in rows if r["beacon_rmse_m"] is not None]
        report["four_beacons"] = {"summary": {"beacon_rmse_m_median": float(np.median(raw)) if raw else None,
                                              "beacon_rmse_aligned_m_median": float(np.median(values)) if values else None,
                                              "all_four_found": sum(r["beacons_found"] == 4 for r in rows),
                                              "runs": len(rows)}, "runs": rows}
    if "two-robots" in parts:
        rows = [two_robots_run(s, args.laps, 500, 800, args.association) for s in range(args.seeds)]
        summary = {}
        for rid in ("r1", "r2"):
            summary[rid] = {"alone_m_median": float(np.median([r[f"{rid}_alone_m"] for r in rows])),
                            "central_m_median": float(np.median([r[f"{rid}_central_m"] for r in rows])),
                            "central_better": sum(r[f"{rid}_central_m"] < r[f"{rid}_alone_m"] for r in rows)}
        report["two_robots"] = {"summary": summary, "runs": rows}
    emit(report, args.out)


if __name__ == "__main__":
    main()
