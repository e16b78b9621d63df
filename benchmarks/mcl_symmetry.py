"""MCL in the symmetric cross (Sehestedt and Schneider §6, figures 1-2): which variants keep every plausible pose.

Sehestedt and Schneider, "Monte Carlo Localization in Highly Symmetric Environments".

The ``cross`` world is four-fold symmetric except for a room off the east arm.
A robot starts near the centre with no pose and tours the north, west and
south arms before entering the room. From the truth we count, at each scan,
the *consistent twins*: the rotations of the true pose by 0°, 90°, 180°, 270°
whose view (landmarks within range) has matched the true view at every scan
so far — the hypotheses a perfect filter would still hold. For every variant
we report, over several seeds, how often the truth is among the significant
hypotheses (``truth_held``), how often the filter holds fewer hypotheses than
there are consistent twins (``premature``), when it first holds a single one,
and when it converges on the truth. A PNG shows, for one seed, the
hypotheses over time against the consistent twins, and the hypothesis
means of a clustered and a plain variant on the map.

    .venv/bin/python benchmarks/mcl_symmetry.py [--seeds 5] [--particles 300] [--out FILE] [--png FILE]
"""

from __future__ import annotations

import argparse

import numpy as np

from robots.models import RangeBearingSensor, rotation
from robots.simulator import simulate
from robots.worlds import make_world
from services.mcl.config import MclConfig
from services.mcl.core import VARIANTS, MonteCarloLocalizer
from support.mcl_scenarios import Trace, trace_run
from report import emit


def consistent_twins(world, truth: np.ndarray) -> np.ndarray:
    """Per truth pose ``(T, 3)``: how many of the four rotated poses have matched the true view so far."""
    sensor = RangeBearingSensor(tuple(world.sensor.offset))
    alive = np.ones(4, bool)
    counts = []
    for pose in truth:
        seen = sensor.observe(pose, world.landmarks)[:, 0] <= world.sensor.max_range
        reference = np.sort(np.round(world.landmarks[seen], 3), axis=0)
        for k in range(1, 4):
            angle = k * np.pi / 2
            twin = np.concatenate([rotation(angle) @ pose[:2], [pose[2] + angle]])
            twin_seen = sensor.observe(twin, world.landmarks)[:, 0] <= world.sensor.max_range
            back = world.landmarks[twin_seen] @ rotation(angle)  # rotate the twin's view back by -angle
            same = twin_seen.sum() == seen.sum() and np.allclose(np.sort(np.round(back, 3), axis=0), reference, atol=1e-2)
            alive[k] &= same
        counts.append(int(alive.sum()))
    return np.array(counts)


def truth_held(trace: Trace, truth_at, xy: float = 0.5, theta: float = 0.2) -> np.ndarray:
    """Per scan: is some significant hypothesis within (xy, theta) of the truth?"""
    held = []
    for stamp, means in zip(trace.stamp, trace.means):
        actual = truth_at(stamp)
        dxy = np.hypot(*(means[:, :2] - actual[:2]).T)
        dth = np.abs(np.mod(means[:, 2] - actual[2] + np.pi, 2 * np.pi) - np.pi)
        held.append(bool(np.any((dxy <= xy) & (dth <= theta))))
    return np.array(held)


def run_variant(dataset, world, variant: str, particles: int, seed: int) -> tuple[dict, Trace, np.ndarray]:
    log = dataset.robots["r1"]
    config = MclConfig(variant=variant, particles=particles, seed=seed)
    mcl = MonteCarloLocalizer(dataset.landmarks, log.info, config)
    truth_at = lambda t: log.truth_at(np.array([t]))[0]  # noqa: E731
    trace = trace_run(mcl, dataset.events(), truth_at)
    twins = consistent_twins(world, log.truth_at(np.asarray(trace.stamp)))
    held = truth_held(trace, truth_at)
    hyps = np.asarray(trace.hypotheses)
    stamps = np.asarray(trace.stamp)
    single = np.flatnonzero(hyps <= 1)
    symmetric_until = float(stamps[np.flatnonzero(twins <= 1)[0]]) if np.any(twins <= 1) else None
    result = {
        "variant": variant, "seed": seed,
        "truth_held": float(held[1:].mean()),
        "premature": float(np.mean(hyps[1:] < twins[1:])),
        "first_single_s": float(stamps[single[0]]) if single.size else None,
        "symmetric_until_s": symmetric_until,
        "converge_s": trace.first_converged(0.5, 0.2),
        "final_correct": bool(trace.converged(0.5, 0.2)[-1]),
        "restarts": mcl.restarts,
        "particles_mean": float(np.mean(trace.particles)),
    }
    return result, trace, twins


