"""The one in-memory form of a robot log, simulated or real.

A :class:`RobotLog` holds one robot's time-ordered odometry, scans (ragged,
as flat arrays with offsets), optional truth, and its :class:`RobotInfo`.
A :class:`Dataset` holds the logs of a fleet and the true landmark map when
there is one. The simulator and every loader produce a Dataset; the robot
process publishes a RobotLog over Zenoh; ``fleetslam run`` feeds
:meth:`Dataset.events` straight into an estimator. One form, three uses.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass, field
from typing import Iterator

import numpy as np

from schemas.contract import Event, OdomEvent, ScanEvent, TruthEvent
from schemas.messages import RobotInfo




def _tagged(stamps: np.ndarray, rank: int, make) -> Iterator[tuple]:
    """(stamp, stream rank, index, maker) for each element of one stream, for a time-ordered merge."""
    for k, t in enumerate(stamps.tolist()):
        yield t, rank, k, make


@dataclass
class RobotLog:
    """One robot's data: controls, scans (flat + offsets), optional truth."""

    info: RobotInfo
    odom_stamp: np.ndarray  # (K,) time at the END of each control interval
    odom_dt: np.ndarray  # (K,)
    odom_control: np.ndarray  # (K, 2)
    odom_cov: np.ndarray  # (2, 2), or (K, 2, 2): one covariance per control
    scan_stamp: np.ndarray  # (S,)
    scan_offsets: np.ndarray  # (S+1,) detections of scan s are [offsets[s], offsets[s+1])
    det_range: np.ndarray  # (D,)
    det_bearing: np.ndarray  # (D,)
    det_id: np.ndarray | None  # (D,) true landmark ids, -1 unknown; None if the data has none
    scan_cov: np.ndarray  # (2, 2)
    truth_stamp: np.ndarray = field(default_factory=lambda: np.zeros(0))
    truth_pose: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # θ may be NaN (GPS only)
    robot_det_offsets: np.ndarray | None = None  # (S+1,) robot-to-robot detections per scan
    robot_det_ids: list[str] = field(default_factory=list)
    robot_det_range: np.ndarray = field(default_factory=lambda: np.zeros(0))
    robot_det_bearing: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def robot_id(self) -> str:
        return self.info.robot_id

    @property
    def start_stamp(self) -> float:
        stamps = [a[0] for a in (self.odom_stamp - self.odom_dt, self.scan_stamp) if a.size]
        return float(min(stamps)) if stamps else 0.0

    @property
    def end_stamp(self) -> float:
        stamps = [a[-1] for a in (self.odom_stamp, self.scan_stamp) if a.size]
        return float(max(stamps)) if stamps else 0.0

    def stream_rates(self) -> dict[str, float]:
        """Messages per second of data time of each stream over the whole log (what a publisher cache is sized by)."""
        span = max(self.end_stamp - self.start_stamp, 1e-3)
        return {"odom": self.odom_stamp.size / span, "scan": self.scan_stamp.size / span,
                "truth": self.truth_stamp.size / span}

    def motion_limits(self) -> dict[str, float]:
        """The motion limits to announce in RobotInfo, from the controls the log holds (their largest magnitude, a
        quarter more and a little): receivers refuse odometry beyond them (a forged or corrupted control)."""
        if self.odom_control.shape[0] == 0:
            return {}
        speed, turn = np.abs(self.odom_control).max(axis=0)
        limits = {"max_speed": 1.25 * float(speed) + 0.05}
        if self.info.motion_model == "unicycle":
            limits["max_turn_rate"] = 1.25 * float(turn) + 0.05
        else:
            limits["max_steering"] = min(1.25 * float(turn) + 0.02, math.pi / 2)
        return limits

    def scan(self, s: int) -> ScanEvent:
        lo, hi = self.scan_offsets[s], self.scan_offsets[s + 1]
        robot_ids, robot_r, robot_b = [], np.zeros(0), np.zeros(0)
        if self.robot_det_offsets is not None:
            rlo, rhi = self.robot_det_offsets[s], self.robot_det_offsets[s + 1]
            robot_ids = self.robot_det_ids[rlo:rhi]
            robot_r, robot_b = self.robot_det_range[rlo:rhi], self.robot_det_bearing[rlo:rhi]
        return ScanEvent(self.robot_id, s, float(self.scan_stamp[s]), self.det_range[lo:hi], self.det_bearing[lo:hi],
                         None if self.det_id is None else self.det_id[lo:hi], self.scan_cov,
                         list(robot_ids), robot_r, robot_b)

    def odom(self, k: int) -> OdomEvent:
        return OdomEvent(self.robot_id, k, float(self.odom_stamp[k]), float(self.odom_dt[k]), self.odom_control[k],
                         self.odom_cov if self.odom_cov.ndim == 2 else self.odom_cov[k])

    def truth(self, k: int) -> TruthEvent:
        return TruthEvent(self.robot_id, k, float(self.truth_stamp[k]), self.truth_pose[k])

    def events(self, until: float | None = None, with_truth: bool = True) -> Iterator[Event]:
        """This robot's events in time order; at equal stamps odometry first, then scan, then truth."""
        streams = [(self.odom_stamp, 0, self.odom), (self.scan_stamp, 1, self.scan)]
        if with_truth:
            streams.append((self.truth_stamp, 2, self.truth))
        merged = heapq.merge(*[_tagged(stamps, rank, make) for stamps, rank, make in streams])
        for stamp, _, k, make in merged:
            if until is not None and stamp > until:
                return
            yield make(k)

    def truth_at(self, stamps: np.ndarray) -> np.ndarray:
        """Truth poses interpolated at ``stamps`` (NaN outside the truth span)."""
        stamps = np.asarray(stamps, float)
        out = np.full(stamps.shape + (3,), np.nan)
        if self.truth_stamp.size < 2:
            return out
        inside = (stamps >= self.truth_stamp[0]) & (stamps <= self.truth_stamp[-1])
        for j in range(2):
            out[inside, j] = np.interp(stamps[inside], self.truth_stamp, self.truth_pose[:, j])
        unwrapped = np.unwrap(self.truth_pose[:, 2])
        theta = np.interp(stamps[inside], self.truth_stamp, unwrapped)
        out[inside, 2] = np.mod(theta + np.pi, 2 * np.pi) - np.pi
        return out


