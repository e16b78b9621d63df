"""The report folder: ``metrics.json``, TUM trajectories (readable by evo), PNG plots.

- ``metrics.json``: what :func:`services.evaluation.metrics.score_estimates` returns, plus context.
- ``{estimator}_{robot}.tum`` and ``truth_{robot}.tum``: one line per pose,
  ``stamp x y z qx qy qz qw`` with z = 0 and the heading as a yaw quaternion
  (identity where the truth has no heading, e.g. GPS).
- ``map_{estimator}.png``: true landmarks, estimated landmarks with their 95 %
  covariance ellipses, true and estimated trajectories.
- ``errors.png``: position error over time for every estimator and robot.

Plots use matplotlib's Agg backend (no display needed).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.collections import LineCollection  # noqa: E402

from robots.gaussian import ellipse_outlines  # noqa: E402
from robots.models import transform_points  # noqa: E402
from services.evaluation.metrics import Trajectory  # noqa: E402


def write_tum(path: Path, trajectory: Trajectory) -> None:
    """Write a trajectory in TUM format (stamp x y z qx qy qz qw)."""
    poses = trajectory.poses
    half = np.where(np.isfinite(poses[:, 2]), 0.5 * poses[:, 2], 0.0)
    zeros = np.zeros(len(trajectory))
    table = np.column_stack([trajectory.stamps, poses[:, 0], poses[:, 1], zeros, zeros, zeros, np.sin(half), np.cos(half)])
    np.savetxt(path, table, fmt="%.6f", header="timestamp tx ty tz qx qy qz qw", comments="# ")


def _colors(count: int):
    cmap = plt.get_cmap("tab10")
    return [cmap(i % 10) for i in range(count)]


def plot_map(path: Path, title: str, estimator: str, truth: dict[str, Trajectory], estimated: dict[str, Trajectory],
             means: np.ndarray, covs: np.ndarray | None, true_landmarks: np.ndarray | None,
             truth_offset=(0.0, 0.0)) -> None:
    """One estimator's map and trajectories over the truth (estimates drawn at the truth's body point)."""
    offset = np.asarray(truth_offset, float)
    fig, ax = plt.subplots(figsize=(11, 8), dpi=110)
    robots = sorted(set(truth) | set(estimated))
    for color, rid in zip(_colors(len(robots)), robots):
        if rid in truth and len(truth[rid]):
            t = truth[rid].poses
            if truth[rid].has_heading:
                ax.plot(t[:, 0], t[:, 1], color=color, lw=0.8, ls="--", alpha=0.6, label=f"{rid} truth")
            else:
                ax.plot(t[:, 0], t[:, 1], ".", color=color, ms=2, alpha=0.5, label=f"{rid} truth (GPS fixes)")
        if rid in estimated and len(estimated[rid]):
            e = transform_points(estimated[rid].poses, offset) if np.any(offset) else estimated[rid].poses
            where = f" at ({offset[0]:g}, {offset[1]:g})" if np.any(offset) else ""
            ax.plot(*break_at_jumps(e[:, :2]).T, color=color, lw=1.4, label=f"{rid} {estimator}{where}")
            ax.plot(e[0, 0], e[0, 1], "o", color=color, ms=5)
    if true_landmarks is not None and len(true_landmarks):
        ax.plot(true_landmarks[:, 0], true_landmarks[:, 1], "k+", ms=10, mew=1.8, label="true landmarks")
    if len(means):
        ax.plot(means[:, 0], means[:, 1], ".", color="crimson", ms=4, label=f"{estimator} landmarks")
        if covs is not None and len(covs) == len(means):
            outlines = ellipse_outlines(means, covs)
            ax.add_collection(LineCollection(outlines, colors="crimson", linewidths=0.6, alpha=0.7,
                                             label="95 % ellipses"))
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"{title}: {estimator}")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, borderaxespad=0.0)
    fig.subplots_adjust(left=0.07, right=0.8, bottom=0.07, top=0.95)  # fixed margins: tight_layout drew it twice
    fig.savefig(path)
    plt.close(fig)


def break_at_jumps(xy: np.ndarray, factor: float = 20.0, floor_m: float = 2.0) -> np.ndarray:
    """``xy`` ``(N, 2)`` with a NaN row inserted at every step longer than ``factor`` times the median step (and
    ``floor_m``): a line plot then shows a global localization's jump from a guess to the found pose as a gap,
    not as a long straight line."""
    if len(xy) < 3:
        return xy
    step = np.hypot(*np.diff(xy, axis=0).T)
    jumps = np.flatnonzero(step > max(floor_m, factor * float(np.median(step))))
    return np.insert(np.asarray(xy, float), jumps + 1, np.nan, axis=0) if jumps.size else xy


def plot_errors(path: Path, title: str, curves: dict[str, dict[str, dict]]) -> None:
    """Position error over time: one panel per estimator, one line per robot."""
    names = [n for n in sorted(curves) if curves[n]]
    if not names:
        return
    fig, axes = plt.subplots(len(names), 1, figsize=(10, 2.8 * len(names) + 0.6), dpi=110, squeeze=False, sharex=True)
    start = min(float(c["stamps"][0]) for n in names for c in curves[n].values() if len(c["stamps"]))
    for ax, name in zip(axes[:, 0], names):
        robots = sorted(curves[name])
        for color, rid in zip(_colors(len(robots)), robots):
            c = curves[name][rid]
            ax.plot(c["stamps"] - start, c["position_error_m"], color=color, lw=1.0, label=rid)
        errors = np.concatenate([np.asarray(curves[name][rid]["position_error_m"], float) for rid in robots])
        errors = errors[np.isfinite(errors)]
        if errors.size and errors.max() > 3.0 * np.percentile(errors, 90):  # a global start's first guesses
            ax.set_ylim(0.0, 1.5 * np.percentile(errors, 90))
            ax.text(0.99, 0.95, f"clipped: max {errors.max():.1f} m", transform=ax.transAxes, ha="right", va="top",
                    fontsize=8)
        ax.set_ylabel("position error (m)")
        ax.set_title(name, fontsize=10)
        ax.grid(True, alpha=0.3)
        ax.legend(loc="upper left", fontsize=8, ncol=min(len(robots), 5))
    axes[-1, 0].set_xlabel("time since start (s)")
    fig.suptitle(title)
    height = fig.get_figheight()  # margins fixed in inches: tight_layout drew the figure twice
    fig.subplots_adjust(left=0.08, right=0.98, bottom=0.55 / height, top=1.0 - 0.75 / height, hspace=0.35)
    fig.savefig(path)
    plt.close(fig)


def _safe(name: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in name)


REPORT_FILES = ("results.json", "metrics.json", "*.tum", "map_*.png", "errors.png")
"""What a report folder holds; :func:`clear_report` removes exactly these."""


def clear_report(folder: str | Path) -> int:
    """Remove the files of an earlier report from ``folder`` (only the names :data:`REPORT_FILES` matches, so a
    folder shared with other files keeps them); returns how many were removed."""
    folder = Path(folder)
    if not folder.is_dir():
        return 0
    stale = {path for pattern in REPORT_FILES for path in folder.glob(pattern) if path.is_file()}
    for path in stale:
        path.unlink()
    return len(stale)


def write_report(folder: str | Path, metrics: dict, curves: dict, truth: dict[str, Trajectory],
                 trajectories: dict[str, dict[str, Trajectory]], maps: dict[str, tuple[np.ndarray, np.ndarray | None]],
                 true_landmarks: np.ndarray | None, title: str, truth_offset=(0.0, 0.0)) -> list[Path]:
    """Write metrics.json, the TUM files and the plots into ``folder``; return the paths written."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written = [folder / "metrics.json"]
    written[0].write_text(json.dumps(clean_json(metrics), indent=2))
    for rid, trajectory in sorted(truth.items()):
        path = folder / f"truth_{_safe(rid)}.tum"
        write_tum(path, trajectory)
        written.append(path)
    for name, robots in sorted(trajectories.items()):
        for rid, trajectory in sorted(robots.items()):
            if len(trajectory):
                path = folder / f"{_safe(name)}_{_safe(rid)}.tum"
                write_tum(path, trajectory)
                written.append(path)
    for name in sorted(set(trajectories) | set(maps)):
        means, covs = maps.get(name, (np.zeros((0, 2)), None))
        path = folder / f"map_{_safe(name)}.png"
        plot_map(path, title, name, truth, trajectories.get(name, {}), means, covs, true_landmarks, truth_offset)
        written.append(path)
    if any(curves.values()):
        path = folder / "errors.png"
        plot_errors(path, title, curves)
        written.append(path)
    return written


def clean_json(value):
    """``value`` made JSON-safe: numpy scalars and arrays to Python, NaN and infinity to None."""
    if isinstance(value, dict):
        return {str(k): clean_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [clean_json(v) for v in value]
    if isinstance(value, np.ndarray):
        return clean_json(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