def summarise(results: list[dict]) -> dict:
    out = {}
    for variant in sorted({r["variant"] for r in results}, key=VARIANTS.index):
        rows = [r for r in results if r["variant"] == variant]
        singles = [r["first_single_s"] for r in rows if r["first_single_s"] is not None]
        converge = [r["converge_s"] for r in rows if r["converge_s"] is not None]
        out[variant] = {
            "runs": len(rows),
            "truth_held_mean": round(float(np.mean([r["truth_held"] for r in rows])), 3),
            "premature_mean": round(float(np.mean([r["premature"] for r in rows])), 3),
            "first_single_s_median": float(np.median(singles)) if singles else None,
            "symmetric_until_s_median": float(np.median([r["symmetric_until_s"] for r in rows if r["symmetric_until_s"]])),
            "converge_s_median": float(np.median(converge)) if converge else None,
            "final_correct": sum(r["final_correct"] for r in rows),
        }
    return out


def plot(path: str, world, runs: dict[str, tuple[Trace, np.ndarray]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(13, 8))
    top = fig.add_subplot(2, 1, 1)
    twins_drawn = False
    for variant, (trace, twins) in runs.items():
        if not twins_drawn:
            top.step(trace.stamp, twins, where="post", color="k", lw=3, alpha=0.3, label="consistent twins (truth)")
            twins_drawn = True
        top.step(trace.stamp, np.asarray(trace.hypotheses) + 0.04 * list(runs).index(variant), where="post", label=variant)
    top.set_xlabel("robot time (s)")
    top.set_ylabel("significant hypotheses")
    top.set_yticks(range(0, 6))
    top.legend(loc="upper right", ncol=4, fontsize=8)
    top.set_title("cross world: hypotheses held against the poses the scans cannot tell apart")
    moments = (2.0, 20.0, 45.0, 70.0)
    colours = ("tab:blue", "tab:green", "tab:orange", "tab:red")
    for column, variant in enumerate(("cluster_kld_srl", "mcl")):
        if variant not in runs:
            continue
        ax = fig.add_subplot(2, 2, 3 + column)
        trace, _ = runs[variant]
        ax.scatter(world.landmarks[:, 0], world.landmarks[:, 1], marker="*", c="k", s=30)
        stamps = np.asarray(trace.stamp)
        for moment, colour in zip(moments, colours):
            k = int(np.argmin(np.abs(stamps - moment)))
            means = trace.means[k]
            ax.quiver(means[:, 0], means[:, 1], np.cos(means[:, 2]), np.sin(means[:, 2]), color=colour, scale=25,
                      width=0.006, label=f"t = {stamps[k]:.0f} s: {len(means)} hypotheses")
        ax.set_aspect("equal")
        ax.legend(loc="lower left", fontsize=7)
        ax.set_title(f"{variant}: hypotheses (mean pose) at four moments")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--particles", type=int, default=300, help="sample size (fixed variants; initial for adaptive)")
    parser.add_argument("--duration", type=float, default=100.0)
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--out", help="also write the JSON here")
    parser.add_argument("--png", help="figure of the first seed")
    args = parser.parse_args()
    world = make_world("cross")
    results, first = [], {}
    for seed in range(args.seeds):
        dataset = simulate(world, seed=seed, duration=args.duration, unknown_start=True)
        for variant in args.variants.split(","):
            result, trace, twins = run_variant(dataset, world, variant, args.particles, seed)
            results.append(result)
            if seed == 0:
                first[variant] = (trace, twins)
    report = {"benchmark": "mcl_symmetry", "world": "cross", "seeds": args.seeds, "particles": args.particles,
              "duration_s": args.duration, "summary": summarise(results), "runs": results}
    if args.png:
        plot(args.png, world, first)
        report["png"] = args.png
    emit(report, args.out)


if __name__ == "__main__":
    main()
