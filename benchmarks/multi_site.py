"""Three sites meshed over slow, lossy links, with faults: the scenario of tests/integration/sites.py, repeated.

Per run (seed ``--first-seed + i``: the robots' data, central's draws and the link relays' delays and stalls): the
cut of site1's cable (``--cut-s``, 30 s by default: three leases), central killed with SIGKILL half-way through the
cut and started again at once from its checkpoints, the restart of site2's router; then every message each robot
sent against what reached the depot (lost) and central (``missing``), how soon after its cable's return site1's
robot was heard at the depot, how soon after its router's restart site2's was, how soon central was back, the
bytes per second each site's link carried with one robot at 10 Hz, and whether central's final estimate (its state
query's full reply) is, bit for bit, that of an untouched copy of the fleet (same robots, same data, same central,
no fault) run beside it. Links are shaped with ``tc netem`` where the kernel has it, else by a relay in the depot
(tests/integration/linkrelay.py; ``link_shaping`` says which). A run that fails on the way (a timeout) is counted,
with why. Needs root (network namespaces).

The summary counts the runs that meet each of the issue's targets and all of them: nothing lost (every seq once
and in order at the depot's receiver, central took every one with none missing), the cut site heard again within
2 s of its cable's return, central equal to the untouched copy's.

    sudo .venv/bin/python benchmarks/multi_site.py --runs 10 --out reports/multi_site.json
"""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.report import emit, over_seeds, summary  # noqa: E402
from tests.integration.netns import NetnsLab, netns_unavailable  # noqa: E402
from tests.integration.sites import run_sites  # noqa: E402

HEARD_AGAIN_WITHIN_S = 2.0
ORDER_REJECTIONS = {"duplicate", "out_of_order", "time_backwards"}


def run_row(run, seed: int, workdir: Path) -> dict:
    """One run's figures, flat, with a verdict per target."""
    figures = dict(run.figures)
    complete = all(run.received[rid][s] == list(range(n)) for rid, counts in run.sent.items()
                   for s, n in counts.items())
    central = run.central or {}
    row = {"seed": seed, "workdir": str(workdir), **figures, "complete_in_order": complete,
           "central_took_all": run.central is not None,
           "cut_lasted_s": figures.get("cut_s"),
           "central_order_rejections": sorted(ORDER_REJECTIONS & set(central.get("rejected", {}))),
           "untouched_took_all": run.untouched_central is not None,
           "site1_bytes_per_s": figures["cable_bytes_per_s"]["site1"],
           "site2_bytes_per_s": figures["cable_bytes_per_s"]["site2"]}
    for site, relay in (figures.get("relay") or {}).items():
        if relay:
            row[f"{site}_relay_delay_ms_mean"] = relay["up"]["delay_ms_mean"]
            row[f"{site}_relay_stalls"] = relay["up"]["stalls"] + relay["down"]["stalls"]
            row[f"{site}_relay_chunks"] = relay["up"]["chunks"] + relay["down"]["chunks"]
    row["nothing_lost"] = (row["lost"] == 0 and complete and row["central_took_all"] and row["central_missing"] == 0
                           and not row["central_order_rejections"])
    row["heard_again_in_time"] = row.get("site1_heard_again_s") is not None and \
        row["site1_heard_again_s"] <= HEARD_AGAIN_WITHIN_S
    row["central_equal"] = bool(row.get("central_equal_untouched")) and row["central_took_all"] and \
        row["untouched_took_all"] and bool(row.get("untouched_sent_the_same"))
    row["every_target"] = row["nothing_lost"] and row["heard_again_in_time"] and row["central_equal"]
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--cut-s", type=float, default=30.0)
    parser.add_argument("--shaping", choices=("auto", "netem", "relay", "none"), default="auto")
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    why = netns_unavailable()
    if why:
        sys.exit(f"multi_site: {why}")
    signal.signal(signal.SIGTERM, lambda *_: sys.exit("multi_site: stopped (SIGTERM)"))  # the lab is closed on the way
    started = time.monotonic()
    runs, failed = [], []
    for index in range(args.runs):
        seed = args.first_seed + index
        workdir = Path(tempfile.mkdtemp(prefix=f"multi-site-{seed}-"))
        lab = NetnsLab(f"sites{index}")
        try:
            run = run_sites(lab, workdir, cut_s=args.cut_s, seed=seed, shaping=args.shaping)
        except (AssertionError, RuntimeError, OSError, subprocess.SubprocessError) as error:
            # a timeout on the way (or a process that would not stop): the run failed, say why
            failed.append({"seed": seed, "workdir": str(workdir), "why": str(error)})
            print(f"run {index} (seed {seed}): FAILED {error}", file=sys.stderr, flush=True)
            continue
        finally:
            lab.close()
        row = run_row(run, seed, workdir)
        runs.append(row)
        print(f"run {index} (seed {seed}): every target {row['every_target']}: lost {row['lost']}, central missing "
              f"{row['central_missing']}, site1 heard again {row.get('site1_heard_again_s')} s, central back "
              f"{row.get('central_back_s')} s, central equal untouched {row['central_equal']} "
              f"{'' if row['central_equal'] else row.get('central_vs_untouched')}", file=sys.stderr, flush=True)
    asked = args.runs
    keys = ["lost", "central_missing", "site1_heard_again_s", "site2_heard_again_s", "central_back_s",
            "central_killed_after_cut_s", "cut_lasted_s", "site1_bytes_per_s", "site2_bytes_per_s",
            "site1_relay_delay_ms_mean", "site2_relay_delay_ms_mean",
            "site1_relay_stalls", "site2_relay_stalls"]
    result = {
        "benchmark": "multi_site", "runs": asked, "runs_completed": len(runs), "runs_failed": len(failed),
        "cut_s": args.cut_s, "link_shaping": sorted({r["link_shaping"] for r in runs}),
        "links": runs[0]["links"] if runs else None,
        "central_partition_wait_s": runs[0].get("central_partition_wait_s") if runs else None,
        "targets": {name: f"{sum(bool(r.get(key)) for r in runs)} of {asked}" for name, key in (
            ("nothing_lost", "nothing_lost"),
            (f"site1_heard_again_within_{HEARD_AGAIN_WITHIN_S:g}_s", "heard_again_in_time"),
            ("central_equal_untouched", "central_equal"),
            ("central_resumed_from_checkpoint", "central_resumed_from_checkpoint"),
            ("every_target", "every_target"))},
        **over_seeds(runs, keys, least=True),
        "failures": failed, "per_run": runs, "wall_s": round(time.monotonic() - started, 1),
    }
    emit(summary(result), args.out)


if __name__ == "__main__":
    main()
