"""The kill -9 scenario over many seeds: does a killed service always resume and lose nothing, and how close
does it end to the copy that was never killed?

Runs tests/integration/test_crash_restart.py (two copies of one fleet through one router; copy B's central
FastSLAM, D-SLAM and MCL and the router are killed with SIGKILL at seeded random moments and started again at
once) for the seeds ``--first-seed`` .. ``--first-seed + --seeds - 1`` (pytest option ``--crash-seed``), each in
a fresh pytest process, reads each run's ``CRASH-RESTART {json}`` line and prints JSON: how many runs passed,
failed and were skipped; per service, over the seeds (median and worst), the error of copy B against copy A for
each measure as the ratio B/A and as the difference B−A in metres (A's errors are a few cm, so the ratio of two
small numbers is noisy) and, in ``agreement``, in how many runs B ended exactly where A did and in how many
within 5 % of A's error, the seconds from each restart to the service's first stats and, for the central
service, to its first estimate (whatever ``*_after_s`` figures the test prints per restart), the same split
by kills in the first half of the run (``killed_early``) and the second (``killed_late``); "lost": the test
asserts that no service of B misses a message, so a run that printed its figures lost nothing, and a run that
failed on that check is listed with the service and its ``missing`` count; why every failing run failed (its
assertion line); and every run's record. With ``--control-seeds N`` also N runs that kill nothing (``control``):
how far B's errors differ from A's between two untouched live runs, the noise the killed runs are read against.
Variables FLEETSLAM_* of the caller are not passed on.

    .venv/bin/python benchmarks/crash_restart.py --seeds 10 --control-seeds 5 --out reports/crash_restart.json
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from report import emit, over_seeds  # noqa: E402
from support.pytest_runs import (count_outcomes, failed_line, failure_lines, progress, run_pytest,  # noqa: E402
                                 run_record, tagged)
from tests.integration.test_crash_restart import DURATION, SPEEDUP  # noqa: E402

TEST = "tests/integration/test_crash_restart.py"
TAG = "CRASH-RESTART"
MEASURES = {
    "central": ("central_pose_m", "central_map_m"),
    "dslam": ("dslam_pose_m", "dslam_map_m"),
    "mcl": ("mcl_pose_m",),
}
RUN_WALL_S = DURATION / SPEEDUP  # the robots' run in wall seconds: the kill times count from its start
EARLY_BEFORE_S = RUN_WALL_S / 2
SERVICE_IN_MESSAGE = re.compile(r"^AssertionError: \('(\w+)', \{")  # the message of the test's missing == 0 check
SERVICE_IN_SOURCE = re.compile(r'final_stats\("(\w+)", "(\w+)"\)')  # its check of copy A's central service
MISSING_COUNT = re.compile(r"^assert (-?[\d.]+) == 0$")


def error_comparison(figures: dict) -> dict:
    """Per measure, copy B's error against copy A's: ``b_over_a`` (None when A's error is 0) and ``b_minus_a_m``."""
    errors_a, errors_b = figures.get("errors_A", {}), figures.get("errors_B", {})
    out = {}
    for measure in (m for measures in MEASURES.values() for m in measures):
        if measure in errors_a and measure in errors_b:
            a, b = errors_a[measure], errors_b[measure]
            out[measure] = {"b_over_a": round(b / a, 3) if a else None, "b_minus_a_m": round(b - a, 4)}
    return out


def parse_run(seed: int, output: str) -> dict:
    """What one run printed: its ``CRASH-RESTART`` figures (none when it failed before printing them) and the
    comparison of B's errors with A's."""
    lines = tagged(output, TAG)
    if not lines:
        return {"seed": seed}
    figures = {k: v for k, v in lines[-1].items() if k != "seed"}
    return {"seed": seed, **figures, "comparison": error_comparison(figures)}


def why_failed(output: str) -> dict:
    """Why a run failed: ``why`` (the assertion or exception), ``failed_at`` (the test's line it stopped on) and,
    when that line is a ``missing == 0`` check, ``lost``: the service and how many messages it missed."""
    errors, at = failure_lines(output), failed_line(output)
    found = {"why": errors[0] if errors else "no assertion line in the output", "failed_at": at}
    if at and '"missing"' in at:
        in_message, in_source = SERVICE_IN_MESSAGE.match(errors[0]), SERVICE_IN_SOURCE.search(at)
        service = (in_message.group(1) if in_message else
                   f"{in_source.group(2)} of copy {in_source.group(1)}" if in_source else None)
        counts = [float(m.group(1)) for m in map(MISSING_COUNT.match, errors) if m]
        found["lost"] = {"service": service, "missing": int(counts[0]) if counts else None}
    return found


def service_rows(runs: list[dict], service: str) -> list[dict]:
    """One flat row per run that printed its figures: the service's kill time, restart figures, ``already_held``
    and, per measure, A's and B's errors and their comparison (keys ``{measure}.{a_m|b_m|b_over_a|b_minus_a_m}``)."""
    rows = []
    for run in runs:
        if "comparison" not in run:
            continue
        row = dict(run.get("restarts", {}).get(service, {}))
        row["already_held"] = run.get("already_held", {}).get(service)
        for measure in MEASURES[service]:
            row[f"{measure}.a_m"] = run.get("errors_A", {}).get(measure)
            row[f"{measure}.b_m"] = run.get("errors_B", {}).get(measure)
            for name, value in run["comparison"].get(measure, {}).items():
                row[f"{measure}.{name}"] = value
        rows.append(row)
    return rows


def errors_over_seeds(rows: list[dict], service: str, names=("a_m", "b_m", "b_over_a", "b_minus_a_m")) -> dict:
    """Per measure of ``service`` and per name, the median and worst over ``rows`` (measures no row has left out)."""
    out = {}
    for measure in MEASURES[service]:
        spread = over_seeds(rows, [f"{measure}.{name}" for name in names])
        if spread:
            out[measure] = {key.split(".", 1)[1]: value for key, value in spread.items()}
    return out


def restart_figures(rows: list[dict]) -> list[str]:
    """The restart figures the test printed (seconds from the restart to a first sign of life, ``*_after_s``)."""
    return sorted({key for row in rows for key in row if key.endswith("_after_s")})


def service_summary(runs: list[dict], service: str) -> dict:
    """Over the seeds, for one service: kill times, restart figures and error comparison, all of them and split
    by early and late kills."""
    rows = service_rows(runs, service)
    after = restart_figures(rows)
    summary = {
        **over_seeds(rows, ("killed_at_s", *after, "already_held"), least=True),
        "errors": errors_over_seeds(rows, service),
    }
    for half, in_half in (("killed_early", lambda at: at < EARLY_BEFORE_S), ("killed_late", lambda at: at >= EARLY_BEFORE_S)):
        chosen = [row for row in rows if row.get("killed_at_s") is not None and in_half(row["killed_at_s"])]
        summary[half] = {"runs": len(chosen), **over_seeds(chosen, after),
                         "errors": errors_over_seeds(chosen, service, ("b_over_a", "b_minus_a_m"))}
    return summary


def agreement(runs: list[dict]) -> dict:
    """Per measure, over the runs that printed their figures: in how many B ended exactly where A did (the test's
    ``exact``: same number to the last bit) and in how many within the issue's 5 % of A's error."""
    out = {}
    for measure in (m for measures in MEASURES.values() for m in measures):
        rows = [run for run in runs if measure in run.get("errors_A", {}) and measure in run.get("errors_B", {})]
        out[measure] = {"runs": len(rows), "exact": sum(bool(run.get("exact", {}).get(measure)) for run in rows),
                        "within_5_percent": sum(run["errors_B"][measure] <= 1.05 * run["errors_A"][measure]
                                                for run in rows)}
    return out


def router_summary(runs: list[dict]) -> dict:
    """When the router was killed: the spread of its kill times, and in how many runs early and late."""
    kills = [{"killed_at_s": at} for run in runs for at, name in run.get("plan_s", []) if name == "router"]
    return {**over_seeds(kills, ("killed_at_s",), least=True),
            "killed_early": sum(k["killed_at_s"] < EARLY_BEFORE_S for k in kills),
            "killed_late": sum(k["killed_at_s"] >= EARLY_BEFORE_S for k in kills)}


def lost_summary(runs: list[dict]) -> dict:
    """Messages lost: the test checks ``missing == 0`` for each service of B (and the central service of A) before
    it prints its figures, so a run with figures lost nothing; a run that failed on that check names the service
    and its count; the other failed runs (see their ``why``) failed before it or on another check."""
    with_loss, failed_otherwise = [], []
    for run in runs:
        if "comparison" in run or run["outcome"] == "skipped":
            continue
        if "lost" in run:
            with_loss.append({"seed": run["seed"], **run["lost"]})
        else:
            failed_otherwise.append(run["seed"])
    return {"runs_lost_nothing": sum("comparison" in run for run in runs), "runs_with_loss": with_loss,
            "runs_failed_otherwise": failed_otherwise}


def details(run: dict) -> list[str]:
    """What the progress line shows of a run: each restart's figures, and the largest B−A."""
    parts = [f"{name} " + " ".join(f"{key} {value}" for key, value in figures.items())
             for name, figures in run.get("restarts", {}).items()]
    diffs = {measure: c["b_minus_a_m"] for measure, c in run.get("comparison", {}).items()}
    if diffs:
        measure = max(diffs, key=diffs.get)
        parts.append(f"largest B-A {measure} {diffs[measure]:+.3f} m")
    return parts


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10, help="how many seeds to run (about 35 s each)")
    parser.add_argument("--first-seed", type=int, default=0, help="the first kill-time seed")
    parser.add_argument("--out", help="also write the JSON here")
    parser.add_argument("--control-seeds", type=int, default=0, help="also this many runs that kill nothing "
                        "(--crash-kills none): how far copy B's errors differ from A's without any kill, the noise "
                        "floor the killed runs' differences are read against")
    parser.add_argument("--stop-on-failure", action="store_true", help="stop after the first failing run")
    parser.add_argument("--timeout", type=float, default=300.0, help="wall seconds one run may take before it counts "
                        "as failed")
    args = parser.parse_args()

    started = time.monotonic()
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    runs: list[dict] = []
    for index, seed in enumerate(seeds, start=1):
        finished = run_pytest(TEST, args.timeout, ("--crash-seed", str(seed)))
        run = run_record(finished, parse_run(seed, finished.output))
        if run["outcome"] == "failed" and "why" not in run:
            run.update(why_failed(finished.output))
        runs.append(run)
        print(progress(f"seed {seed} ({index}/{len(seeds)})", run, details(run)), file=sys.stderr, flush=True)
        if run["outcome"] == "failed" and args.stop_on_failure:
            break
    controls: list[dict] = []
    for index in range(args.control_seeds):
        finished = run_pytest(TEST, args.timeout, ("--crash-seed", str(index), "--crash-kills", "none"))
        run = run_record(finished, parse_run(index, finished.output))
        controls.append(run)
        print(progress(f"control {index + 1}/{args.control_seeds}", run, details(run)), file=sys.stderr, flush=True)
    result = {
        "test": TEST, "seeds": [run["seed"] for run in runs], "seeds_asked": seeds, **count_outcomes(runs),
        "run_wall_s": RUN_WALL_S, "early_before_s": EARLY_BEFORE_S,
        "services": {service: service_summary(runs, service) for service in MEASURES},
        "agreement": agreement(runs),
        "router": router_summary(runs),
        "lost": lost_summary(runs),
        "failures": [{"seed": run["seed"], "why": run["why"], "failed_at": run.get("failed_at")}
                     for run in runs if run["outcome"] == "failed"],
        "per_run": runs, "wall_s": round(time.monotonic() - started, 1),
    }
    if controls:
        result["control"] = {"runs": len(controls), **count_outcomes(controls),
                             "errors": {service: errors_over_seeds(service_rows(controls, service), service)
                                        for service in MEASURES},
                             "agreement": agreement(controls),
                             "per_run": controls}
    emit(result, args.out)


if __name__ == "__main__":
    main()
