"""The robots one Monte Carlo localization run tracks: one filter per robot on a shared map.

:class:`MclFleet` is the single per-robot table of both drivers: the
``fleetslam mcl`` service (robots join as their RobotInfo arrives, the map may
come later) and the offline estimator ``fleetslam run --estimator mcl``
(:func:`make_estimator`: a prior map, every robot from no pose, and with the
truth the time each robot took to converge). It offers the
:class:`~schemas.contract.Estimator` protocol. Every filter it builds draws
from its own stream ``[seed, crc32(robot id), n]``, n counting the filters
built for that robot so far: not from the order robots happened to announce
themselves, so two runs of the same data draw the same numbers.
"""

from __future__ import annotations

import time
import zlib
from dataclasses import dataclass
from typing import Callable

import numpy as np

from robots.models import wrap_angle
from schemas.contract import MapView, OdomEvent, RunOptions, ScanEvent
from schemas.messages import RobotInfo, SensorSpec
from services.mcl.config import MclConfig
from services.mcl.core import Hypothesis, MonteCarloLocalizer, UpdateReport
from services.mcl.likelihood import MapCache, scan_log_likelihood

UNKNOWN_COV = np.diag([1e6, 1e6, 1e2])


@dataclass
class RobotState:
    """One robot of the fleet: its filter (None until there is a map) and what was measured about it."""

    info: RobotInfo
    mcl: MonteCarloLocalizer | None = None
    scans: int = 0
    localized: bool = False  # as of the last scan
    first_stamp: float | None = None
    hypotheses_max: int = 0
    localized_s: float | None = None  # robot time from the first scan until first localized
    converge_s: float | None = None  # ... until first localized within converge_xy / converge_theta of the truth
    final_error_m: float | None = None
    final_error_rad: float | None = None
    particles_total: int = 0  # sum over the scans of the sample size after each
    particles_max: int = 0


