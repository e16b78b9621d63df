"""Pieces every log loader shares: reading tables, odometry intervals, grouping detections into scans."""

from __future__ import annotations

import lzma
from pathlib import Path

import numpy as np


def find_file(folder: Path, name: str) -> Path:
    """``folder/name``, or its xz-compressed twin ``name.xz``; FileNotFoundError naming both."""
    plain = folder / name
    if plain.is_file():
        return plain
    packed = folder / f"{name}.xz"
    if packed.is_file():
        return packed
    raise FileNotFoundError(f"neither {plain} nor {packed} exists")


def read_table(path: Path, columns: int | None = None) -> np.ndarray:
    """A whitespace-separated numeric table (``#`` comments), plain or ``.xz``, as a 2-D float array."""
    opener = lzma.open if path.suffix == ".xz" else open
    with opener(path, "rt") as handle:
        table = np.loadtxt(handle, comments="#", ndmin=2)
    if columns is not None and table.size and table.shape[1] != columns:
        raise ValueError(f"{path}: expected {columns} columns, found {table.shape[1]}")
    return table.reshape(-1, columns) if columns is not None and not table.size else table


def first_stamp(path: Path) -> float | None:
    """The first column of the first data line of a table (reads only the file's head)."""
    opener = lzma.open if path.suffix == ".xz" else open
    with opener(path, "rt") as handle:
        for line in handle:
            if line.strip() and not line.lstrip().startswith("#"):
                return float(line.split()[0])
    return None


def odometry_intervals(stamps: np.ndarray, controls: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Per-interval controls from time-stamped readings.

    Reading k holds from its stamp until the next reading, so interval k ends at
    ``stamps[k+1]`` with ``dt = stamps[k+1] - stamps[k]`` and control ``controls[k]``.
    A reading followed by one with the same stamp never acts and is dropped (the
    later one holds). Returns (end stamps, dt, controls, readings dropped).
    """
    order = np.argsort(stamps, kind="stable")
    stamps, controls = stamps[order], controls[order]
    acting = np.append(np.diff(stamps) > 0, True)
    dropped = int((~acting).sum())
    stamps, controls = stamps[acting], controls[acting]
    return stamps[1:], np.diff(stamps), controls[:-1], dropped


def group_by_stamp(stamps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For time-sorted detection stamps: (distinct stamps, offsets) so scan s is ``[offsets[s], offsets[s+1])``."""
    if stamps.size == 0:
        return np.zeros(0), np.zeros(1, np.int64)
    starts = np.flatnonzero(np.r_[True, np.diff(stamps) > 0])
    return stamps[starts], np.append(starts, stamps.size).astype(np.int64)


def offsets_at(stamps: np.ndarray, scan_stamps: np.ndarray) -> np.ndarray:
    """Offsets of time-sorted ``stamps`` into the scans at ``scan_stamps`` (every stamp must be a scan stamp)."""
    return np.searchsorted(stamps, np.append(scan_stamps, np.inf), side="left").astype(np.int64)


def median_rate(stamps: np.ndarray) -> float:
    """Typical rate (Hz) of a time-stamped stream: 1 / median interval."""
    steps = np.diff(stamps)
    steps = steps[steps > 0]
    return float(1.0 / np.median(steps)) if steps.size else 1.0


def gps_spikes(stamps: np.ndarray, xy: np.ndarray, max_speed: float, slack: float) -> np.ndarray:
    """Mask of GPS fixes that jump away from both neighbours and back: farther from the previous and from the
    next fix than the vehicle can drive in between (``max_speed`` · dt + ``slack`` m). A failing receiver's
    isolated jumps (Victoria Park: one fix 141 m off) would otherwise dominate an RMSE against it."""
    stamps, xy = np.asarray(stamps, float), np.asarray(xy, float)
    spikes = np.zeros(stamps.size, bool)
    if stamps.size < 3:
        return spikes
    step = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    too_far = step > max_speed * np.diff(stamps) + slack
    spikes[1:-1] = too_far[:-1] & too_far[1:]
    return spikes


def without_gps_spikes(gps: np.ndarray, max_speed: float, slack: float) -> tuple[np.ndarray, dict]:
    """The rows (t, x, y) of a GPS table that are not spikes (:func:`gps_spikes`), and the counts a loader's meta
    reports: ``gps_fixes`` (every row read) and ``gps_spikes_dropped``."""
    spikes = gps_spikes(gps[:, 0], gps[:, 1:3], max_speed, slack)
    return gps[~spikes], {"gps_fixes": int(gps.shape[0]), "gps_spikes_dropped": int(spikes.sum())}
