"""Global localization success rate over random starts (Sehestedt and Schneider §6: "successfully done in all cases").

Sehestedt and Schneider, "Monte Carlo Localization in Highly Symmetric Environments".

Each trial puts one robot at a random pose (uniform over the world's bounds,
any heading), simulates ``--duration`` seconds of its own trajectory, and
runs MCL from no pose at all against the world's map. A trial succeeds when
the filter is localized (one hypothesis holds) within 0.5 m / 0.2 rad of the
truth at the end of the run; ``converge_s`` is the robot time of the first
such scan. The ``grid196`` world (a regular 3 m grid) is highly symmetric:
only its borders tell places apart; ``office`` mixes repeated structure with
unique features.

    .venv/bin/python benchmarks/mcl_global.py [--worlds office,grid196] [--trials 40] [--out FILE]
"""

from __future__ import annotations

import argparse

import numpy as np

from robots.simulator import simulate
from robots.worlds import make_world
from services.mcl.config import MclConfig
from services.mcl.core import MonteCarloLocalizer
from support.mcl_scenarios import random_starts, trace_run
from report import emit


def trial(world_name: str, variant: str, seed: int, duration: float, particles: int) -> dict:
    world = random_starts(make_world(world_name, 0), 1, seed)
    start = world.start_poses(0)
    dataset = simulate(world, seed=seed, duration=duration, unknown_start=True)
    log = dataset.robots["r1"]
    config = MclConfig(variant=variant, seed=seed, particles=particles)
    mcl = MonteCarloLocalizer(dataset.landmarks, log.info, config)
    trace = trace_run(mcl, dataset.events(), lambda t: log.truth_at(np.array([t]))[0])
    return {"seed": seed, "start": np.round(start, 2).tolist(), "success": bool(trace.converged(0.5, 0.2)[-1]),
            "converge_s": trace.first_converged(0.5, 0.2), "hypotheses_max": int(max(trace.hypotheses)),
            "final_error_m": round(trace.error_m[-1], 3), "restarts": mcl.restarts}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", default="office,grid196")
    parser.add_argument("--variants", default="cluster_kld_srl")
    parser.add_argument("--trials", type=int, default=40)
    parser.add_argument("--duration", type=float, default=60.0)
    parser.add_argument("--particles", type=int, default=1000)
    parser.add_argument("--out")
    args = parser.parse_args()
    summary, runs = {}, []
    for world in args.worlds.split(","):
        for variant in args.variants.split(","):
            rows = [trial(world, variant, seed, args.duration, args.particles) for seed in range(args.trials)]
            runs += [{"world": world, "variant": variant, **row} for row in rows]
            converge = [r["converge_s"] for r in rows if r["success"] and r["converge_s"] is not None]
            summary[f"{world}/{variant}"] = {
                "trials": len(rows), "successes": sum(r["success"] for r in rows),
                "success_rate": round(sum(r["success"] for r in rows) / len(rows), 3),
                "converge_s_median": float(np.median(converge)) if converge else None,
                "converge_s_p90": float(np.percentile(converge, 90)) if converge else None,
            }
    report = {"benchmark": "mcl_global", "duration_s": args.duration, "particles": args.particles,
              "target": "success >= 95 % over random starts in the office layout", "summary": summary, "runs": runs}
    emit(report, args.out)


if __name__ == "__main__":
    main()
