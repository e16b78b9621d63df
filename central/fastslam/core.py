"""Centralised multi-robot FastSLAM (Howard, "Multi-robot simultaneous localization and mapping using
particle filters"), vectorised over particles.

Each particle holds the pose of every placed robot and one shared landmark map with an EKF per landmark.
Robots' streams arrive in time order; a robot's controls are buffered and applied once per scan, then the
scan updates every particle. :class:`FastSlam` holds the state and orchestrates; the work is done by
functions that take it explicitly, one module per concern:

- :mod:`~central.fastslam.lifecycle`: robots waiting, placed, sent back to wait, removed;
- :mod:`~central.fastslam.motion`: buffering controls and applying them;
- :mod:`~central.fastslam.proposal`: the FastSLAM 2.0 proposal (``proposal="fastslam2"``, and ``auto`` with shared
  association);
- :mod:`~central.fastslam.association`: known / nn / mht association and the landmark updates;
- :mod:`~central.fastslam.evidence`: negative evidence, landmark existence, merging duplicates;
- :mod:`~central.fastslam.robot_detections`: robot-to-robot detections (``robot_detections``);
- :mod:`~central.fastslam.resampling`: weights, effective sample size, resampling;
- :mod:`~central.fastslam.landmarks`: every particle's landmark map and its EKF (per-particle association);
- :mod:`~central.fastslam.aligned_map`: the landmark map of known and shared association, in copy-on-write blocks
  that particles share;
- :mod:`~central.fastslam.kernels`: the numba kernels of the per-scan work (``compiled``; numpy references kept).
"""

from __future__ import annotations

import logging
import math
from collections import Counter

import numpy as np

from central.fastslam import (association, kernels, lifecycle, motion, noise_gain, proposal, resampling, robot_detections,
                              shared)
from central.fastslam.config import FastSlamConfig
from central.fastslam.aligned_map import AlignedMap, SlotTable
from central.fastslam.landmarks import LandmarkMap
from central.fastslam.lifecycle import RobotState
from central.fastslam.silence import Silences
from robots.gaussian import chi2_quantile, sandwich, valid_cov2
from robots.models import compose_jacobian, se2_compose, wrap_angle
from schemas.contract import MapView, OdomEvent, RunOptions, ScanEvent, build_config
from schemas.messages import RobotInfo

log = logging.getLogger("fleetslam.fastslam")


