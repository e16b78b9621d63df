"""Fleet placement without start poses, offline: who anchors the frame, and where the others join.

``fleetslam run --start-poses known|first|none`` decides which robots keep the start pose of the data
(:func:`withhold_start_poses`). An estimator that can take robots without a pose (it offers ``is_waiting``,
``place_robot``, ``landmark_map`` and ``robot_count``: the central FastSLAM) then gets them placed by a
:class:`FleetPlacer` that sits between the data and the estimator, as the MCL service does live:

- while no robot is placed, the first robot to scan anchors the world frame: it is placed at the origin
  (DESIGN §3: the world frame is the first robot's start pose unless a start pose is given), unless the
  estimator started from a saved map (``--map``): that map's frame is the world frame, and every robot is
  localized against it;
- every other robot without a pose is localized globally by Monte Carlo localization (one filter per robot
  in a :class:`services.mcl.fleet.MclFleet`, the table the MCL service and estimator use) against the estimator's map so far, with landmark ids
  as signatures when the map and the scans have them; once localized it joins the estimator at the
  localized pose and covariance. Its odometry and scans until then feed the localizer only; they are
  counted, never silently dropped;
- with signatures, a localized pose must also explain the landmarks the robot sees by id: every detection of
  a mapped landmark within the gate (``verify_gate``), over scans that cover two landmarks at least
  ``verify_baseline_m`` apart. MCL may call a pose localized when resampling has collapsed its particles on
  one arc of the circle a single landmark allows (MR.CLAM: a robot that sees one landmark for 30 s); a
  detection the pose contradicts starts the robot's localization again, from that scan.

Each robot's :class:`Placement` says when and how it was placed, or why not.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from robots.gaussian import chi2_quantile, inv2, quad2
from robots.models import robot_models
from schemas.contract import Event, OdomEvent, ScanEvent
from schemas.messages import RobotInfo
from services.mcl.config import MclConfig
from services.mcl.fleet import MclFleet

START_POSES = ("known", "first", "none")


def withhold_start_poses(infos: list[RobotInfo], mode: str) -> list[RobotInfo]:
    """The robots' infos under ``mode``: ``known`` as they are, ``first`` only the first robot's start pose,
    ``none`` no start pose at all."""
    if mode not in START_POSES:
        raise ValueError(f"start poses must be one of {', '.join(START_POSES)}, not {mode!r}")
    keep = {"known": len(infos), "first": 1, "none": 0}[mode]
    return [info if k < keep else info.model_copy(update={"start_pose": None, "start_pose_cov": None})
            for k, info in enumerate(infos)]


@dataclass
class Placement:
    """How one robot entered the estimator (``how``: start pose, anchor, mcl), or why it has not."""

    robot_id: str
    how: str | None = None
    placed_stamp: float | None = None
    first_scan_stamp: float | None = None
    scans_before: int = 0  # scans that went to the localizer before the robot was placed
    odometry_before: int = 0
    mcl_updates: int = 0
    mcl_restarts: int = 0  # localizations started again because the localized pose contradicted a detection
    reason: str | None = None  # why the robot is not placed (at the end)

    def report(self, start: float) -> dict:
        """The JSON form, stamps made relative to the run's ``start``, and the delay from the first scan."""
        out = asdict(self)
        placed, first = out.pop("placed_stamp"), out.pop("first_scan_stamp")
        out["placed_s"] = None if placed is None else round(placed - start, 3)
        out["first_scan_s"] = None if first is None else round(first - start, 3)
        if self.placed_stamp is not None and self.first_scan_stamp is not None:
            out["placed_after_first_scan_s"] = round(self.placed_stamp - self.first_scan_stamp, 3)
        return out


class PlacementCheck:
    """Whether a robot MCL placed must be placed again: MCL, localized, has put it farther than ``distance_m`` from
    the filter's pose for ``messages`` poses in a row. MCL's first ``localized`` can be a wrong hypothesis of a
    symmetric map that it later leaves by relocalizing; the filter never sees that on its own, since the robot's
    scans then build its own part of the map where it was put."""

    def __init__(self, distance_m: float, messages: int):
        self.distance_m = distance_m
        self.messages = messages
        self.runs: dict[str, int] = {}

    def observe(self, robot_id: str, filter_pose, mcl_pose) -> bool:
        """Count one localized MCL pose; True (and the count starts again) when the robot must be placed again."""
        if self.messages <= 0:
            return False
        apart = float(np.hypot(*(np.asarray(filter_pose, float)[:2] - np.asarray(mcl_pose, float)[:2])))
        run = self.runs.get(robot_id, 0) + 1 if apart > self.distance_m else 0
        self.runs[robot_id] = run
        if run < self.messages:
            return False
        self.runs.pop(robot_id)
        return True

    def forget(self, robot_id: str) -> None:
        self.runs.pop(robot_id, None)