class MclFleet:
    """One :class:`MonteCarloLocalizer` per robot on one landmark map.

    ``use_start_pose``: a robot whose RobotInfo gives a start pose is tracked from it (else it is localized
    globally, as every robot is offline). ``truth`` ``{rid: (stamps, poses)}`` lets the fleet measure errors.
    """

    def __init__(self, config: MclConfig, landmarks: np.ndarray | None = None,
                 truth: dict[str, tuple[np.ndarray, np.ndarray]] | None = None, use_start_pose: bool = True,
                 landmark_ids: np.ndarray | None = None):
        self.config = config
        self.landmarks = None if landmarks is None else np.asarray(landmarks, float).reshape(-1, 2)
        self.landmark_ids = None if landmark_ids is None else np.asarray(landmark_ids, np.int64).reshape(-1)
        self.truth = {rid: (np.asarray(s, float), np.asarray(p, float)) for rid, (s, p) in (truth or {}).items()}
        self.use_start_pose = use_start_pose
        self.robots: dict[str, RobotState] = {}
        self.filters_built: dict[str, int] = {}
        self.maps = MapCache()  # the map prepared once for the robots and queries that share a sensor

    def __setstate__(self, state: dict) -> None:
        """Unpickle (a service checkpoint); one written before the map cache existed gets an empty one."""
        self.__dict__.update(state)
        self.__dict__.setdefault("maps", MapCache())

    # ------------------------------------------------------------ membership

    def __contains__(self, rid: str) -> bool:
        return rid in self.robots

    def add_robot(self, info: RobotInfo) -> None:
        """Take a robot in (its filter is built now if there is a map, else with the first map)."""
        self.robots[info.robot_id] = RobotState(info=info, mcl=self._build(info))

    def remove_robot(self, rid: str) -> None:
        self.robots.pop(rid, None)

    def set_map(self, landmarks: np.ndarray, landmark_ids: np.ndarray | None = None) -> None:
        """Use a (newer) map, with its landmark ids if it has them: robots waiting for one get their filter, the
        others keep their particles."""
        self.landmarks = np.asarray(landmarks, float).reshape(-1, 2)
        self.landmark_ids = None if landmark_ids is None else np.asarray(landmark_ids, np.int64).reshape(-1)
        for state in self.robots.values():
            if state.mcl is None:
                state.mcl = self._build(state.info)
            else:
                state.mcl.set_map(self.landmarks, self.landmark_ids, self.maps)

    def _build(self, info: RobotInfo) -> MonteCarloLocalizer | None:
        if self.landmarks is None:
            return None
        if not self.use_start_pose:
            info = info.model_copy(update={"start_pose": None, "start_pose_cov": None})
        rid = info.robot_id
        built = self.filters_built.get(rid, 0)
        self.filters_built[rid] = built + 1
        rng = np.random.default_rng([self.config.seed, zlib.crc32(rid.encode()), built])
        return MonteCarloLocalizer(self.landmarks, info, self.config, rng, self.landmark_ids, self.maps)

    # ---------------------------------------------------------------- events

    def on_odometry(self, event: OdomEvent) -> None:
        state = self.robots.get(event.robot_id)
        if state is not None and state.mcl is not None:
            state.mcl.predict(event.control, event.dt, event.control_cov)

    def on_scan(self, event: ScanEvent) -> UpdateReport | None:
        """Run the filter's update; None for a robot the fleet has no filter for."""
        state = self.robots.get(event.robot_id)
        if state is None or state.mcl is None:
            return None
        mcl = state.mcl
        report = mcl.update(event.observations, event.landmark_ids)
        state.scans += 1
        state.localized = report.localized
        if state.first_stamp is None:
            state.first_stamp = event.stamp
        elapsed = event.stamp - state.first_stamp
        state.hypotheses_max = max(state.hypotheses_max, report.hypotheses)
        state.particles_total += report.particles_after
        state.particles_max = max(state.particles_max, report.particles_after)
        if report.localized and state.localized_s is None:
            state.localized_s = elapsed
        error = self._error(event.robot_id, event.stamp, mcl)
        if error is not None:
            state.final_error_m, state.final_error_rad = error
            close = error[0] <= self.config.converge_xy and error[1] <= self.config.converge_theta
            if report.localized and close and state.converge_s is None:
                state.converge_s = elapsed
        return report

    def _error(self, rid: str, stamp: float, mcl: MonteCarloLocalizer) -> tuple[float, float] | None:
        """(position, heading) error of the best hypothesis against the nearest truth sample, if any."""
        if rid not in self.truth or mcl.best() is None:
            return None
        stamps, poses = self.truth[rid]
        if stamps.size == 0:
            return None
        k = int(np.clip(np.searchsorted(stamps, stamp), 1, stamps.size - 1)) if stamps.size > 1 else 0
        if stamps.size > 1 and abs(stamps[k - 1] - stamp) < abs(stamps[k] - stamp):
            k -= 1
        truth = poses[k]
        if abs(stamps[k] - stamp) > 0.5 or not np.all(np.isfinite(truth)):
            return None
        best = mcl.best()[0]
        return float(np.hypot(*(best[:2] - truth[:2]))), float(abs(wrap_angle(best[2] - truth[2])))

    # --------------------------------------------------------------- outputs

    def poses(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Every robot's best hypothesis (mean, covariance); a huge covariance before its first scan."""
        out = {}
        for rid, state in self.robots.items():
            best = state.mcl.best() if state.mcl is not None else None
            out[rid] = best if best is not None else (np.zeros(3), UNKNOWN_COV.copy())
        return out

    def hypotheses(self, rid: str) -> list[Hypothesis]:
        """A robot's significant hypotheses, heaviest first (empty before its first scan)."""
        state = self.robots.get(rid)
        return state.mcl.hypotheses() if state is not None and state.mcl is not None else []

    def localized_count(self) -> int:
        return sum(1 for state in self.robots.values() if state.mcl is not None and state.mcl.localized)

    def landmark_map(self) -> MapView:
        """Localization only: no map of its own."""
        return MapView.empty()

    def extra_metrics(self) -> dict:
        """Per robot: localized at the end, time to converge (s of robot time), most hypotheses held, and more."""
        built = {rid: state for rid, state in self.robots.items() if state.mcl is not None}
        return {
            "localized": {rid: state.mcl.localized for rid, state in built.items()},
            "converge_s": {rid: state.converge_s for rid, state in built.items()},
            "hypotheses_max": {rid: state.hypotheses_max for rid, state in built.items()},
            "mcl": {
                "variant": self.config.variant,
                "robots": {
                    rid: {
                        "localized_s": state.localized_s,
                        "final_error_m": state.final_error_m,
                        "final_error_rad": state.final_error_rad,
                        "particles_mean": state.particles_total / state.scans if state.scans else None,
                        "particles_max": state.particles_max if state.scans else None,
                        "restarts": state.mcl.restarts,
                        "kidnaps_detected": state.mcl.kidnaps,
                        "contradictions": state.mcl.contradictions,
                    }
                    for rid, state in built.items()
                },
            },
        }

    # -------------------------------------------------------------- one-shot

    def localize_once(self, observations: np.ndarray, sensor: SensorSpec, particles: int, seed: int,
                      robot_id: str = "query", landmarks: np.ndarray | None = None, time_budget_s: float | None = None,
                      clock: Callable[[], float] = time.perf_counter, slice_cells: int = 1_000_000,
                      ) -> MonteCarloLocalizer:
        """A fresh filter globally localized from one scan ``(n, 2)`` and weighed by it (not resampled).

        Against ``landmarks`` (default: the fleet's map; ValueError without one); the fleet's robots are not
        touched, so a worker thread may run it. The candidates are weighed ``slice_cells`` (observations ×
        poses) at a time; with ``time_budget_s`` (seconds on ``clock``) TimeoutError is raised once the budget is
        spent, between slices.
        """
        landmarks = self.landmarks if landmarks is None else landmarks
        if landmarks is None:
            raise ValueError("no map to localize against yet")
        started = clock()

        def check(stage: str) -> None:
            if time_budget_s is not None and clock() - started > time_budget_s:
                raise TimeoutError(f"the {time_budget_s:.3g} s budget ran out {stage} ({particles} particles, "
                                   f"{len(observations)} observations)")

        info = RobotInfo(robot_id=robot_id, stamp=0.0, motion_model="unicycle", sensor=sensor, odom_rate_hz=1.0,
                         scan_rate_hz=1.0)
        mcl = MonteCarloLocalizer(landmarks, info, self.config, np.random.default_rng(seed), maps=self.maps)
        z = np.asarray(observations, float).reshape(-1, 2)
        mcl.initialize_global(z, particles)
        check("drawing poses from the scan")
        loglik, quality = np.empty(mcl.count), np.empty(mcl.count)
        step = max(1, slice_cells // max(len(z), 1))
        for start in range(0, mcl.count, step):
            part = slice(start, start + step)
            loglik[part], quality[part] = scan_log_likelihood(mcl.particles[part], z, mcl.map, mcl.model,
                                                              self.config.chunk_particles, self.config.compiled)
            check("weighing the poses")
        mcl.reweigh(loglik, quality)  # what MonteCarloLocalizer.weigh does after its likelihood, here in slices
        return mcl


def make_estimator(options: RunOptions, infos: list[RobotInfo]) -> MclFleet:
    """The offline MCL estimator: every robot localized from no pose against ``options.landmarks``.

    ``options.settings`` are :class:`MclConfig` settings (``--set variant=kld``); ``options.particles``, when
    given, is the sample size; ``options.truth`` enables the convergence figures; with ``association`` known,
    ``options.landmark_ids`` (the map's ids) let detections with ids act as signatures. SettingsError (a ValueError)
    on an unknown or bad setting, ValueError without a map.
    """
    if options.landmarks is None:
        raise ValueError("the mcl estimator localizes against a map: pass RunOptions.landmarks, an (L, 2) array")
    given = {"seed": options.seed, **({"particles": options.particles} if options.particles is not None else {}),
             **options.settings}
    config = MclConfig().with_overrides(given, owner="mcl")
    ids = options.landmark_ids if options.association == "known" else None
    fleet = MclFleet(config, options.landmarks, options.truth, use_start_pose=False, landmark_ids=ids)
    for info in infos:
        fleet.add_robot(info)
    return fleet
