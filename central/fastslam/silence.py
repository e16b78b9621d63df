"""Confirmed landmarks the fleet has stopped seeing (shared association): negative evidence with a learned null.

A robot that goes wrong before its drift says so maps a second copy of what it sees (MR.CLAM 2 seed 0, start
poses known: 11 of 25 landmarks, 1.1–3.5 m from the survey). Such a copy is detected again only by a robot that is
wrong the same way: the robots whose scans are pinned by other landmarks look at it, scan after scan, and see
nothing. A true landmark is also missed for stretches (a barcode turned away, a tree hidden behind another, a robot
in front), and how long a stretch a true landmark can show differs between data sets by an order of magnitude. So
no count of misses is fixed here; both scales are learned from the map while it runs:

- **detection model**: per robot, the chance that a landmark predicted in view at a range is detected, counted
  over the views of confirmed landmarks from scans that matched another confirmed landmark (bins of range,
  Beta(1, 1) prior);
- **silence**: each confirmed landmark's expected detections since it was last associated by any robot, Σ p(r)·v
  over the views that missed it (v: the chance its detection fell inside the sensor's limits, from the predicted
  detection and its innovation covariance). A view counts only when the robot's predicted detection has left the
  gate of its last counted view of that landmark: a robot parked before a landmark it cannot read sees it once;
- **null**: every silence a later association ended is a silence a true landmark survived. A landmark is deleted
  when its silence passes the tail of those: the threshold u + β·ln(n_u / α) of a peaks-over-threshold fit
  (u the ``silence_tail_quantile`` of the ended silences, β their mean excess over u with the silences still running
  counted as censored, n_u how many exceed u), the level that any of them would reach with probability α
  (``silence_alpha``). No landmark is deleted before ``silence_min_ended`` silences have ended.

On MR.CLAM 2 (seed 0, the instrumented run that motivated it) true landmarks' silences stayed below 25 expected
detections and the copies reached 113–304; in Victoria Park a tree occluded by others stayed silent for 53–67.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from central.fastslam import kernels
from central.fastslam.evidence import view_limits, visibility
from robots.models import wrap_angle

if TYPE_CHECKING:
    from central.fastslam.core import FastSlam
    from central.fastslam.lifecycle import RobotState

RANGE_BINS = 8  # bins of the detection model over the sensor's range
MIN_VISIBILITY = 0.05  # a view of a landmark whose detection would fall outside the sensor's limits is no view


@dataclass
class Silences:
    """The filter's state for :func:`observe`, by map slot: each confirmed landmark's silence and each robot's last
    counted view of it; per robot its detection counts by range; the silences associations ended (the null)."""

    silence: np.ndarray = field(default_factory=lambda: np.zeros(0))
    last_view: dict = field(default_factory=dict)  # robot id -> (slots, 2) predicted detection last counted (NaN: none)
    detections: dict = field(default_factory=dict)  # robot id -> (2, RANGE_BINS): detected, viewed (v-weighted)
    ended: list = field(default_factory=list)  # the latest ``silence_memory`` silences an association ended
    ended_total: int = 0
    threshold: float = math.inf
    threshold_at: int = 0  # ended_total when the threshold was computed

    def fit(self, capacity: int, robot_id: str) -> tuple[np.ndarray, np.ndarray]:
        """The robot's (last views, detection counts), every array grown to the map's ``capacity``."""
        if self.silence.size < capacity:
            self.silence = np.concatenate([self.silence, np.zeros(capacity - self.silence.size)])
        views = self.last_view.get(robot_id)
        if views is None or views.shape[0] < capacity:
            grown = np.full((capacity, 2), np.nan)
            if views is not None:
                grown[: views.shape[0]] = views
            views = self.last_view[robot_id] = grown
        counts = self.detections.setdefault(robot_id, np.zeros((2, RANGE_BINS)))
        return views, counts

    def forget(self, slots: np.ndarray) -> None:
        """Slots whose landmark is gone: no silence, no last view."""
        self.silence[slots] = 0.0
        for views in self.last_view.values():
            views[slots[slots < views.shape[0]]] = np.nan


def tail_threshold(ended: np.ndarray, ongoing: np.ndarray, quantile: float, alpha: float) -> float:
    """u + β·ln(n_u / α): the level that any of the silences above u would pass with probability ``alpha`` under an
    exponential tail (u the ``quantile`` of the ``ended`` silences; n_u how many silences, ended or ``ongoing``, exceed
    it). β is the tail's maximum-likelihood scale with the ongoing silences as right-censored values: their excess
    counts, their end does not. Without them the scale would be biased low early in a run, when only the short
    silences have ended yet. inf without a tail."""
    ended, ongoing = np.asarray(ended, float), np.asarray(ongoing, float)
    if ended.size == 0:
        return math.inf
    u = float(np.quantile(ended, quantile))
    above = ended[ended > u] - u
    beyond = ongoing[ongoing > u] - u
    if above.size == 0:
        return math.inf
    scale = (float(above.sum()) + float(beyond.sum())) / above.size
    return u + scale * math.log(max((above.size + beyond.size) / alpha, 1.0))


def current_threshold(slam: FastSlam) -> float:
    """The null's threshold (:func:`tail_threshold`), inf until ``silence_min_ended`` silences have ended; computed
    again after every 1 % more (at least 10) have ended."""
    config, state = slam.config, slam.silences
    if state.ended_total < config.silence_min_ended:
        return math.inf
    if state.ended_total >= max(1.01 * state.threshold_at, state.threshold_at + 10):
        ongoing = state.silence[state.silence > 0.0]
        state.threshold = tail_threshold(np.asarray(state.ended), ongoing, config.silence_tail_quantile,
                                         config.silence_alpha)
        state.threshold_at = state.ended_total
    return state.threshold


def observe(slam: FastSlam, robot: RobotState, slots: np.ndarray, confirmed: np.ndarray, hit: np.ndarray,
            zhat: np.ndarray, h_x: np.ndarray, own: np.ndarray, pose_cov: np.ndarray, r: np.ndarray) -> None:
    """Count one scan's views of the confirmed landmarks near the robot; delete those silent past the null.

    ``slots`` ``(K,)``: the candidates' map slots, ``confirmed`` which are, ``hit`` which this scan associated,
    ``zhat`` ``(K, 2)`` their predicted detections, ``h_x`` ``(K, 2, 3)`` and ``own`` ``(K, 2, 2)`` the pose Jacobians
    and the landmarks' own covariances in detection space, ``pose_cov`` ``(3, 3)`` the pose covariance the scan was
    gated with, ``r`` the sensor's noise.
    """
    config, state = slam.config, slam.silences
    views, counts = state.fit(slam.map.capacity, robot.robot_id)
    scan = kernels.silence_kernel if config.compiled else silence_reference
    ended, deleted = scan(slots, confirmed, hit, zhat, h_x, own, pose_cov, r, *view_limits(slam, robot), state.silence,
                          views, counts, slam.gate, current_threshold(slam))
    if ended.size:
        state.ended.extend(ended.tolist())
        state.ended_total += ended.size
        if len(state.ended) > config.silence_memory:
            del state.ended[: len(state.ended) - config.silence_memory]
    if deleted.any():
        from central.fastslam.shared import drop_landmarks  # here: shared imports this module

        gone = slots[deleted]
        state.forget(gone)
        drop_landmarks(slam, gone)
        slam.counts["landmarks_silenced"] += int(gone.size)


def silence_reference(slots, confirmed, hit, zhat, h_x, own, pose_cov, r, min_range, max_range, half_fov, silence,
                      views, counts, gate, threshold) -> tuple[np.ndarray, np.ndarray]:
    """The numpy reference of :func:`central.fastslam.kernels.silence_kernel`: (silences ended by this scan's
    associations, which candidates to delete). Updates ``silence``, ``views`` (this robot's) and ``counts`` in place.

    The detection model's chances are read before the scan adds to it. A scan with no confirmed landmark associated
    counts no view (its misses may be its pose's error), and a landmark is viewed from it only when another confirmed
    landmark pins the scan."""
    associated = confirmed & hit
    ended = silence[slots[associated]]
    ended = ended[ended > 0.0]
    silence[slots[associated]] = 0.0
    deleted = np.zeros(slots.size, bool)
    pinned = int(associated.sum())
    if pinned == 0:
        return ended, deleted
    s = own + np.einsum("kij,jl,kml->kim", h_x, pose_cov, h_x) + r
    v = visibility(zhat, np.sqrt(s[:, 0, 0]), np.sqrt(s[:, 1, 1]), min_range, max_range, half_fov)
    bins = np.clip((zhat[:, 0] / max_range * RANGE_BINS).astype(np.int64), 0, RANGE_BINS - 1)
    chance = (counts[0, bins] + 1.0) / (counts[1, bins] + 2.0)
    step = zhat - views[slots]
    step[:, 1] = wrap_angle(step[:, 1])
    moved = np.einsum("ki,ij,kj->k", step, np.linalg.inv(r), step) >= gate  # NaN (no view yet) compares False
    fresh = np.isnan(views[slots, 0]) | moved | hit
    counted = confirmed & (v > MIN_VISIBILITY) & fresh & ~(hit & (pinned < 2))
    views[slots[counted]] = zhat[counted]
    np.add.at(counts[1], bins[counted], v[counted])
    np.add.at(counts[0], bins[counted & hit], v[counted & hit])
    missed = counted & ~hit
    silence[slots[missed]] += chance[missed] * v[missed]
    deleted[missed] = silence[slots[missed]] > threshold
    silence[slots[deleted]] = 0.0
    return ended, deleted