class FleetPlacer:
    """Hold back the events of robots the estimator has not placed, anchor the first, localize the others."""

    def __init__(self, estimator, infos: list[RobotInfo], config: MclConfig, use_signatures: bool,
                 map_refresh_s: float = 5.0, min_landmarks: int = 3, verify_probability: float = 0.999,
                 verify_baseline_m: float = 0.3):
        self.estimator = estimator
        self.use_signatures = use_signatures
        self.map_refresh_s = map_refresh_s
        self.min_landmarks = min_landmarks
        self.verify_gate = chi2_quantile(verify_probability, 2)
        self.verify_baseline_m = verify_baseline_m
        self.noise_scale = config.noise_scale
        self.verified: dict[str, set[int]] = {}  # per robot: landmark ids its localized pose has explained
        self.slot_of: dict[int, int] = {}  # landmark id -> row of the localizers' map
        self.infos = {info.robot_id: info for info in infos}
        self.localizers = MclFleet(config, use_start_pose=False)  # a robot joins it at its first scan with a map
        self.map_stamp = -np.inf
        self.map_ready = False
        self.prior_map = len(estimator.landmark_map().means) > 0  # a saved map: its frame, no anchor
        self.placements = {info.robot_id: Placement(info.robot_id) for info in infos}
        for info in infos:
            if estimator.has_robot(info.robot_id):
                self.placements[info.robot_id].how = "start pose"

    def holds(self, event: Event) -> bool:
        """Take the event if its robot waits for a pose (True); False: the estimator should have it."""
        rid = event.robot_id
        if rid not in self.placements or not self.estimator.is_waiting(rid):
            return False
        record = self.placements[rid]
        if isinstance(event, OdomEvent):
            record.odometry_before += 1
            self.localizers.on_odometry(event)
            return True
        if not isinstance(event, ScanEvent):
            return True
        if record.first_scan_stamp is None:
            record.first_scan_stamp = event.stamp
        if self.estimator.robot_count == 0 and not self.prior_map:
            return self._place(record, np.zeros(3), np.zeros((3, 3)), event.stamp, "anchor")
        self._refresh_map(event.stamp)
        if not self.map_ready:
            return self._hold(record, f"the map has fewer than {self.min_landmarks} landmarks")
        if rid not in self.localizers:
            self.localizers.add_robot(self.infos[rid])
        report = self.localizers.on_scan(event)
        record.mcl_updates += 1
        if not report.localized:
            self.verified.pop(rid, None)
            return self._hold(record, "not localized against the map yet")
        pose, cov = self.localizers.robots[rid].mcl.best()
        if self.use_signatures and self.localizers.landmark_ids is not None and event.landmark_ids is not None:
            explained = self._explained(rid, pose, event)
            if explained is None:
                record.mcl_restarts += 1
                self.verified.pop(rid, None)
                self.localizers.remove_robot(rid)
                self.localizers.add_robot(self.infos[rid])
                self.localizers.on_scan(event)  # the new filter starts from the scan that contradicted the old one
                return self._hold(record, "the localized pose contradicted a detection: localizing again")
            seen = self.verified.setdefault(rid, set()) | explained
            self.verified[rid] = seen
            if not self._spread(seen):
                return self._hold(record, f"localized; waiting to see landmarks {self.verify_baseline_m:g} m apart by id")
        return self._place(record, pose, cov, event.stamp, "mcl")

    def _explained(self, rid: str, pose: np.ndarray, event: ScanEvent) -> set[int] | None:
        """The mapped landmark ids of the scan that ``pose`` explains (each detection within ``verify_gate`` of its
        landmark, with the sensor noise scaled as MCL scales it); None if it contradicts one of them."""
        ids = np.asarray(event.landmark_ids).ravel()
        ranges, bearings = np.asarray(event.ranges, float).ravel(), np.asarray(event.bearings, float).ravel()
        if not (ids.size == ranges.size == bearings.size) or ids.dtype.kind not in "iu":
            return set()  # a malformed scan checks nothing (the estimator counts its rejection)
        rows = [j for j, i in enumerate(ids.tolist()) if i in self.slot_of]
        if not rows:
            return set()
        _, sensor = robot_models(self.infos[rid])
        targets = self.localizers.landmarks[[self.slot_of[int(ids[j])] for j in rows]]
        z = np.stack([ranges[rows], bearings[rows]], -1)
        nu = sensor.innovation(z, sensor.observe(np.asarray(pose, float), targets))
        noise = np.asarray(event.noise_cov, float) * self.noise_scale**2
        d2 = quad2(nu, inv2(noise[None])[0])
        return None if np.any(d2 > self.verify_gate) else {int(ids[j]) for j in rows}

    def _spread(self, ids: set[int]) -> bool:
        """Whether the landmarks ``ids`` include two at least ``verify_baseline_m`` apart."""
        points = self.localizers.landmarks[[self.slot_of[i] for i in ids if i in self.slot_of]]
        return len(points) > 1 and float(np.max(np.linalg.norm(points[:, None] - points[None], axis=-1))) >= self.verify_baseline_m

    @staticmethod
    def _hold(record: Placement, reason: str) -> bool:
        """Keep a scan from the estimator (counted), saying why the robot is not placed yet."""
        record.scans_before += 1
        record.reason = reason
        return True

    def _place(self, record: Placement, pose, cov, stamp: float, how: str) -> bool:
        """Place the robot; its scan then goes to the estimator too (False), unless the estimator refused it."""
        if not self.estimator.place_robot(record.robot_id, pose, cov, stamp=stamp):
            return self._hold(record, f"the estimator refused the {how} pose")
        record.how, record.placed_stamp, record.reason = how, stamp, None
        self.verified.pop(record.robot_id, None)
        self.localizers.remove_robot(record.robot_id)
        return False

    def _refresh_map(self, stamp: float) -> None:
        """The estimator's map, taken again every ``map_refresh_s`` of data time (None: too few landmarks)."""
        if stamp - self.map_stamp < self.map_refresh_s:
            return
        view = self.estimator.landmark_map()
        means = np.asarray(view.means, float).reshape(-1, 2)
        self.map_stamp = stamp
        self.map_ready = len(means) >= self.min_landmarks
        if self.map_ready:
            self.localizers.set_map(means, None if view.ids is None or not self.use_signatures else view.ids)
            ids = self.localizers.landmark_ids
            self.slot_of = {} if ids is None else {int(i): k for k, i in enumerate(ids.tolist())}

    def report(self, start: float) -> dict:
        """Per robot: how and when it was placed, or why not."""
        return {rid: record.report(start) for rid, record in self.placements.items()}
