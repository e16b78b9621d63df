"""MCL behind the common estimator protocol, for ``fleetslam run --estimator mcl`` and the benchmarks.

Global localisation offline: every robot starts with no pose (unless
``options.extra["use_start_pose"]``) and is localised against the map given in
``options.extra["map"]`` (``(L, 2)``, the data set's true map). With the truth
in ``options.extra["truth"]`` = ``{rid: (stamps, poses)}`` it also measures,
per robot, the robot time until it converged: localised (one hypothesis
holds) and within ``converge_xy`` / ``converge_theta`` of the truth.
``extra_metrics()`` reports ``localized``, ``converge_s``, ``hypotheses_max``
per robot. Other filter settings may come in ``options.extra["mcl"]``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from robots.dataset import OdomEvent, ScanEvent
from robots.models import wrap_angle
from schemas.config import MclFilterSettings
from schemas.messages import RobotInfo
from services.estimator import MapView, RunOptions, refuse_unknown_settings
from services.mcl.core import MonteCarloLocalizer

UNKNOWN_COV = np.diag([1e6, 1e6, 1e2])


@dataclass
class RobotRecord:
    """What the estimator measured about one robot's localisation."""

    first_stamp: float | None = None
    hypotheses_max: int = 0
    converge_s: float | None = None
    localized_s: float | None = None
    final_error_m: float | None = None
    final_error_rad: float | None = None
    particles: list[int] = field(default_factory=list)


class MclEstimator:
    """One :class:`MonteCarloLocalizer` per robot on a fixed map."""

    def __init__(self, options: RunOptions, infos: list[RobotInfo]):
        extra = options.extra or {}
        if extra.get("map") is None:
            raise ValueError("the mcl estimator localises against a map: pass options.extra['map'] = (L, 2) landmarks")
        self.landmarks = np.asarray(extra["map"], float).reshape(-1, 2)
        overrides = {"seed": options.seed, **({"variant": options.variant} if options.variant else {})}
        if "particles" in extra:
            overrides["particles"] = int(extra["particles"])
        refuse_unknown_settings("mcl", extra.get("mcl", {}), set(MclFilterSettings.model_fields) - {"seed", "variant"})
        overrides.update(extra.get("mcl", {}))
        self.settings = MclFilterSettings(**overrides)
        self.truth = {rid: (np.asarray(s, float), np.asarray(p, float)) for rid, (s, p) in extra.get("truth", {}).items()}
        self.use_start_pose = bool(extra.get("use_start_pose", False))
        self.filters: dict[str, MonteCarloLocalizer] = {}
        self.records: dict[str, RobotRecord] = {}
        for info in infos:
            self.add_robot(info)

    def add_robot(self, info: RobotInfo) -> None:
        if not self.use_start_pose:
            info = info.model_copy(update={"start_pose": None, "start_pose_cov": None})
        rng = np.random.default_rng([self.settings.seed, len(self.filters)])
        self.filters[info.robot_id] = MonteCarloLocalizer(self.landmarks, info, self.settings, rng)
        self.records[info.robot_id] = RobotRecord()

    def on_odometry(self, event: OdomEvent) -> None:
        if event.robot_id in self.filters:
            self.filters[event.robot_id].predict(event.control, event.dt, event.control_cov)

    def on_scan(self, event: ScanEvent) -> None:
        mcl = self.filters.get(event.robot_id)
        if mcl is None:
            return
        report = mcl.update(event.observations)
        record = self.records[event.robot_id]
        if record.first_stamp is None:
            record.first_stamp = event.stamp
        elapsed = event.stamp - record.first_stamp
        record.hypotheses_max = max(record.hypotheses_max, report.hypotheses)
        record.particles.append(report.particles_after)
        if report.localized and record.localized_s is None:
            record.localized_s = elapsed
        error = self._error(event.robot_id, event.stamp, mcl)
        if error is not None:
            record.final_error_m, record.final_error_rad = error
            close = error[0] <= self.settings.converge_xy and error[1] <= self.settings.converge_theta
            if report.localized and close and record.converge_s is None:
                record.converge_s = elapsed

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

    def poses(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        out = {}
        for rid, mcl in self.filters.items():
            best = mcl.best()
            out[rid] = best if best is not None else (np.zeros(3), UNKNOWN_COV.copy())
        return out

    def landmark_map(self) -> MapView:
        return MapView(np.zeros((0, 2)), np.zeros((0, 2, 2)), None)

    def extra_metrics(self) -> dict:
        """Per robot: localised at the end, time to converge (s of robot time), most hypotheses held."""
        return {
            "localized": {rid: self.filters[rid].localized for rid in self.filters},
            "converge_s": {rid: r.converge_s for rid, r in self.records.items()},
            "hypotheses_max": {rid: r.hypotheses_max for rid, r in self.records.items()},
            "mcl": {
                "variant": self.settings.variant,
                "robots": {
                    rid: {
                        "localized_s": r.localized_s,
                        "final_error_m": r.final_error_m,
                        "final_error_rad": r.final_error_rad,
                        "particles_mean": float(np.mean(r.particles)) if r.particles else None,
                        "particles_max": int(max(r.particles)) if r.particles else None,
                        "restarts": self.filters[rid].restarts,
                        "kidnaps_detected": self.filters[rid].kidnaps,
                    }
                    for rid, r in self.records.items()
                },
            },
        }


def make_estimator(options: RunOptions, infos: list[RobotInfo]) -> MclEstimator:
    return MclEstimator(options, infos)
