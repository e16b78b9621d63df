"""MCL update time against particle count (Sehestedt and Schneider report about 0.03 s per update).

Sehestedt and Schneider, "Monte Carlo Localization in Highly Symmetric Environments".

A map of 200 landmarks uniform in a 40 m square and the ``random`` world's
sensor (8 m range, 120° field of view, about 8 landmarks per scan); one robot
tracked from its known start pose (``mcl``, fixed sample size), and the same
robot in global localization (``cluster_kld_srl``, adaptive). Reports, per
particle count, the time of one scan update (weigh, cluster, resample) as
wall time and as this process's CPU time (less disturbed by other work on a
shared machine), of the likelihood alone (CPU; the numba kernel, and its numpy
reference in the same run: ``likelihood_speedup``), of one odometry message (``predict``, wall: buffered, MCL
moves its particles once per scan) and of applying a scan's buffered odometry (``motion``, wall: one draw per
particle from the integrated motion): median and 10th/90th percentiles over the run. ``kernel_warm_up_s``: compiling
(or loading the cached) kernel before the first run.

    .venv/bin/python benchmarks/mcl_timing.py [--out FILE] [--particles 100,300,1000,3000]
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from robots.simulator import simulate
from robots.worlds import make_world
from schemas.contract import OdomEvent, ScanEvent
from services.mcl.config import MclConfig
from services.mcl.core import MonteCarloLocalizer
from services import compiled
from services.mcl.likelihood import scan_log_likelihood
from report import emit


def landmark_world(count: int, seed: int):
    rng = np.random.default_rng([seed, 7])
    base = make_world("random", seed)
    return dataclasses.replace(
        base, name=f"uniform{count}", landmarks=rng.uniform(0.0, 40.0, size=(count, 2)), bounds=(6.0, 34.0, 6.0, 34.0),
        start_poses=lambda i: np.array([10.0, 10.0, 0.3]),
    )


def percentiles(samples: list[float]) -> dict:
    ms = np.asarray(samples) * 1e3
    return {"median_ms": round(float(np.median(ms)), 3), "p10_ms": round(float(np.percentile(ms, 10)), 3),
            "p90_ms": round(float(np.percentile(ms, 90)), 3)}


def timed(work) -> tuple[float, float]:
    """(wall, CPU) seconds of ``work()``: the CPU time of this process is less disturbed by a busy machine."""
    wall, cpu = time.perf_counter(), time.process_time()
    work()
    return time.perf_counter() - wall, time.process_time() - cpu


def run(dataset, variant: str, particles: int, known_start: bool, seed: int) -> dict:
    log = dataset.robots["r1"]
    info = log.info if known_start else log.info.model_copy(update={"start_pose": None, "start_pose_cov": None})
    config = MclConfig(variant=variant, particles=particles, seed=seed,
                       max_particles=max(particles, 5000), min_particles=min(100, particles))
    mcl = MonteCarloLocalizer(dataset.landmarks, info, config)
    times: dict[str, list] = {"update": [], "update_cpu": [], "likelihood": [], "likelihood_numpy": [], "predict": [],
                               "motion": []}
    counts, observations = [], []
    for event in dataset.events():
        if isinstance(event, OdomEvent):
            times["predict"].append(timed(lambda: mcl.predict(event.control, event.dt, event.control_cov))[0])
        elif isinstance(event, ScanEvent):
            z = event.observations
            if mcl.initialized:
                times["motion"].append(timed(lambda: mcl.particles)[0])
                times["likelihood"].append(timed(lambda: scan_log_likelihood(mcl.particles, z, mcl.map, mcl.model))[1])
                times["likelihood_numpy"].append(timed(lambda: scan_log_likelihood(
                    mcl.particles, z, mcl.map, mcl.model, compiled=False))[1])
            wall, cpu = timed(lambda: mcl.update(z))
            times["update"].append(wall)
            times["update_cpu"].append(cpu)
            counts.append(mcl.count)
            observations.append(len(z))
    summary = {name: percentiles(samples[5:]) for name, samples in times.items()}
    speedup = summary["likelihood_numpy"]["median_ms"] / max(summary["likelihood"]["median_ms"], 1e-9)
    return {"variant": variant, "particles": particles, "known_start": known_start, **summary,
            "likelihood_speedup": round(speedup, 2),
            "particles_median": int(np.median(counts)), "observations_median": float(np.median(observations)),
            "scans": len(counts)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", help="also write the JSON here")
    parser.add_argument("--particles", default="100,300,1000,3000")
    parser.add_argument("--landmarks", type=int, default=200)
    parser.add_argument("--duration", type=float, default=20.0, help="robot seconds per run")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    warm_up_s = compiled.warm_up()
    world = landmark_world(args.landmarks, args.seed)
    dataset = simulate(world, seed=args.seed, duration=args.duration)
    results = [run(dataset, "mcl", int(p), True, args.seed) for p in args.particles.split(",")]
    results.append(run(dataset, "cluster_kld_srl", 1000, False, args.seed))
    report = {"benchmark": "mcl_timing", "landmarks": args.landmarks, "world": world.name, "duration_s": args.duration,
              "target": "update <= 1 ms for 1000 particles with 200 landmarks", "kernel_warm_up_s": round(warm_up_s, 3),
              "runs": results}
    emit(report, args.out)


if __name__ == "__main__":
    main()
