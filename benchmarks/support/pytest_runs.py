"""One pytest file run again and again, each time in a fresh process: what the repeat benchmarks share.

:func:`run_pytest` runs the file once with a time limit, without the caller's ``FLEETSLAM_*`` variables (so
every run uses the test's own settings); :func:`outcome` tells from pytest's summary line and exit code whether
it passed, failed or was skipped; :func:`run_record` adds the wall time and, for a failing run, the last lines
of its output; :func:`tagged` reads the ``TAG {json}`` lines a test prints; :func:`failure_lines` and
:func:`failed_line` say why and where a run failed; :func:`progress` is the one stderr line per run.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
TAIL_LINES = 40
INTERRUPT_GRACE_S = 30.0  # after a timeout, how long pytest may take to stop its test's processes itself
OUTCOMES = ("passed", "failed", "skipped")
OUTCOME_WORDS = re.compile(r"(\d+) (passed|failed|skipped|errors?)\b")
ERROR_LINE = re.compile(r"^E\s+(\S.*)$")


@dataclass
class Finished:
    """One pytest process: its output (stdout and stderr), exit code (None: it timed out) and wall seconds."""

    output: str
    returncode: int | None
    wall_s: float


def run_pytest(test: str, timeout_s: float, args: tuple[str, ...] = ()) -> Finished:
    """Run ``test`` once in a fresh pytest process (``args`` added to its command line), in its own process
    group, so that a run that overruns ``timeout_s`` can be stopped with everything it started."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("FLEETSLAM_")}
    command = [sys.executable, "-m", "pytest", "-q", "-s", "-rs", "-p", "no:cacheprovider", *args, test]
    started = time.monotonic()
    with subprocess.Popen(command, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                          start_new_session=True) as process:
        try:
            output, _ = process.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            return Finished(stop_overrun(process), None, time.monotonic() - started)
    return Finished(output, process.returncode, time.monotonic() - started)


def stop_overrun(process: subprocess.Popen) -> str:
    """Stop a run that overran: interrupt pytest (its fixtures then stop the processes the test started), give it
    ``INTERRUPT_GRACE_S`` to exit, then kill whatever is left of its process group; its whole output. Waits on
    pytest's exit, not on the end of its output, which a process it started may hold open."""
    process.send_signal(signal.SIGINT)
    deadline = time.monotonic() + INTERRUPT_GRACE_S
    while process.poll() is None and time.monotonic() < deadline:
        try:
            process.communicate(timeout=0.5)  # keeps reading, so pytest never blocks on a full pipe
        except subprocess.TimeoutExpired:
            pass
    kill_group(process.pid)
    output, _ = process.communicate()
    return output


def kill_group(group_id: int) -> None:
    """SIGKILL every process left in the group ``group_id`` (the group of a pytest run this module started)."""
    try:
        os.killpg(group_id, signal.SIGKILL)
    except ProcessLookupError:
        pass  # the group is empty: pytest and everything it started have exited


def outcome(output: str, returncode: int | None) -> dict:
    """The run's ``outcome`` (passed, failed or skipped) and, for a run that timed out or was skipped, ``why``."""
    summary = next((line for line in reversed(output.splitlines()) if OUTCOME_WORDS.search(line)), "")
    counts = {word.rstrip("s") if word.startswith("error") else word: int(n) for n, word in OUTCOME_WORDS.findall(summary)}
    if returncode is None:
        return {"outcome": "failed", "why": "timed out"}
    if counts.get("failed") or counts.get("error") or returncode not in (0, 5):
        return {"outcome": "failed"}
    if counts.get("passed"):
        return {"outcome": "passed"}
    reason = next((line for line in output.splitlines() if line.startswith("SKIPPED")), None)
    return {"outcome": "skipped", "why": reason or "no test ran"}


def run_record(finished: Finished, fields: dict) -> dict:
    """A run's record: ``fields`` (what the caller read from the output), its outcome, its wall seconds and, when
    it failed, the last ``TAIL_LINES`` lines of its output."""
    record = {**fields, **outcome(finished.output, finished.returncode), "wall_s": round(finished.wall_s, 1)}
    if record["outcome"] == "failed":
        record["tail"] = finished.output.splitlines()[-TAIL_LINES:]
    return record


def tagged(output: str, tag: str) -> list[dict]:
    """The JSON objects of the lines that start with ``tag`` and a space, in order."""
    start = tag + " "
    return [json.loads(line[len(start):]) for line in output.splitlines() if line.startswith(start)]


def failure_lines(output: str) -> list[str]:
    """The ``E`` lines of pytest's report of the first failure, without the ``E``: the assertion or exception that
    failed the run, then what pytest explains of it (``assert 3 == 0``, ``+ where ...``); empty when none."""
    lines = output.splitlines()
    first = next((i for i, line in enumerate(lines) if ERROR_LINE.match(line)), None)
    if first is None:
        return []
    block = []
    for line in lines[first:]:
        match = ERROR_LINE.match(line)
        if not match:
            break
        block.append(match.group(1))
    return block


def failed_line(output: str) -> str | None:
    """The source line the first failure stopped on (pytest's ``>`` line before its first ``E`` line)."""
    lines = output.splitlines()
    first = next((i for i, line in enumerate(lines) if ERROR_LINE.match(line)), None)
    marked = [line for line in lines[:first] if line.startswith(">")] if first is not None else []
    return marked[-1][1:].strip() if marked else None


def count_outcomes(runs: list[dict]) -> dict:
    """How many runs passed, failed and were skipped."""
    return {name: sum(run["outcome"] == name for run in runs) for name in OUTCOMES}


def progress(label: str, run: dict, details: list[str]) -> str:
    """One stderr line per run: ``label``, outcome and wall time, the caller's ``details``, then ``why``."""
    parts = [f"{label}: {run['outcome']} in {run['wall_s']:.0f} s", *details]
    if "why" in run:
        parts.append(run["why"])
    return ", ".join(parts)
