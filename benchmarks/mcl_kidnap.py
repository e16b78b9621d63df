"""Recovery from kidnapping (Sehestedt and Schneider §6: about 2 s): robot time until MCL is back on the truth.

Sehestedt and Schneider, "Monte Carlo Localization in Highly Symmetric Environments".

Each trial simulates two robots from random poses in one world and splices them: the filter
localizes robot 1 from no pose and follows it until ``--at`` seconds, then receives robot 2's odometry and
scans, as if the robot had been carried to robot 2's place. Recovery time is
the robot time from the kidnap to the first scan at which the filter is again
localized (one hypothesis holds) within 0.5 m / 0.2 rad of the truth.

    .venv/bin/python benchmarks/mcl_kidnap.py [--trials 10] [--world office] [--out FILE]
"""

from __future__ import annotations

import argparse

import numpy as np

from robots.simulator import simulate
from robots.worlds import make_world
from services.mcl.config import MclConfig
from services.mcl.core import MonteCarloLocalizer
from support.mcl_scenarios import kidnapped, random_starts, trace_run
from report import emit


def trial(world: str, variant: str, seed: int, at: float, duration: float, particles: int) -> dict:
    dataset = simulate(random_starts(make_world(world, seed), 2, seed), robots=2, seed=seed, duration=duration,
                       unknown_start=True)
    events, truth = kidnapped(dataset, "r1", "r2", at)
    config = MclConfig(variant=variant, seed=seed, particles=particles)
    mcl = MonteCarloLocalizer(dataset.landmarks, dataset.robots["r1"].info, config)
    trace = trace_run(mcl, events, truth)
    before = trace.first_converged(0.5, 0.2)
    back = trace.first_converged(0.5, 0.2, after=at)
    stamps = np.asarray(trace.stamp)
    detected = stamps[np.asarray(trace.kidnapped) & (stamps >= at)]
    return {"seed": seed, "localized_before_s": before, "recovery_s": None if back is None else round(back - at, 3),
            "detected_after_s": round(float(detected[0] - at), 3) if detected.size else None,
            "final_correct": bool(trace.converged(0.5, 0.2)[-1])}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="office")
    parser.add_argument("--variants", default="cluster_kld_srl,csrl,kld_srl,srl,mcl")
    parser.add_argument("--trials", type=int, default=10)
    parser.add_argument("--at", type=float, default=15.0, help="robot time of the kidnap (s)")
    parser.add_argument("--duration", type=float, default=30.0)
    parser.add_argument("--particles", type=int, default=1000)
    parser.add_argument("--out")
    args = parser.parse_args()
    summary, runs = {}, []
    for variant in args.variants.split(","):
        rows = [trial(args.world, variant, seed, args.at, args.duration, args.particles) for seed in range(args.trials)]
        runs += [{"variant": variant, **row} for row in rows]
        times = np.array([r["recovery_s"] if r["recovery_s"] is not None else np.inf for r in rows])
        done = times[np.isfinite(times)]
        summary[variant] = {
            "trials": len(rows),
            "recovered": int(done.size),
            "within_2s": int(np.sum(times <= 2.0)),
            "recovery_s_median": float(np.median(times)) if done.size else None,
            "recovery_s_p90": float(np.percentile(times, 90)) if np.all(np.isfinite(times)) else None,
            "recovery_s_max": float(done.max()) if done.size else None,
            "detected_after_s_median": (float(np.median(detected)) if (detected := [
                r["detected_after_s"] for r in rows if r["detected_after_s"] is not None]) else None),
        }
    report = {"benchmark": "mcl_kidnap", "world": args.world, "kidnap_at_s": args.at, "trials": args.trials,
              "particles": args.particles, "target": "recovery within 2 s of robot time", "summary": summary,
              "runs": runs}
    emit(report, args.out)


if __name__ == "__main__":
    main()