def robot_log_from_streams(info: RobotInfo, odom: list, scans: list, truth_stamps=(), truth_poses=()) -> RobotLog:
    """A RobotLog from one robot's items in time order, as a recorded fleet holds them (MCAP, rosbag2).

    ``odom`` items have ``stamp``, ``dt``, ``control``, ``control_cov`` (an Odometry message or an OdomEvent);
    ``scans`` items ``stamp``, ``ranges``, ``bearings``, ``landmark_ids``, ``noise_cov`` and the other robots'
    ``robot_ids``, ``robot_ranges``, ``robot_bearings`` (a Scan or a ScanEvent). The controls keep one covariance
    when all have the same, else one each; landmark ids are kept when any scan has them (-1 where one has none).
    """
    counts = np.array([len(s.ranges) for s in scans], np.int64)
    robot_counts = np.array([len(s.robot_ids) for s in scans], np.int64)
    covs = np.array([m.control_cov for m in odom], float).reshape(-1, 2, 2)
    odom_cov = np.zeros((2, 2)) if not covs.shape[0] else covs[0] if np.all(covs == covs[0]) else covs
    with_ids = any(s.landmark_ids is not None for s in scans)
    return RobotLog(
        info=info,
        odom_stamp=np.array([m.stamp for m in odom], float),
        odom_dt=np.array([m.dt for m in odom], float),
        odom_control=np.array([m.control for m in odom], float).reshape(-1, 2),
        odom_cov=odom_cov,
        scan_stamp=np.array([s.stamp for s in scans], float),
        scan_offsets=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        det_range=np.concatenate([s.ranges for s in scans]) if scans else np.zeros(0),
        det_bearing=np.concatenate([s.bearings for s in scans]) if scans else np.zeros(0),
        det_id=np.concatenate([s.landmark_ids if s.landmark_ids is not None else np.full(len(s.ranges), -1, np.int64)
                               for s in scans]).astype(np.int64) if with_ids else None,
        scan_cov=scans[0].noise_cov if scans else info.sensor.noise_cov,
        truth_stamp=np.asarray(truth_stamps, float).reshape(-1),
        truth_pose=np.asarray(truth_poses, float).reshape(-1, 3),
        robot_det_offsets=np.concatenate([[0], np.cumsum(robot_counts)]).astype(np.int64),
        robot_det_ids=[rid for s in scans for rid in s.robot_ids],
        robot_det_range=np.concatenate([s.robot_ranges for s in scans]) if scans else np.zeros(0),
        robot_det_bearing=np.concatenate([s.robot_bearings for s in scans]) if scans else np.zeros(0),
    )


@dataclass
class Dataset:
    """A fleet's logs and, where known, the true landmark map."""

    name: str
    robots: dict[str, RobotLog]
    landmarks: np.ndarray | None = None  # (L, 2)
    landmark_ids: np.ndarray | None = None  # (L,)
    meta: dict = field(default_factory=dict)

    @property
    def start_stamp(self) -> float:
        return min(log.start_stamp for log in self.robots.values())

    @property
    def end_stamp(self) -> float:
        return max(log.end_stamp for log in self.robots.values())

    def events(self, duration: float | None = None, robots: list[str] | None = None, with_truth: bool = False) -> Iterator[Event]:
        """Every selected robot's events merged in time order (``duration`` of data from the start)."""
        chosen = [self.robots[r] for r in (robots or list(self.robots))]
        until = None if duration is None else self.start_stamp + duration
        if len(chosen) == 1:  # nothing to merge: skip the merge's key per event
            yield from chosen[0].events(until, with_truth)
            return
        order = {log.robot_id: i for i, log in enumerate(chosen)}
        merged = heapq.merge(*[log.events(until, with_truth) for log in chosen],
                             key=lambda e: (e.stamp, order[e.robot_id]))
        yield from merged
