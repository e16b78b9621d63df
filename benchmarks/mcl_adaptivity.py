"""KLD adaptivity: sample size over time for the adaptive variants (Fox 2003; Sehestedt and Schneider tables 2, 4).

Sehestedt and Schneider, "Monte Carlo Localization in Highly Symmetric Environments".

Global localization from no pose, a kidnap half-way, and tracking: in the
``office`` world (two robots from random poses spliced at ``--at``) and in the
symmetric ``cross`` world (one robot). Reports per variant the sample size at
the start, while tracking (median), right after the kidnap (max within 2 s)
and its mean; the PNG shows the sample size over time.

    .venv/bin/python benchmarks/mcl_adaptivity.py [--out FILE] [--png FILE]
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

VARIANTS = ("kld", "kld_srl", "cluster_kld_srl")


def scenarios(seed: int, at: float, duration: float):
    office = simulate(random_starts(make_world("office", seed), 2, seed), robots=2, seed=seed, duration=duration,
                      unknown_start=True)
    events, truth = kidnapped(office, "r1", "r2", at)
    yield "office (kidnapped)", office, list(events), truth, at
    cross = simulate("cross", seed=seed, duration=duration * 3, unknown_start=True)
    log = cross.robots["r1"]
    yield "cross", cross, list(cross.events()), lambda t: log.truth_at(np.array([t]))[0], None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--at", type=float, default=20.0)
    parser.add_argument("--duration", type=float, default=40.0)
    parser.add_argument("--out")
    parser.add_argument("--png")
    args = parser.parse_args()
    results, curves = [], {}
    for name, dataset, events, truth, at in scenarios(args.seed, args.at, args.duration):
        for variant in VARIANTS:
            config = MclConfig(variant=variant, seed=args.seed)
            mcl = MonteCarloLocalizer(dataset.landmarks, dataset.robots["r1"].info, config)
            trace = trace_run(mcl, events, truth)
            stamps, counts = np.asarray(trace.stamp), np.asarray(trace.particles)
            tracking = trace.converged(0.5, 0.2)
            row = {"scenario": name, "variant": variant, "initial": int(counts[0]),
                   "tracking_median": int(np.median(counts[tracking])) if tracking.any() else None,
                   "mean": float(counts.mean()), "max": int(counts.max())}
            if at is not None:
                window = (stamps >= at) & (stamps <= at + 2.0)
                row["after_kidnap_max"] = int(counts[window].max())
            results.append(row)
            curves[(name, variant)] = (stamps, counts)
    report = {"benchmark": "mcl_adaptivity", "seed": args.seed, "kidnap_at_s": args.at, "runs": results}
    if args.png:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        names = sorted({name for name, _ in curves}, reverse=True)
        fig, axes = plt.subplots(len(names), 1, figsize=(11, 3.5 * len(names)))
        for ax, name in zip(np.atleast_1d(axes), names):
            for variant in VARIANTS:
                stamps, counts = curves[(name, variant)]
                ax.step(stamps, counts, where="post", label=variant)
            if name.startswith("office"):
                ax.axvline(args.at, color="k", ls="--", lw=1, label="kidnap")
            ax.set_yscale("log")
            ax.set_ylabel("particles")
            ax.set_xlabel("robot time (s)")
            ax.set_title(f"{name}: sample size over time")
            ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(args.png, dpi=110)
        report["png"] = args.png
    emit(report, args.out)


if __name__ == "__main__":
    main()
