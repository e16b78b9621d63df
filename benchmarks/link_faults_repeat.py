"""The link-fault scenario run many times in a row: does it pass every time, and how do its figures spread?

Runs tests/integration/test_link_faults.py (a 15 s link cut and a router restart under the compose fleet, in
network namespaces: it needs root, and skips otherwise) ``--runs`` times, each in a fresh pytest process, reads
each run's ``LINK-FAULT RECEIVER {json}`` line, and prints JSON: how many runs passed, failed and were skipped,
the messages lost per run and in total, each run's figures (lease detection, reconnect, link and router
recovery times) with their median, worst and least, and the last lines of output of every failing run.
Variables FLEETSLAM_* of the caller are not passed on, so every run uses the test's own settings.

    sudo .venv/bin/python benchmarks/link_faults_repeat.py --runs 20 --out reports/link_faults_repeat.json
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from report import emit, over_seeds  # noqa: E402
from support.pytest_runs import count_outcomes, progress, run_pytest, run_record, tagged  # noqa: E402

TEST = "tests/integration/test_link_faults.py"
FIGURES = ("lease_detection_s", "reconnect_s", "link_recovered_s", "router_restart_s", "router_recovered_s")


def figures_of(output: str) -> dict:
    """One run's receiver figures (``LINK-FAULT RECEIVER``) and, from the central service's counters
    (``LINK-FAULT FIGURES``), its ``central_messages_in``."""
    figures: dict = {}
    for receiver in tagged(output, "LINK-FAULT RECEIVER"):
        figures.update(receiver)
    for counters in tagged(output, "LINK-FAULT FIGURES"):
        figures.update({k: v for k, v in counters.items() if k.endswith("_messages_in")})
    return figures


def details(run: dict) -> list[str]:
    """What the progress line shows of a run besides its outcome: messages lost and the figures."""
    parts = [f"lost {run['lost']} of {run.get('sent')}"] if "lost" in run else []
    return parts + [f"{name} {run[name]}" for name in FIGURES if name in run]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=20, help="how many times to run the scenario (about 90 s each)")
    parser.add_argument("--out", help="also write the JSON here")
    parser.add_argument("--stop-on-failure", action="store_true", help="stop after the first failing run")
    parser.add_argument("--timeout", type=float, default=600.0, help="wall seconds one run may take before it counts "
                        "as failed")
    args = parser.parse_args()

    started = time.monotonic()
    runs: list[dict] = []
    for index in range(1, args.runs + 1):
        finished = run_pytest(TEST, args.timeout)
        run = run_record(finished, {"run": index, **figures_of(finished.output)})
        runs.append(run)
        print(progress(f"run {index}/{args.runs}", run, details(run)), file=sys.stderr, flush=True)
        if run["outcome"] == "failed" and args.stop_on_failure:
            break
    lost = [run.get("lost") for run in runs]
    measured = [run for run in runs if run["outcome"] != "skipped"]
    result = {
        "test": TEST, "runs": len(runs), "runs_asked": args.runs,
        **count_outcomes(runs),
        "lost_per_run": lost, "total_lost": sum(n for n in lost if n is not None),
        "figures": over_seeds(measured, FIGURES, least=True),
        "per_run": runs, "wall_s": round(time.monotonic() - started, 1),
    }
    emit(result, args.out)


if __name__ == "__main__":
    main()
