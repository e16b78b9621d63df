"""Output of the benchmark scripts: the results as JSON on stdout, and in a file when asked."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from services.evaluation.report import clean_json


def summary(value):
    """``value`` made JSON-safe for a report: numpy scalars to numbers, NaN and infinity to null, and arrays held
    in a dict left out (they are a run's data, kept for its caller, not results)."""
    if isinstance(value, dict):
        return {str(k): summary(v) for k, v in value.items() if not isinstance(v, np.ndarray)}
    if isinstance(value, (list, tuple)):
        return [summary(v) for v in value]
    return clean_json(value)


def over_seeds(runs: list[dict], keys, least: bool = False) -> dict:
    """Per key, the median and the worst (the largest, for errors and counts alike) over the runs that have a
    value, and with ``least`` the smallest too: what the seed benchmarks report, never the best alone."""
    out = {}
    for key in keys:
        values = [run[key] for run in runs if run.get(key) is not None]
        if values:
            out[key] = {"median": round(float(np.median(values)), 3), "worst": round(float(max(values)), 3)}
            if least:
                out[key]["min"] = round(float(min(values)), 3)
    return out


def emit(result: dict, out: str | None) -> None:
    """Print ``result`` as indented JSON; also write it to ``out`` (folders made) when given."""
    text = json.dumps(summary(result), indent=2)
    print(text)
    if out:
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        Path(out).write_text(text + "\n")


def setting(text: str) -> tuple[str, object]:
    """``KEY=VALUE`` with VALUE read as JSON when it parses (numbers, booleans, lists), else as a string: the
    ``--set`` arguments of the benchmarks."""
    key, sep, value = text.partition("=")
    if not sep:
        raise argparse.ArgumentTypeError(f"{text!r}: expected KEY=VALUE")
    try:
        return key, json.loads(value)
    except json.JSONDecodeError:
        return key, value
