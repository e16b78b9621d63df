"""The D-SLAM core: one shared static map, a 3-dof localization per robot (Wang, Huang, Dissanayake,
"Implementation Issues and Experimental Evaluation of D-SLAM"). Numeric only: no Zenoh, no settings.

Per scan of a robot:

1. Association: known ids, or one call of the association entry point
   (:func:`services.association.core.associate`, or the queryable in the
   service) on the landmarks and tentative features near the robot.
   Measurements that claim the same feature are set aside.
2. Localization (phase II): the process-model estimate and the estimate from
   the mapped landmarks seen, combined by covariance intersection
   (:mod:`services.dslam.localization`). A robot whose start pose is unknown
   is placed once it sees two mapped landmarks (ids needed then).
3. Mapping. Phase I (robot still at its known start pose, or the pose the
   fleet placement gave it; or, to start a map, moved but not yet localized
   against it, with a small dead-reckoning error and fewer than two mapped
   features in view): the raw observations give
   absolute positions with the joint covariance of the pose and the noise.
   Phase II: the scan joins the robot's local map (:mod:`services.dslam.local_map`,
   several scans in the robot's own frame); once that holds at least two mapped
   landmarks, its points are recast into z_map (eq. 3) around the
   best-conditioned reference pair, new features are initialised by eq. 9 and
   the map updated by eq. 10, unless z_map fails its χ² test
   (``local_map_max_std=0``: one scan at a time, as in the paper). z_map is free
   of any robot frame, so every robot's scans update the one map.
4. Recovery of the mean and of the covariance columns near the robots
   (:class:`services.dslam.information_filter.InformationMap`).

Features are first *tentative* (counted sightings, dropped after misses in
view) and enter the map once confirmed (§3.1); sightings from a known pose
are kept and applied on confirmation.

Re-acquisition (not in the paper; ``reacquire``): without ids, a robot whose
position std passes ``reacquire_position_sd`` is lost. Its scans neither
localize it nor map: their detections are held, placed from its dead-reckoned
pose, until one rigid correction of them against the map is clear (the Hough
vote of :mod:`central.fastslam.reacquire`). A robot sure of a wrong pose is
found by the robots it sees (``reacquire_by_robots``): when most of its
detections of two other robots lie beyond the gate of the two poses, it is
lost too, and those detections vote in its search.
"""

from __future__ import annotations

import math
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import scipy.linalg

from robots.gaussian import block_diagonal, chi2_quantile, inv2, turn_slip, valid_placement
from robots.models import in_field_of_view, robot_models, wrap_angle
from robots.odometry_noise import OdometryNoiseGain
from central.fastslam import reacquire
from schemas.association import AMBIGUOUS, NEW, AssociationReply, AssociationRequest
from schemas.contract import MapView, OdomEvent, RunOptions, ScanEvent, SettingsError, build_config
from schemas.messages import RobotInfo
from services.dslam.config import DslamConfig
from services.dslam.information_filter import ColumnJob, InformationMap
from services.dslam.local_map import LocalMap
from services.dslam.localization import localize, observation_estimate, pose_from_points, predict
from services.dslam.recast import scan_points

MAPPED, TENTATIVE, FRESH, CLUTTER = 0, 1, 2, 3
LOCALIZATION_GATE = chi2_quantile(1 - 1e-6, 3)  # prediction and observation estimate cannot both be right

Associator = Callable[[AssociationRequest, str], AssociationReply]


def in_process_associate(request: AssociationRequest, method: str) -> AssociationReply:
    """The association entry point of :mod:`services.association`, called in this process."""
    from services.association.core import associate

    return associate(request, method)


@dataclass
class Tentative:
    """A feature seen but not yet in the map."""

    key: int
    position: np.ndarray  # (2,) world estimate (NaN when seen by an unlocalized robot)
    cov: np.ndarray  # (2, 2)
    hits: int = 1
    misses: int = 0
    phase_one: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)  # (position, cov) from a known pose


@dataclass
class RobotState:
    """One robot's localization state."""

    info: RobotInfo
    pose: np.ndarray | None
    cov: np.ndarray | None
    moved: bool = False
    stamp: float = float("-inf")
    omega: float = float("nan")
    observed: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    streams: set = field(default_factory=set)
    localized: bool = False
    disagreements: int = 0
    local: LocalMap | None = None  # scans collected since the last z_map (local_map_max_std > 0)
    turn_slip: float = 0.0  # heading variance turned since the last full-rank localization: widens the gate only
    placed_at: float = float("-inf")  # the stamp of the pose it was placed at: its events before then are past
    blind: reacquire.BlindWindow | None = None  # a lost robot's held detections (re-acquisition)
    contradicted: bool = False  # its detections of other robots contradict its pose: lost until a correction
    robot_checks: list = field(default_factory=list)  # (stamp, robot seen, explained): reacquire.contradicted
    deferred: tuple = ()  # scans kept, without a pose, until the columns of their mapped landmarks are solved
    wanted: tuple = ()  # ... those landmarks (DSlam.column_prefetch solves them first)
    odometry_noise: OdometryNoiseGain | None = None  # its turn scale (turn_scale_adapt): its odometry's turns × it

    def __post_init__(self) -> None:
        self.model, self.sensor = robot_models(self.info)

    def __setstate__(self, state: dict) -> None:
        """Restore a pickled robot (a checkpoint), also one written before it kept its robot detections."""
        state.setdefault("robot_checks", [])
        state.setdefault("odometry_noise", None)
        self.__dict__.update(state)

    @property
    def known_start(self) -> bool:
        return self.info.start_pose is not None

    def check_start(self, stream: str, seq: int) -> bool:
        """False when a stream's first message is not its first (seq > 0): the start was missed, the pose is unknown."""
        if stream in self.streams:
            return True
        self.streams.add(stream)
        if seq > 0 and self.pose is not None and not self.moved:
            self.pose = self.cov = None
            return False
        return True

    def in_phase_one(self, mapped: int, bootstrap_std: float) -> bool:
        """Raw observations map directly from this robot's pose (phase I) for this scan?

        Yes while it stands at its known start pose (the paper's phase I). Also,
        to start a map when the robot moves before it sees anything (MR.CLAM), while
        it has not yet been localized against the map, sees fewer than two mapped
        features and its dead-reckoned position std is at most ``bootstrap_std``.
        """
        if self.pose is None or not self.known_start or self.localized:
            return False
        if not self.moved:
            return True
        return mapped < 2 and self.position_std() <= bootstrap_std

    def position_std(self) -> float:
        """The largest standard deviation (m) of the robot's position."""
        return float(np.sqrt(np.max(np.linalg.eigvalsh(self.cov[:2, :2]))))