class FastSlam:
    """The central filter: robots in and out, ``on_odometry``, ``on_scan``, ``poses``, ``landmark_map``.

    State: ``pose`` ``(P, R, 3)`` (every particle's pose of every placed robot), ``turn_gain`` ``(P, R)`` (each
    particle's turn gain of each robot: 1 unless ``turn_gain_std`` or ``turn_gain_walk`` is set), ``logw`` ``(P,)``
    (log-weights), ``map`` (:class:`AlignedMap` with known or shared association, else :class:`LandmarkMap`),
    ``robots`` (placed, by id) and ``waiting`` (known, no
    pose yet), ``known_slots`` (known association: landmark id → map slot), and the counters ``counts`` and
    ``rejected``. Bad input (wrong shapes, NaN, negative ranges, time going backwards, robots never
    announced or not yet placed) is counted in ``rejected`` and leaves the state untouched.
    """

    def __init__(self, config: FastSlamConfig, infos=()):
        self.config = config
        self.rng = np.random.default_rng(config.seed)
        n = config.particles
        self.pose = np.zeros((n, 0, 3))
        self.turn_gain = np.ones((n, 0))
        self.logw = np.zeros(n)
        self.map = AlignedMap(n) if config.association in ("known", "shared") else LandmarkMap(n)
        self.robots: dict[str, RobotState] = {}
        self.waiting: dict[str, RobotInfo] = {}
        self.known_slots = SlotTable()
        self.next_landmark_id = 0  # shared association: the id of the next new landmark
        self.tentative_misses: dict[int, int] = {}  # shared association: misses of tentative landmarks
        self.silences = Silences()  # shared association: how long each confirmed landmark went unseen
        self.rejected: Counter = Counter()
        self.counts: Counter = Counter()
        self.gate = chi2_quantile(config.gate_probability, 2)
        self.new_gate = chi2_quantile(config.new_landmark_probability, 2)
        self.best_hint = 0  # the particle that inherited the heaviest one at the last resampling
        self.workers = effective_workers(config)  # a run's choice, not the filter's state: no result depends on it
        for info in infos:
            self.add_robot(info)

    # ------------------------------------------------------------------ robots
    def has_robot(self, robot_id: str) -> bool:
        """True when the robot is placed (its pose is in the particles)."""
        return robot_id in self.robots

    def is_waiting(self, robot_id: str) -> bool:
        """True when the robot is known but waits for a pose (:meth:`place_robot`)."""
        return robot_id in self.waiting

    def add_robot(self, info: RobotInfo) -> bool:
        """Place a robot with a known start pose, make one without wait; True when it was placed now.
        A robot already known is left as it is (robots republish their RobotInfo)."""
        return lifecycle.add(self, info)

    def place_robot(self, robot_id: str, pose, cov, stamp: float | None = None) -> bool:
        """Place a waiting robot at ``pose`` ``(3,)``, spreading the particles by ``cov`` ``(3, 3)`` (the
        localization hook); ``stamp`` is the time the pose holds at. False (counted) if refused."""
        return lifecycle.place(self, robot_id, pose, cov, stamp)

    def unplace(self, robot_id: str) -> RobotInfo | None:
        """Send a placed robot that has not moved yet back to wait; its RobotInfo, or None."""
        return lifecycle.unplace(self, robot_id)

    def remove_robot(self, robot_id: str) -> RobotInfo | None:
        """Take a robot out, placed or waiting (the landmarks it mapped stay); its RobotInfo, or None."""
        return lifecycle.remove(self, robot_id)

    def load_landmarks(self, ids, means, covs, hits=None) -> None:
        """Seed the map with landmarks every particle agrees on (a saved map, :mod:`schemas.mapfile`): ids ``(n,)``
        (known: the scans' ids; shared: later new landmarks are numbered after the largest), means ``(n, 2)``,
        covariances ``(n, 2, 2)``, hits ``(n,)`` (None: ``confirm_hits``; at least that, so they are confirmed),
        existence at ``exist_max``. Stored once for every particle. ValueError on an id already in the map."""
        ids = np.asarray(ids, np.int64).reshape(-1)
        means, covs = np.asarray(means, float).reshape(-1, 2), np.asarray(covs, float).reshape(-1, 2, 2)
        confirm = self.config.confirm_hits
        hits = np.full(ids.size, confirm) if hits is None else np.maximum(np.asarray(hits, np.int64), confirm)
        if len(set(ids.tolist())) != ids.size or set(ids.tolist()) & set(self.known_slots):
            raise ValueError("landmark ids repeat or are already in the map")
        if ids.size and isinstance(self.map, AlignedMap):
            slots = self.map.add(means, covs, self.config.exist_max, hits, ids)
            self.known_slots.update(zip(ids.tolist(), slots.tolist()))
            self.next_landmark_id = max(self.next_landmark_id, int(ids.max()) + 1)
        elif ids.size:  # nn, mht: every particle's own map gets a copy
            self.map.reserve(ids.size)
            particle = np.repeat(np.arange(self.particle_count), ids.size)
            tile = lambda a: np.tile(a, (self.particle_count,) + (1,) * (a.ndim - 1))  # noqa: E731
            slots = self.map.append(particle, tile(means), tile(covs), self.config.exist_max, tile(ids))
            self.map.hits[particle, slots] = tile(np.minimum(hits, 2**31 - 1))

    # ------------------------------------------------------------------ events
    def on_odometry(self, event: OdomEvent) -> bool:
        """Buffer one control; it is applied with the others at the robot's next scan (or every ``max_batch_s``)."""
        robot = lifecycle.placed(self, event.robot_id)
        return robot is not None and motion.take_control(self, robot, event)

    def on_scan(self, event: ScanEvent) -> bool:
        """Update every particle with one scan of one robot: motion (or the FastSLAM 2.0 proposal), landmark
        association and updates, robot detections, then resampling if the weights have degenerated."""
        robot = lifecycle.placed(self, event.robot_id)
        if robot is None:
            return False
        ranges, bearings = np.asarray(event.ranges, float).ravel(), np.asarray(event.bearings, float).ravel()
        ids = None if event.landmark_ids is None else np.asarray(event.landmark_ids).ravel()
        noise = np.asarray(event.noise_cov, float)
        stamp = float(event.stamp)
        reason = _scan_problem(ranges, bearings, ids, noise, stamp)
        if reason is None and stamp < robot.last_scan_stamp:
            reason = "time_backwards"
        if reason is not None:
            self.rejected[reason] += 1
            return False
        robot.last_scan_stamp = stamp
        motion.advance_to(robot, stamp, self.config)
        keep = ranges > 1e-6
        if self.config.max_obs_range is not None:
            keep &= ranges <= self.config.max_obs_range
        kept = int(np.count_nonzero(keep))
        self.counts["detections_dropped"] += keep.size - kept
        z = np.empty((kept, 2))
        z[:, 0], z[:, 1] = ranges[keep], wrap_angle(bearings[keep])
        ids = None if ids is None else ids[keep].astype(np.int64)
        r = noise * self.config.sensor_noise_scale
        self.counts["scans"] += 1
        self.counts["detections"] += z.shape[0]
        weigh_updates, updated = True, None
        associate = self.config.association == "shared" and z.shape[0]
        if self.config.fastslam2 and z.shape[0]:
            if associate:  # before the proposal moves the particles, from the predicted pose
                ids = shared.associate(self, robot, z, r)
            weighed, updated = proposal.propose(self, robot, z, r, ids)
            weigh_updates = not weighed
        else:
            motion.flush(self, robot)
            if associate:
                ids = shared.associate(self, robot, z, r)
        if self.config.association in ("known", "shared"):
            association.update_known(self, robot, z, r, ids, weigh_updates, updated)
        elif z.shape[0]:
            association.update_unknown(self, robot, z, r, ids, weigh_updates)
        noise_gain.observe(self, robot, z, r, ids)
        if self.config.robot_detections and len(event.robot_ids):
            robot_detections.weigh(self, robot, event, r)
        resampling.normalise_and_resample(self)
        return True

    # ------------------------------------------------------------------ estimates
    @property
    def robot_count(self) -> int:
        """Robots placed in the particles."""
        return len(self.robots)

    @property
    def particle_count(self) -> int:
        return self.pose.shape[0]

    def __setstate__(self, state: dict) -> None:
        """Restore a pickled filter (a checkpoint), also one written before the weights were cached, the
        known-landmark table kept its arrays (such a checkpoint holds ``logw`` and a plain dict), the map
        numbered its landmarks, the robots kept their detections of robots (``robot_checks``) and their odometry noise
        gains (``odometry_noise``), the filter its worker count (``workers``: 1) or its landmarks' silences (they start
        again)."""
        if "logw" in state:
            state["_logw"] = state.pop("logw")
        state["_weights"] = None
        state.setdefault("silences", Silences())  # a checkpoint from before silences: they start again
        state.setdefault("workers", 1)  # a checkpoint from before the parallel kernels (the service sets its own)
        if "turn_gain" not in state:  # a checkpoint from before the turn gains: every particle's gain 1
            state["turn_gain"] = np.ones(state["pose"].shape[:2])
        if not isinstance(state.get("known_slots"), SlotTable):
            state["known_slots"] = SlotTable(state.get("known_slots", {}))
        for robot in state.get("robots", {}).values():  # robots pickled before they kept these
            robot.__dict__.setdefault("robot_checks", [])
            robot.__dict__.setdefault("odometry_noise", None)
            robot.__dict__.setdefault("scaled_gain", None)
        self.__dict__.update(state)
        if isinstance(self.map, AlignedMap):  # a map pickled before it numbered its landmarks: the table's order
            self.map.set_order(self.known_slots.arrays()[1])

    @property
    def logw(self) -> np.ndarray:
        """Log-weights ``(P,)``. Assigning them (``+=`` included) forgets the normalised weights computed from them."""
        return self._logw

    @logw.setter
    def logw(self, value: np.ndarray) -> None:
        self._logw, self._weights = value, None

    def weights(self) -> np.ndarray:
        """Normalised particle weights, computed once per change of the log-weights (a scan's association, its
        resampling test and the pose reports between two scans read the same ones). Callers must not change the
        array returned."""
        if self._weights is None:
            self._weights = resampling.weights(self._logw)
        return self._weights

    def effective_particles(self) -> float:
        return resampling.effective_particles(self)

    def best_particle(self) -> int:
        """The highest-weight particle (after a resampling: a child of the heaviest particle before it)."""
        return resampling.best_particle(self)

    def pose_stamp(self, robot_id: str) -> float | None:
        """The time a placed robot's reported pose holds at (None: not placed, or it has not moved yet)."""
        robot = self.robots.get(robot_id)
        return None if robot is None else robot.pose_time

    def poses(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Every placed robot's weighted mean pose and covariance (buffered controls included, no draw)."""
        w = self.weights()
        out = {}
        for rid, robot in self.robots.items():
            pose = self.pose[:, robot.index]
            pending = motion.pending_motion(robot, self.config)
            if self.config.compiled:
                out[rid] = kernels.weighted_pose(pose, w, pending)
                continue
            extra = np.zeros((3, 3))
            if pending is not None:
                extra = np.einsum("p,pij->ij", w, sandwich(compose_jacobian(pose[:, 2]), pending[1]))
                pose = se2_compose(pose, pending[0])
            mean, cov = resampling.weighted_pose(pose, w)
            cov = cov + extra
            out[rid] = (mean, 0.5 * (cov + cov.T))
        return out

    def landmark_map(self) -> MapView:
        """Known and shared association: the weighted mixture per landmark (shared: the confirmed ones); otherwise
        the best particle's confirmed landmarks
        (associated at least ``confirm_hits`` times, and either permanent or with an existence score at least
        its initial value)."""
        if self.config.association in ("known", "shared"):
            ids, slots, mean, cov = shared.marginal_map(self)
            if self.config.association == "shared":
                keep = shared.confirmed_slots(self, slots)
                return MapView(mean[keep], cov[keep], None)
            return MapView(mean, cov, ids) if ids.size else MapView.empty(with_ids=True)
        p = self.best_particle()
        hits = self.map.hits[p]
        settled = self.map.exist[p] >= self.config.exist_init
        if self.config.permanent_hits is not None:
            settled |= hits >= self.config.permanent_hits
        keep = self.map.valid[p] & (hits >= self.config.confirm_hits) & settled
        return MapView(self.map.mean[p, keep].copy(), self.map.cov[p, keep].copy(), None)

    def extra_metrics(self) -> dict:
        """Figures ``fleetslam run`` adds to its JSON: the filter's counters and particle statistics."""
        out = {"fastslam": self.stats()}
        if self.config.adapts_motion_noise:
            out["noise_gain"] = {rid: round(noise_gain.gain(robot), 4) for rid, robot in self.robots.items()}
            out["turn_scale"] = {rid: round(noise_gain.turn_scale(robot), 4) for rid, robot in self.robots.items()}
        return out

    def stats(self) -> dict[str, float]:
        """Counters and particle statistics (for the service's stats and the benchmarks)."""
        counts = self.map.counts()
        out = {
            "particles": float(self.pose.shape[0]),
            "effective_particles": self.effective_particles(),
            "robots": float(len(self.robots)),
            "robots_waiting": float(len(self.waiting)),
            "landmarks_mean": float(counts.mean()) if counts.size else 0.0,
            "landmarks_best": float(counts[self.best_particle()]) if counts.size else 0.0,
            "map_capacity": float(self.map.capacity),
        }
        out.update({k: float(v) for k, v in self.counts.items()})
        out.update({f"rejected_{k}": float(v) for k, v in self.rejected.items()})
        return out


def _scan_problem(ranges, bearings, ids, noise, stamp) -> str | None:
    """Why a scan is refused (the ``rejected`` counter's name), or None if it is well formed."""
    if ranges.shape != bearings.shape or (ids is not None and ids.shape != ranges.shape):
        return "bad_scan_shape"
    if not (np.isfinite(ranges).all() and np.isfinite(bearings).all() and math.isfinite(stamp)):
        return "bad_scan_values"
    if (ranges < 0).any():
        return "negative_range"
    if ids is not None and ids.dtype.kind not in "iu":
        return "bad_scan_ids"
    if not valid_cov2(noise) or noise[0, 0] * noise[1, 1] - noise[0, 1] ** 2 <= 0:
        return "bad_scan_noise"
    return None


def effective_workers(config: FastSlamConfig) -> int:
    """The threads the per-particle kernels run on: ``config.worker_count``, capped at numba's pool (1 with the numpy
    references, ``compiled=False``)."""
    if not config.compiled:
        return 1
    return max(1, min(config.worker_count, kernels.max_threads()))


def make_estimator(options: RunOptions, infos: list[RobotInfo]) -> FastSlam:
    """FastSLAM with ``options.association`` (known | nn | mht), ``options.particles`` (None: the default) and
    ``options.seed``; ``options.settings`` (``--set``) overrides any :class:`FastSlamConfig` field, e.g.
    ``proposal=fastslam2``. A bad name or value raises :class:`schemas.contract.SettingsError` (one line)."""
    base = {"association": options.association, "seed": options.seed}
    if options.particles is not None:
        base["particles"] = options.particles
    config = build_config(FastSlamConfig, base, owner="fastslam").with_overrides(options.settings, owner="fastslam")
    slam = FastSlam(config, infos)
    log.info("fastslam: %d particles, per-particle kernels on %d worker%s", config.particles, slam.workers,
             "" if slam.workers == 1 else "s")
    return slam
