"""Point landmarks (poles, tree trunks, reflectors) from planar laser scans.

A scan is cut into clusters of consecutive valid beams wherever the range jumps by more than
``range_jump_m``; a cluster is a point landmark when it is narrow (``min_beams`` .. ``max_width_m``) and,
without reflectors, when it stands in front of the beams on both sides of it (two occlusion edges: a pole,
not a piece of wall). With intensities, ``min_intensity`` keeps only reflective beams (the ACFR car park's
taped beacons). It is the kind of detector the ACFR data sets were made with: reflective clusters for the car
park's beacons (Guivant & Nebot 2001, IEEE T-RA 17(3)) and range-discontinuity clusters for Victoria Park's tree
trunks (Guivant, Masson & Nebot 2002, Robotics and Autonomous Systems 40). One function serves one scan and a
stack of scans alike, vectorised with numpy over all beams at once.

The range of a detection is the mean range of its beams: the front surface of the object, not its centre.
For a disc of radius ρ the beams' mean lies about ρ·π/4 in front of the centre (ρ ≈ ``width``/2 when the
caller wants the centre); for poles and reflectors (ρ of a few cm) that is below the sensor's noise, and it is
what the car park loader has always used. The bearing is the mean beam angle. The covariance is the floor
(``range_std``, ``bearing_std``) plus the extent of the cluster, which is the object's size and does not average
out over beams: range variance = range_std² + the variance of the cluster's ranges; bearing variance =
bearing_std² + (n·Δθ)²/12, the variance of a point spread uniformly over the n beams' angular footprint.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from robots.models import wrap_angle


@dataclass(frozen=True)
class ExtractorConfig:
    """How beams become point landmarks; the defaults suit a 2D lidar of about 0.5° resolution and 30 m reach."""

    min_range: float = 0.5  # m: nearer beams are invalid (the vehicle itself, dust)
    max_range: float = 30.0  # m: farther beams are invalid (and count as "nothing there" for the occlusion test)
    range_jump_m: float = 0.3  # m: a larger range step between neighbouring beams ends a cluster
    min_beams: int = 1  # a cluster needs at least this many beams
    max_width_m: float = 1.0  # m: a cluster wider than this (chord from its first to its last beam) is not a point
    min_intensity: float | None = None  # with intensities given: only beams at or above it count (reflectors)
    require_discontinuity: bool = True  # both neighbouring beams must lie behind the cluster (occlusion edges)
    range_std: float = 0.05  # m: floor of the range standard deviation of a detection
    bearing_std: float = math.radians(0.5)  # rad: floor of the bearing standard deviation of a detection


@dataclass
class PointLandmarks:
    """Detections of a scan or a stack of scans, ordered by scan then beam."""

    scan: np.ndarray  # (D,) index of the scan each detection came from (0 for a single scan)
    range: np.ndarray  # (D,) m, from the laser origin: the mean range of the cluster's beams
    bearing: np.ndarray  # (D,) rad, in the laser frame (0 = laser x axis), wrapped to [-π, π)
    cov: np.ndarray  # (D, 2, 2) range/bearing covariance: the floor plus the cluster's spread
    beams: np.ndarray  # (D,) beams in the cluster
    width: np.ndarray  # (D,) m, chord from the cluster's first beam point to its last


def _neighbour_behind(ranges: np.ndarray, scan: np.ndarray, beam: np.ndarray, edge_range: np.ndarray,
                      config: ExtractorConfig) -> np.ndarray:
    """Whether beam ``beam`` of scan ``scan`` lies behind a cluster edge at ``edge_range``: its range exceeds the edge's
    by more than ``range_jump_m``, or it has no return (+inf, or beyond ``max_range``). Past the scan's ends, a NaN
    (no measurement) or a nearer return, it does not: nothing shows that the cluster is a free-standing object."""
    inside = (beam >= 0) & (beam < ranges.shape[1])
    neighbour = ranges[scan, np.clip(beam, 0, ranges.shape[1] - 1)]
    with np.errstate(invalid="ignore"):
        behind = (neighbour > edge_range + config.range_jump_m) | (neighbour > config.max_range)
    return inside & behind


def extract_point_landmarks(ranges, angle_min: float, angle_increment: float, intensities=None,
                            config: ExtractorConfig = ExtractorConfig()) -> PointLandmarks:
    """Point landmarks in one scan ``(B,)`` or a stack of scans ``(S, B)``; beam k is at angle_min + k·angle_increment.

    Invalid beams (NaN, ±inf, ≤ 0, outside [min_range, max_range]) and, with ``intensities`` and
    ``config.min_intensity``, beams below that intensity never join a cluster. See the module docstring for the
    range, bearing and covariance of a detection.
    """
    ranges = np.asarray(ranges, dtype=float)
    if ranges.ndim not in (1, 2):
        raise ValueError(f"ranges must be (B,) or (S, B), not {ranges.shape}")
    ranges = np.atleast_2d(ranges)
    scans, beams = ranges.shape
    with np.errstate(invalid="ignore"):
        member = np.isfinite(ranges) & (ranges > 0) & (ranges >= config.min_range) & (ranges <= config.max_range)
        if intensities is not None and config.min_intensity is not None:
            intensities = np.atleast_2d(np.asarray(intensities, dtype=float))
            if intensities.shape != ranges.shape:
                raise ValueError(f"intensities {intensities.shape} do not match ranges {ranges.shape}")
            member &= intensities >= config.min_intensity
        step = np.abs(np.diff(ranges, axis=1))
    linked = member[:, :-1] & member[:, 1:] & (step <= config.range_jump_m)  # beams k and k+1 in one cluster
    no_link = np.zeros((scans, 1), bool)
    starts = member & ~np.hstack([no_link, linked])
    stops = member & ~np.hstack([linked, no_link])
    scan, first = np.nonzero(starts)
    _, last = np.nonzero(stops)
    count = last - first + 1

    # mean range from running sums along each scan (the car park loader's detections depend on this exact arithmetic)
    running = np.zeros((scans, beams + 1))
    running[:, 1:] = np.cumsum(np.where(member, ranges, 0.0), axis=1)
    mean_range = (running[scan, last + 1] - running[scan, first]) / count
    label = np.cumsum(starts.ravel())[member.ravel()] - 1  # the cluster of each member beam, in order
    deviation = ranges[member] - mean_range[label]
    range_var = np.bincount(label, weights=deviation**2, minlength=count.size) / np.maximum(count, 1)

    first_range, last_range = ranges[scan, first], ranges[scan, last]
    span = (last - first) * angle_increment
    width = np.sqrt(np.maximum(first_range**2 + last_range**2 - 2.0 * first_range * last_range * np.cos(span), 0.0))
    keep = (count >= config.min_beams) & (width <= config.max_width_m)
    if config.require_discontinuity:
        keep &= _neighbour_behind(ranges, scan, first - 1, first_range, config)
        keep &= _neighbour_behind(ranges, scan, last + 1, last_range, config)

    mean_beam = 0.5 * (first + last)
    count = count[keep]
    cov = np.zeros((count.size, 2, 2))
    cov[:, 0, 0] = config.range_std**2 + range_var[keep]
    cov[:, 1, 1] = config.bearing_std**2 + (count * angle_increment) ** 2 / 12.0
    return PointLandmarks(
        scan=scan[keep], range=mean_range[keep], bearing=wrap_angle(angle_min + mean_beam[keep] * angle_increment),
        cov=cov, beams=count, width=width[keep],
    )