@dataclass
class MapSnapshot:
    """What the service publishes of the map: every landmark mean and id (feature key: the true id with known
    association), the marginal covariances of the landmarks with a cached column (those near the robots),
    information-matrix nnz, the last recovery's iterations and the newest robot stamp."""

    means: np.ndarray  # (n, 2)
    ids: np.ndarray  # (n,)
    covariance_ids: np.ndarray  # (k,) ids of the landmarks in ``covariances``
    covariances: np.ndarray  # (k, 2, 2)
    info_nnz: int
    recovery_iterations: int
    stamp: float


class DSlam:
    """The D-SLAM map of every robot, with each robot's localization (implements the Estimator protocol)."""

    prefetching = False  # class default: a core checkpointed before scans could wait for their columns carries on

    def __init__(self, config: DslamConfig | None = None, associator: Associator | None = None,
                 record: bool = False):
        self.config = config or DslamConfig()
        s = self.config
        self.map = InformationMap(s.recovery_tol, s.recovery_max_iter, s.column_tol, s.column_max_iter, s.column_cache,
                                  refactor_iterations=s.refactor_iterations, columns=s.covariance_columns,
                                  check_every=s.recovery_check_every, column_solver=s.column_solver,
                                  correction_limit=s.column_correction_limit)
        self.associator = associator or in_process_associate
        self.ids: list[int] = []
        self.index_of: dict[int, int] = {}
        self.tentative: dict[int, Tentative] = {}
        self.robots: dict[str, RobotState] = {}
        self.counts: Counter = Counter()
        self.last_step_ms = 0.0
        self._next_key = 0
        self.measurements: list[tuple] | None = [] if record else None
        self.prefetching = False  # a service solves columns between scans (column_prefetch): see defer_scan

    # ----------------------------------------------------------------- robots
    def has_robot(self, rid: str) -> bool:
        return rid in self.robots

    def add_robot(self, info: RobotInfo) -> None:
        """Take a robot in (replacing any robot of that id), at its start pose if known."""
        pose = None if info.start_pose is None else np.asarray(info.start_pose, float).copy()
        cov = None
        if pose is not None:
            cov = np.diag([1e-9, 1e-9, 1e-12]) if info.start_pose_cov is None else np.asarray(info.start_pose_cov, float)
        self.robots[info.robot_id] = RobotState(info, pose, cov, odometry_noise=self._turn_scale(info))

    def _turn_scale(self, info: RobotInfo) -> OdometryNoiseGain | None:
        """The estimator of a robot's turn scale (robots/odometry_noise.py; its covariance gain stays 1): without ids,
        for (v, ω) odometry (an Ackermann robot turns by its steering through its wheelbase); None otherwise."""
        if self.config.association == "known" or not self.config.turn_scale_adapt or info.motion_model != "unicycle":
            return None
        return OdometryNoiseGain(1.0, 1.0, 1.0, turn_scale_bounds=self.config.turn_scale_bounds)

    def is_waiting(self, rid: str) -> bool:
        """True when the robot is known but has no pose (no start pose, or a missed start): :meth:`place_robot`."""
        robot = self.robots.get(rid)
        return robot is not None and robot.pose is None

    @property
    def robot_count(self) -> int:
        """Robots with a pose."""
        return sum(robot.pose is not None for robot in self.robots.values())

    def map_is_empty(self) -> bool:
        """No landmark mapped and no feature placed in the world yet (features seen only by robots without a pose,
        with ids, do not count): a robot placed now starts the map, as from a known start pose."""
        return self.map.n == 0 and not any(np.all(np.isfinite(t.position)) for t in self.tentative.values())

    def place_robot(self, rid: str, pose, cov, stamp: float | None = None) -> bool:
        """Give a waiting robot ``pose`` ``(3,)`` with covariance ``cov`` ``(3, 3)`` at ``stamp`` (the hook of
        :class:`services.placement.FleetPlacer`). A robot placed while the map is empty starts it, as from a known
        start pose (phase I); so does one placed against a map with ``placement_bootstrap`` (the default: it maps
        its raw observations while it is not localized and its dead reckoning is tight, as a robot from a start pose
        does; otherwise it is taken as localized, its covariance widened by ``placement_floor``). False (counted)
        if refused."""
        robot = self.robots.get(rid)
        pose, cov = np.asarray(pose, float), np.asarray(cov, float)
        if robot is None or robot.pose is not None:
            self.counts["place_refused"] += 1
            return False
        if not valid_placement(pose, cov, stamp):
            self.counts["bad_placement"] += 1
            return False
        cov = 0.5 * (cov + cov.T) + np.diag([1e-9, 1e-9, 1e-12])
        if self.map_is_empty() or self.config.placement_bootstrap:
            robot.info = robot.info.model_copy(update={"start_pose": pose.copy(), "start_pose_cov": cov})
        else:
            cov = cov + np.diag(np.square(self.config.placement_floor))
            robot.localized = True
        robot.pose, robot.cov, robot.moved, robot.local, robot.turn_slip = pose.copy(), cov, False, None, 0.0
        robot.streams.update(("odom", "scan"))  # its earlier messages went to the localizer: no missed start
        if stamp is not None:
            robot.stamp = robot.placed_at = float(stamp)
        self.counts["robots_placed"] += 1
        return True

    def remove_robot(self, rid: str) -> None:
        """Forget a robot's localization (its map contributions stay; the scans it kept waiting are dropped,
        counted); nothing if it is unknown."""
        robot = self.robots.pop(rid, None)
        if robot is not None and robot.deferred:
            self.counts["deferred_scans_dropped"] += len(robot.deferred)

    def lose_pose(self, rid: str) -> None:
        """The robot's odometry was lost for good: its pose is unknown until it is localized against the map again,
        as a robot whose start was missed (counted as ``lost_pose``)."""
        robot = self.robots.get(rid)
        if robot is not None and robot.pose is not None:
            robot.pose = robot.cov = None
            robot.localized = False
            robot.local = None
            robot.turn_slip = 0.0
            self.counts["lost_pose"] += 1

    def __getstate__(self) -> dict:
        """Pickled (a checkpoint) without its associator, which may be a service's method: the restorer sets it."""
        state = dict(self.__dict__)
        state["associator"] = in_process_associate
        return state

    def robot_pose(self, rid: str) -> tuple[np.ndarray, np.ndarray] | None:
        """(pose, covariance) of a robot, or None while it is unknown or not localized."""
        robot = self.robots.get(rid)
        if robot is None or robot.pose is None:
            return None
        return robot.pose.copy(), robot.cov.copy()

    def before_placement(self, rid: str, stamp: float) -> bool:
        """Whether ``stamp`` is older than the pose the robot was placed at (its events then are skipped)."""
        robot = self.robots.get(rid)
        return robot is not None and stamp < robot.placed_at

    def _robot_of(self, event: OdomEvent | ScanEvent, stream: str) -> RobotState | None:
        """The robot an event belongs to (None, counted, if unknown, or if the event is older than the pose the robot
        was placed at: that pose has it already); notes a missed start."""
        robot = self.robots.get(event.robot_id)
        if robot is None:
            self.counts["unknown_robot"] += 1
        elif event.stamp < robot.placed_at:
            self.counts["before_placement_pose"] += 1
            return None
        elif not robot.check_start(stream, event.seq):
            self.counts["missed_start"] += 1
        return robot

    def on_odometry(self, event: OdomEvent) -> None:
        robot = self._robot_of(event, "odom")
        if robot is None:
            return
        control = np.asarray(event.control, float)
        if np.any(control != 0.0):
            robot.moved = True
        if robot.odometry_noise is not None:
            control = control * (1.0, robot.odometry_noise.turn_scale)
        if robot.local is not None:
            robot.local.predict(robot.model, control, event.control_cov, event.dt)
        if robot.pose is None:
            return
        heading = robot.pose[2]
        robot.pose, robot.cov = predict(robot.pose, robot.cov, robot.model, control, event.control_cov, event.dt)
        if robot.odometry_noise is not None:  # the increment (robot's frame) and its covariance: its dead reckoning
            _, f_control = robot.model.jacobians(np.zeros(3), control, event.dt)
            robot.odometry_noise.move(robot.model.step(np.zeros(3), control, event.dt),
                                f_control @ np.asarray(event.control_cov, float) @ f_control.T)
        if self.config.turn_slip:
            robot.turn_slip += turn_slip(robot.info.turn_slip_var, robot.pose[2] - heading)
        robot.stamp = event.stamp

    def poses(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        return {rid: (r.pose.copy(), r.cov.copy()) for rid, r in self.robots.items() if r.pose is not None}

    # ------------------------------------------------------------------ scans
    def on_scan(self, event: ScanEvent) -> None:
        """One scan: localization, association, the map (a robot's deferred scans first, see :meth:`defer_scan`)."""
        robot = self.robots.get(event.robot_id)
        if robot is not None and self.defer_scan(robot, event):
            return
        if robot is not None and robot.deferred:
            held, robot.deferred, robot.wanted = robot.deferred, (), ()
            for old in held:
                self._scan(old)
        self._scan(event)

    def defer_scan(self, robot: RobotState, event: ScanEvent) -> bool:
        """With ``prefetching`` (a service that solves columns between scans), keep (counted) the scan of a robot
        without a pose whose mapped landmarks, by id, have columns the cache lacks and a worker can solve: its
        placement and its z_map would solve them within the scan (at 10^5 landmarks about 300 ms for four). It is
        handled, after the scans kept before it, at the robot's first scan whose columns are all cached; at most
        ``max_deferred_scans`` wait (then they are handled, solving what they need)."""
        if (not self.prefetching or robot.pose is not None or event.landmark_ids is None
                or self.config.association != "known" or len(robot.deferred) >= self.config.max_deferred_scans):
            return False
        mapped = [self.index_of[i] for i in np.asarray(event.landmark_ids).tolist() if i in self.index_of]
        wanted = tuple(dict.fromkeys([*robot.wanted, *mapped]))
        if not self.map.solvable_off_scan(wanted):
            return False
        robot.deferred, robot.wanted = (*robot.deferred, event), wanted
        self.counts["scans_deferred"] += 1
        return True

    def _scan(self, event: ScanEvent) -> None:
        started = time.perf_counter()
        robot = self._robot_of(event, "scan")
        if robot is None:
            return
        spec = robot.info.sensor
        obs = event.observations
        keep = np.all(np.isfinite(obs), axis=1) & (obs[:, 0] > 1e-6) & (obs[:, 0] <= 2.0 * spec.max_range)
        if not keep.all():
            self.counts["bad_observations"] += int((~keep).sum())
        obs = obs[keep]
        ids = None if event.landmark_ids is None else np.asarray(event.landmark_ids)[keep]
        noise = np.asarray(event.noise_cov, float)
        robot.stamp = event.stamp
        self.counts["scans"] += 1
        self._check_robots(robot, event, noise)
        if self._held(robot, obs, noise):
            return
        labels = self._associate(robot, obs, noise, ids)
        if labels is None:
            self.counts["scans_unassociated"] += 1
            return
        kinds, refs = labels
        mapped = np.flatnonzero(kinds == MAPPED)
        phase_one = robot.in_phase_one(mapped.size, self.config.bootstrap_std)
        robot.observed = refs[mapped]
        if robot.odometry_noise is not None and mapped.size:
            robot.odometry_noise.scan(robot.sensor.offset, refs[mapped].tolist(), obs[mapped], noise)
        if not phase_one:
            self._localize(robot, obs[mapped], noise, refs[mapped])
        confirmed = self._bookkeep(robot, obs, noise, kinds, refs, phase_one)
        mapped = np.flatnonzero(kinds == MAPPED)
        if phase_one:
            robot.local = None
            self._map_phase_one(robot, obs, noise, kinds, refs, confirmed)
        elif self.config.local_map_max_std > 0:
            self._map_local(robot, obs, noise, kinds, refs)
        else:
            self._map_phase_two(obs, noise, kinds, refs, mapped, confirmed)
        self.map.maintain()
        self.last_step_ms = (time.perf_counter() - started) * 1e3

    # --------------------------------------------------------- re-acquisition
    def _held(self, robot: RobotState, obs: np.ndarray, noise: np.ndarray) -> bool:
        """Whether this scan is held for re-acquisition: the robot is lost (no ids, position std beyond
        ``reacquire_position_sd``) and no rigid correction of its recent detections is clear yet. A correction
        found moves the robot (its covariance then that of the correction's grid) and the scan goes on as usual."""
        s = self.config
        if (not s.reacquire or s.association == "known" or robot.pose is None
                or (robot.position_std() <= s.reacquire_position_sd and not robot.contradicted)):
            robot.blind, robot.contradicted = None, False
            return False
        if robot.blind is None:
            robot.blind = reacquire.BlindWindow(contradicted=robot.contradicted)
            self.counts["reacquire_started"] += 1
        robot.local = None
        window = robot.blind
        window.add(robot.stamp, robot.sensor.inverse(robot.pose, obs), s.reacquire_window_s)
        inlier = s.reacquire_inlier_sigmas * float(np.sqrt(max(noise[0, 0], 0.0)))
        if inlier > 0.0 and window.due(robot.stamp, s.reacquire_every_s):  # no radius from a noise of 0
            correction = reacquire.beyond_caps(
                window, robot.pose[:2], s.reacquire_max_turn, s.reacquire_robots_shift_m, s.reacquire_robots_fit_min,
                s.reacquire_robots_fit_spread_m, s.reacquire_robots_fit_residual_m) if s.reacquire_by_robots else None
            if correction is not None:
                self.counts["reacquired_by_robots"] += 1
            else:
                least = s.reacquire_robots_min_landmarks if robot.contradicted else s.reacquire_min_landmarks
                rule = reacquire.SearchRule(s.reacquire_min_detections, inlier, 4.0 * inlier, s.reacquire_margin, least,
                                            robots_veto=s.reacquire_robots_veto if s.reacquire_by_robots else 0)
                correction = reacquire.search_window(
                    window, robot.pose[:2], float(np.sqrt(robot.cov[2, 2] + robot.turn_slip)), robot.position_std(),
                    s.reacquire_max_turn, math.inf, self._landmarks_near, rule)
            if correction is not None:
                robot.pose = correction.apply(robot.pose)
                robot.cov = np.diag([inlier ** 2, inlier ** 2, reacquire.TURN_STEP ** 2])
                robot.blind, robot.turn_slip, robot.disagreements, robot.contradicted = None, 0.0, 0, False
                self.counts["reacquired"] += 1
                return False
        self.counts["detections_blind"] += obs.shape[0]
        return True

    def _check_robots(self, robot: RobotState, event: ScanEvent, noise: np.ndarray) -> None:
        """The robot's detections of other robots (``reacquire_by_robots``, without ids): each is explained when it
        lies within the 99.9 % gate of the two robots' covariances, the scan's noise times
        ``robot_detection_noise_scale`` and ``robot_detection_position_sd`` of relative position; when most of the
        last ones are not (:func:`central.fastslam.reacquire.contradicted`) the robot is lost, its covariance
        widened to ``reacquire_robots_shift_m`` and ``reacquire_max_turn``. While it is held, each detection joins its
        window with the robot it saw, to vote in the search. They never update a pose or the map."""
        s = self.config
        if (not (s.reacquire and s.reacquire_by_robots) or s.association == "known" or robot.pose is None
                or not event.robot_ids):
            return
        r = noise * s.robot_detection_noise_scale
        for other_id, rng_, brg in zip(event.robot_ids, np.asarray(event.robot_ranges, float),
                                       np.asarray(event.robot_bearings, float)):
            other = self.robots.get(other_id)
            if (other is None or other is robot or other.pose is None
                    or abs(other.stamp - event.stamp) > s.robot_detection_max_dt):
                self.counts["robot_detections_unused"] += 1
                continue
            z = np.array([rng_, brg])
            h_pose, h_other = robot.sensor.jacobians(robot.pose, other.pose[:2])
            other_cov = other.cov[:2, :2] + s.robot_detection_position_sd ** 2 * np.eye(2)
            innovation_cov = h_pose @ robot.cov @ h_pose.T + h_other @ other_cov @ h_other.T + r
            nu = robot.sensor.innovation(z, robot.sensor.observe(robot.pose, other.pose[:2]))
            explained = bool(nu @ np.linalg.solve(innovation_cov, nu) <= reacquire.ROBOT_GATE)
            reacquire.note_robot_detection(robot, event.stamp, other_id, explained, s.reacquire_robots_window_s)
            if robot.blind is not None:
                robot.blind.robots.append((event.stamp, np.r_[robot.sensor.inverse(robot.pose, z), other.pose[:2]]))
            self.counts["robot_detections_used"] += 1
        if not robot.contradicted and reacquire.contradicted(robot, event.stamp, s.reacquire_robots_window_s,
                                                             s.reacquire_robots_min):
            robot.cov = reacquire.widened(robot.cov, s.reacquire_robots_shift_m, s.reacquire_max_turn)
            robot.contradicted = True  # held from this scan on (_held), its local map dropped there
            robot.robot_checks.clear()
            self.counts["reacquire_contradicted"] += 1

    def _landmarks_near(self, point: np.ndarray, radius: float) -> np.ndarray:
        """Means ``(K, 2)`` of the mapped landmarks within ``radius`` of ``point``."""
        means = self.map.means
        return means[np.sum((means - point) ** 2, axis=1) <= radius * radius]

    # ------------------------------------------------------------ association
    def _associate(self, robot: RobotState, obs: np.ndarray, noise: np.ndarray, ids: np.ndarray | None):
        """(kinds (n,), refs (n,)): map index, tentative key, new key or -1 per observation; None if impossible.

        Measurements that claim the same feature (per-measurement NN can do that,
        a misread id too) are all set aside: z_map needs distinct features.
        """
        n = obs.shape[0]
        kinds = np.full(n, CLUTTER, np.int64)
        refs = np.full(n, -1, np.int64)
        if self.config.association == "known" and ids is not None:
            for k, lm in enumerate(ids.tolist()):
                if lm < 0:
                    continue
                if lm in self.index_of:
                    kinds[k], refs[k] = MAPPED, self.index_of[lm]
                elif lm in self.tentative:
                    kinds[k], refs[k] = TENTATIVE, lm
                else:
                    kinds[k], refs[k] = FRESH, lm
        elif robot.pose is None:
            return None
        elif n:
            if self.config.association == "known":
                self.counts["scans_without_ids"] += 1
            method = "auto" if self.config.association == "known" else self.config.association
            candidates, tentative_keys, request = self.association_request(robot, obs, noise)
            reply = self.associator(request, method)
            assignment = np.asarray(reply.assignment, np.int64)
            if assignment.shape != (n,):
                self.counts["assoc_bad_reply"] += 1
                return None
            self.counts[f"assoc_{reply.method}"] += 1
            n_map = candidates.shape[0]
            for k, a in enumerate(assignment.tolist()):
                if 0 <= a < n_map:
                    kinds[k], refs[k] = MAPPED, candidates[a]
                elif n_map <= a < n_map + len(tentative_keys):
                    kinds[k], refs[k] = TENTATIVE, tentative_keys[a - n_map]
                elif a == NEW:
                    kinds[k], refs[k] = FRESH, self._new_key()
                elif a == AMBIGUOUS:
                    self.counts["assoc_not_unique"] += 1
        claimed = kinds != CLUTTER
        keys, counts = np.unique(np.stack([np.minimum(kinds[claimed], TENTATIVE), refs[claimed]], -1), axis=0,
                                 return_counts=True)
        for kind, ref in keys[counts > 1]:
            shared = (np.minimum(kinds, TENTATIVE) == kind) & (refs == ref) & claimed
            kinds[shared], refs[shared] = CLUTTER, -1
            self.counts["assoc_shared_landmark"] += int(shared.sum())
        return kinds, refs

    def _new_key(self) -> int:
        while self._next_key in self.index_of or self._next_key in self.tentative:
            self._next_key += 1
        self._next_key += 1
        return self._next_key - 1

    def association_request(self, robot: RobotState, obs: np.ndarray, noise: np.ndarray):
        """(candidate map indices, candidate tentative keys, AssociationRequest in landmark form) near the robot."""
        spec = robot.info.sensor
        reach = spec.max_range + self.config.candidate_margin
        position = robot.sensor.sensor_position(robot.pose)[0]
        means = self.map.means
        near = np.flatnonzero(np.sum((means - position) ** 2, axis=1) <= reach * reach) if self.map.n else np.zeros(0, np.int64)
        covs = self.map.marginals(near)
        keys = [key for key, t in self.tentative.items()
                if np.all(np.isfinite(t.position)) and np.sum((t.position - position) ** 2) <= reach * reach]
        landmarks = np.vstack([means[near], *[self.tentative[k].position[None] for k in keys]]) if near.size or keys else np.zeros((0, 2))
        landmark_covs = np.concatenate([covs, *[self.tentative[k].cov[None] for k in keys]]) if near.size or keys else covs
        area = max(spec.max_range - spec.min_range, 1e-3) * spec.fov
        s = self.config
        request = AssociationRequest(
            measurements=obs.reshape(-1, 2), noise=noise, landmarks=landmarks.reshape(-1, 2),
            landmark_covs=0.5 * (landmark_covs + np.swapaxes(landmark_covs, 1, 2)), pose=robot.pose,
            pose_cov=0.5 * (robot.cov + robot.cov.T) + np.diag(np.square(s.gate_pose_floor) + [0.0, 0.0, robot.turn_slip]),
            sensor_offset=np.asarray(spec.offset, float),
            gate_probability=s.gate_probability, new_feature_gate_probability=s.new_feature_gate_probability,
            clutter_density=max(spec.clutter_rate / area, 1e-9), new_feature_density=s.new_feature_density,
            detection_probability=min(max(spec.detection_probability, 1e-3), 1 - 1e-3), unique_pairs=s.unique_pairs,
        )
        return near, keys, request

    # ----------------------------------------------------------- localization
    def _localize(self, robot: RobotState, obs: np.ndarray, noise: np.ndarray, index: np.ndarray) -> None:
        """CI of the process-model estimate with the estimate from the mapped landmarks seen (§2.3).

        When the two disagree beyond any doubt, the observations are set aside (a
        misread feature, an ambiguous pair); after ``relocalize_after`` such scans
        with no full-rank agreement between them the robot is taken to have been
        moved and the observation estimate replaces the prediction. A scan of one
        landmark leaves a turn free, so it may agree with a wrong pose: it does not
        reset the count (MR.CLAM 1 without ids: a robot 34° off paired single
        detections with the neighbouring landmarks, and each reset the count).
        """
        if index.size == 0 or (robot.pose is None and index.size < 2):
            return
        landmarks = self.map.landmark_means(index)
        joint = self.map.joint_covariance(index)
        if robot.pose is None:
            points, _ = scan_points(obs, noise)
            guess = pose_from_points(points, landmarks, tuple(robot.sensor.offset))
            estimate = observation_estimate(robot.sensor, guess, obs, noise, landmarks, joint)
            if estimate.full_rank:
                robot.pose = estimate.pose
                robot.cov = scipy.linalg.inv(estimate.info)
                robot.localized = True
                self.counts["robots_placed"] += 1
            return
        estimate = observation_estimate(robot.sensor, robot.pose, obs, noise, landmarks, joint)
        if estimate.full_rank:
            cov = np.linalg.inv(estimate.info)
            delta = estimate.pose - robot.pose
            delta[2] = wrap_angle(delta[2])
            spread = robot.cov + cov
            if self.config.turn_slip_in_localization_gate:
                spread[2, 2] += robot.turn_slip
            if delta @ np.linalg.solve(spread, delta) > LOCALIZATION_GATE:
                robot.disagreements += 1
                if robot.disagreements < self.config.relocalize_after:
                    self.counts["localization_rejected"] += 1
                    return
                robot.pose, robot.cov = estimate.pose, 0.5 * (cov + cov.T)
                robot.disagreements, robot.turn_slip = 0, 0.0
                self.counts["relocalized"] += 1
                return
        robot.pose, robot.cov, robot.omega = localize(robot.pose, robot.cov, estimate, self.config.ci_criterion)
        if estimate.full_rank:  # the heading is observed again
            robot.turn_slip = 0.0
            robot.disagreements = 0
        robot.localized = True

    # ---------------------------------------------------------- feature lists
    def _bookkeep(self, robot: RobotState, obs: np.ndarray, noise: np.ndarray, kinds: np.ndarray, refs: np.ndarray,
                  phase_one: bool) -> list[int]:
        """Count sightings and misses of tentative features; return the observations of features confirmed now.

        Features with stored phase-I sightings enter the map here (kinds become
        MAPPED); the others are returned to be added by this scan's update.
        """
        known = self.config.association == "known"
        need = 1 if known else self.config.confirm_hits
        located = robot.pose is not None
        world = robot.sensor.inverse(robot.pose, obs) if located and obs.size else np.full(obs.shape, np.nan)
        covs = self._world_covs(robot, obs, noise) if located and obs.size else np.full((obs.shape[0], 2, 2), np.nan)
        confirmed = []
        seen = set()
        for k in np.flatnonzero((kinds == TENTATIVE) | (kinds == FRESH)).tolist():
            key = int(refs[k])
            t = self.tentative.get(key)
            if t is None:
                t = Tentative(key, world[k].copy(), covs[k].copy(), hits=0)
                self.tentative[key] = t
                kinds[k] = TENTATIVE
            t.hits += 1
            t.misses = 0
            seen.add(key)
            if located:
                t.position, t.cov = world[k].copy(), covs[k].copy()
            if t.hits < need:
                if phase_one:
                    t.phase_one.append((world[k].copy(), covs[k].copy()))
                continue
            if t.phase_one:
                (first_position, first_cov), *later = t.phase_one
                index = self.map.update_absolute([], np.zeros((0, 2)), first_position, first_cov)
                self._register([key], index)
                self._record("absolute", index, first_position, first_cov)
                for position, cov in later:
                    self.map.update_absolute(index, position, np.zeros((0, 2)), cov)
                    self._record("absolute", index, position, cov)
                kinds[k], refs[k] = MAPPED, int(index[0])
            else:
                confirmed.append(k)
        if located:
            self._count_misses(robot, seen)
        return confirmed

    def _count_misses(self, robot: RobotState, seen: set[int]) -> None:
        spec = robot.info.sensor
        for key in [key for key in self.tentative if key not in seen]:
            t = self.tentative[key]
            if not np.all(np.isfinite(t.position)):
                continue
            predicted = robot.sensor.observe(robot.pose, t.position)
            if in_field_of_view(predicted, spec.max_range, spec.fov, spec.min_range):
                t.misses += 1
                if t.misses >= self.config.tentative_misses:
                    del self.tentative[key]
                    self.counts["tentative_dropped"] += 1

    def _world_covs(self, robot: RobotState, obs: np.ndarray, noise: np.ndarray) -> np.ndarray:
        """Covariances (n, 2, 2) of the world positions of observations from the robot's pose."""
        g_pose, g_obs = robot.sensor.inverse_jacobians(robot.pose, obs)
        return g_obs @ noise @ np.swapaxes(g_obs, 1, 2) + g_pose @ robot.cov @ np.swapaxes(g_pose, 1, 2)

    def _register(self, keys: list[int], index: np.ndarray) -> None:
        """Give map indices to features: they leave the tentative list."""
        for key, i in zip(keys, np.asarray(index).tolist()):
            self.ids.append(int(key))
            self.index_of[int(key)] = i
            self.tentative.pop(int(key), None)

    # ---------------------------------------------------------------- mapping
    def _map_phase_one(self, robot: RobotState, obs, noise, kinds, refs, confirmed: list[int]) -> None:
        """Phase I: positions from the known start pose, joint covariance of pose and noise."""
        old_rows = np.flatnonzero(kinds == MAPPED)
        rows = np.concatenate([old_rows, np.asarray(confirmed, np.int64)]).astype(np.int64)
        if rows.size == 0:
            return
        positions = robot.sensor.inverse(robot.pose, obs[rows])
        g_pose, g_obs = robot.sensor.inverse_jacobians(robot.pose, obs[rows])
        g = g_pose.reshape(-1, 3)
        cov = g @ robot.cov @ g.T + block_diagonal(g_obs @ noise @ np.swapaxes(g_obs, 1, 2))
        old = refs[old_rows]
        added = self.map.update_absolute(old, positions[: old_rows.size], positions[old_rows.size:], cov)
        self._register([int(refs[k]) for k in confirmed], added)
        refs[confirmed] = added
        kinds[confirmed] = MAPPED
        self._record("absolute", np.concatenate([old, added]), positions, cov)
        self.counts["phase_one_updates"] += 1

    def _map_phase_two(self, obs, noise, kinds, refs, mapped: np.ndarray, confirmed: list[int]) -> None:
        """Phase II: recast the scan into z_map around a reference pair and update by eq. 10."""
        if mapped.size < 2:
            if mapped.size or confirmed:
                self.counts["scans_too_few_mapped"] += 1
            return
        done = self.map.update_scan(obs, noise, mapped, refs[mapped], np.asarray(confirmed, np.int64),
                                    self.config.min_reference_distance, self.config.map_gate_probability)
        if done is None:
            self.counts["z_map_refused"] += 1
            return
        added, chain, z_map, r_map = done
        self._register([int(refs[k]) for k in confirmed], added)
        refs[confirmed] = added
        kinds[confirmed] = MAPPED
        self._record("recast", chain, z_map, r_map)
        self.counts["phase_two_updates"] += 1

    def _map_local(self, robot: RobotState, obs, noise, kinds, refs) -> None:
        """Phase II over a local map (:mod:`services.dslam.local_map`): this scan joins the robot's local map,
        whose points give z_map once two mapped features are among them.

        The local map is applied (and started afresh) when it holds two mapped
        features and either this scan saw two, or a confirmed new feature waits,
        or the robot's pose in it has become half as uncertain as allowed, or
        it is full; it is given up (counted) past ``local_map_max_std`` or
        ``local_map_max_features`` without two mapped features.
        Tentative features not yet confirmed are left out (marginalised).
        """
        s = self.config
        keys = np.full(obs.shape[0], -1, np.int64)
        for k in np.flatnonzero(kinds == MAPPED).tolist():
            keys[k] = self.ids[int(refs[k])]
        tentative = kinds == TENTATIVE
        keys[tentative] = refs[tentative]
        if robot.local is None:
            robot.local = LocalMap(robot.sensor)
        local = robot.local
        local.observe(obs, noise, keys)
        need = 1 if s.association == "known" else s.confirm_hits
        mapped_keys = [key for key in local.keys if key in self.index_of]
        new_keys = [key for key in local.keys if key in self.tentative and self.tentative[key].hits >= need]
        std = local.position_std()
        linked = np.sum(kinds == MAPPED) >= 2 or new_keys or std > 0.5 * s.local_map_max_std
        if len(mapped_keys) >= 2 and (linked or local.size >= s.local_map_max_features):
            robot.local = None
            self._apply_local(local, mapped_keys, new_keys)
        elif std > s.local_map_max_std or local.size > s.local_map_max_features:
            robot.local = None
            self.counts["local_maps_given_up"] += 1
            if mapped_keys or new_keys:
                self.counts["scans_too_few_mapped"] += local.scans

    def _apply_local(self, local: LocalMap, mapped_keys: list[int], new_keys: list[int]) -> None:
        """z_map of a local map's mapped and confirmed features: update the map, add the new ones."""
        points, cov = local.points(mapped_keys + new_keys)
        m = len(mapped_keys)
        done = self.map.update_points(points, cov, np.arange(m), [self.index_of[key] for key in mapped_keys],
                                      np.arange(m, m + len(new_keys)), self.config.min_reference_distance,
                                      self.config.map_gate_probability)
        if done is None:
            self.counts["z_map_refused"] += 1
            return
        added, chain, z_map, r_map = done
        self._register(new_keys, added)
        self._record("recast", chain, z_map, r_map)
        self.counts["phase_two_updates"] += 1
        self.counts["local_map_scans"] += local.scans

    def _record(self, kind: str, index, z, cov) -> None:
        if self.measurements is not None:
            self.measurements.append((kind, np.asarray(index, np.int64).copy(), np.asarray(z, float).copy(),
                                      np.asarray(cov, float).copy()))

    # ------------------------------------------------------------------- maps
    def load_landmarks(self, keys, means, covs, hits=None, chunk: int = 64) -> None:
        """Seed the map with saved landmarks (:mod:`schemas.mapfile`) as prior information: each mean with the
        inverse of its covariance, landmarks independent (a saved map keeps marginals only), through the phase-I
        update ``chunk`` landmarks at a time. ``keys`` name them (known association: the scans' ids); ``hits``
        is not needed (a saved landmark is mapped). ValueError on a key already in the map."""
        keys = np.asarray(keys, np.int64).reshape(-1)
        means, covs = np.asarray(means, float).reshape(-1, 2), np.asarray(covs, float).reshape(-1, 2, 2)
        if len(set(keys.tolist())) != keys.size or set(keys.tolist()) & set(self.index_of):
            raise ValueError("landmark keys repeat or are already in the map")
        for start in range(0, keys.size, chunk):
            part = slice(start, start + chunk)
            index = self.map.update_absolute([], np.zeros((0, 2)), means[part], block_diagonal(covs[part]))
            self._register(keys[part].tolist(), index)
        if keys.size:
            self.map.recover()
            self.counts["landmarks_loaded"] += keys.size

    def adopt(self, information_map: InformationMap, keys: list[int]) -> None:
        """Continue from a map built elsewhere (``keys``: the feature key of each landmark index), with this configuration."""
        s = self.config
        information_map.track_columns = True
        information_map.tol, information_map.max_iter = s.recovery_tol, s.recovery_max_iter
        information_map.column_tol, information_map.column_max_iter = s.column_tol, s.column_max_iter
        information_map.refactor_iterations, information_map.cache.capacity = s.refactor_iterations, s.column_cache
        if information_map.factored != (s.covariance_columns == "factored"):
            information_map.use_columns(s.covariance_columns, s.column_cache)
        information_map.check_every = s.recovery_check_every
        information_map.column_solver, information_map.correction_limit = s.column_solver, s.column_correction_limit
        self.map = information_map
        self.ids, self.index_of, self.tentative = [], {}, {}
        self._register(list(keys), np.arange(information_map.n))

    def landmark_map(self) -> MapView:
        """Means, marginal covariances and ids (true ids with known association) of the map.

        Up to ``marginals_limit`` landmarks every marginal is exact; beyond, the
        landmarks with a cached column get theirs and the others the inverse of
        their own information block (a lower bound: the reports' cost stays O(N)).
        """
        self.map.recover()  # the check maintain() may have deferred
        means = self.map.means.copy()
        if self.map.n <= self.config.marginals_limit:
            covs = self.map.all_marginals()
        else:
            covs = inv2(self.map.matrix.diagonal_blocks())[0]
            cached, cached_covs = self.map.cached_marginals()
            covs[cached] = cached_covs
        ids = np.asarray(self.ids, np.int64) if self.config.association == "known" else None
        return MapView(means, covs, ids)

    def map_snapshot(self) -> MapSnapshot:
        """The map as the service publishes it (see :class:`MapSnapshot`); cheap: no covariance is solved."""
        ids = np.asarray(self.ids, np.int64)
        near, covs = self.map.cached_marginals()
        stamps = [r.stamp for r in self.robots.values() if np.isfinite(r.stamp)]
        return MapSnapshot(
            means=self.map.means.copy(), ids=ids, covariance_ids=ids[near] if near.size else np.zeros(0, np.int64),
            covariances=covs, info_nnz=self.map.matrix.nnz, recovery_iterations=self.map.recovery_iterations,
            stamp=max(stamps) if stamps else 0.0,
        )

    # ------------------------------------------------------ columns off the scan
    def column_prefetch(self) -> ColumnJob | None:
        """The covariance columns the robots will soon need and the cache lacks, as a :class:`ColumnJob` for a
        worker thread between scans (None: nothing to do, or ``column_prefetch_margin`` 0): first those the scans
        a robot without a pose keeps wait for (:meth:`defer_scan`); then those of the landmarks within max range +
        ``candidate_margin`` + ``column_prefetch_margin`` of a placed robot's sensor (the association asks for those
        within max range + ``candidate_margin``), nearest first."""
        s = self.config
        if s.column_prefetch_margin <= 0 or self.map.n == 0:
            return None
        wanted = [i for robot in self.robots.values() for i in robot.wanted]
        if wanted and (job := self.map.column_job(wanted, s.column_prefetch_batch)) is not None:
            return job  # scans of a robot without a pose wait for these (defer_scan)
        means = self.map.stale_means()
        best = np.full(self.map.n, np.inf)
        for robot in self.robots.values():
            if robot.pose is None:
                continue
            reach = robot.info.sensor.max_range + s.candidate_margin + s.column_prefetch_margin
            position = robot.sensor.sensor_position(robot.pose)[0]
            d2 = np.sum((means - position) ** 2, axis=1)
            best = np.where(d2 <= reach * reach, np.minimum(best, d2), best)
        near = np.flatnonzero(np.isfinite(best))
        return self.map.column_job(near[np.argsort(best[near], kind="stable")], s.column_prefetch_batch)

    def take_prefetched(self, job: ColumnJob, solved: np.ndarray) -> int:
        """Cache the columns a :meth:`column_prefetch` job solved (exact for the updates since); how many."""
        return self.map.take_columns(job, solved)

    def extra_metrics(self) -> dict:
        """Figures for ``fleetslam run``: the core's counters and sparsity."""
        return {"dslam": self.stats()}

    def stats(self) -> dict[str, float]:
        """Figures for the service's stats: sparsity, recovery, timing, list sizes."""
        return {
            "landmarks": float(self.map.n),
            "tentative": float(len(self.tentative)),
            "info_nnz": float(self.map.matrix.nnz),
            "recovery_iterations": float(self.map.recovery_iterations),
            "column_iterations": float(self.map.column_iterations),
            "column_solves": float(self.map.column_solves),
            "factorisations": float(self.map.factorisations),
            "columns_prefetched": float(self.map.columns_prefetched),
            "columns_prefetch_dropped": float(self.map.columns_prefetch_dropped),
            "step_ms": float(self.last_step_ms),
            "memory_mb": self.map.memory_bytes() / 2**20,
            **{k: float(v) for k, v in self.counts.items()},
        }


def make_estimator(options: RunOptions, infos: list[RobotInfo]) -> DSlam:
    """The "dslam" estimator: ``options.association`` and the ``options.settings`` of :class:`DslamConfig`
    (:class:`SettingsError` naming an unknown setting or a bad value, with the known ones)."""
    known = sorted(set(DslamConfig.model_fields) - {"association"})  # association: RunOptions.association
    unknown = sorted(set(options.settings) - set(known))
    if unknown:
        raise SettingsError(f"unknown dslam setting{'s' if len(unknown) > 1 else ''} {', '.join(unknown)} "
                            f"(known: {', '.join(known)})")
    config = build_config(DslamConfig, {**options.settings, "association": options.association}, owner="dslam",
                          given=set(options.settings))
    estimator = DSlam(config)
    for info in infos:
        estimator.add_robot(info)
    return estimator
