"""Fleet placement without start poses, offline: who anchors the frame, and where the others join.

``fleetslam run --start-poses known|first|none`` decides which robots keep the start pose of the data
(:func:`withhold_start_poses`). An estimator that can take robots without a pose (it offers ``is_waiting``,
``place_robot``, ``landmark_map`` and ``robot_count``: FastSLAM and D-SLAM) then gets them placed by a
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
- with signatures, MCL calls a robot localized only once its hypothesis has explained, by id, detections of
  two landmarks at least ``MclConfig.localized_baseline_m`` apart, and starts again when a detection
  contradicts it: resampling can collapse the particles on one arc of the circle a single landmark allows
  (MR.CLAM);
- robots that detect each other (``meetings``, on by default): a detection between a robot without a pose
  and a placed robot, either way, is kept with the robot's dead-reckoned pose then; its recent meetings place
  it as soon as they fix its pose on their own, map or no map. A meeting no particle of its localizer agrees
  with starts the localization again from where the meeting puts it, and a pose MCL calls localized that
  contradicts one of its meetings is refused (:mod:`services.mcl.meeting`). Without landmark ids a map can be nearly symmetric (MR.CLAM under a half
  turn), and early in a run the anchor's map too small for MCL; the robots' own ids are neither;
- MCL starts on a robot once the map holds ``MclConfig.map_min_landmarks`` (3) landmarks with ids,
  ``map_min_landmarks_unsigned`` (6) without, as the MCL service does live: on three to five of MR.CLAM's
  landmark clusters MCL placed robots 46–155° off (Dataset 1 seeds 1, 4, 8; Dataset 6 seed 25).

Each robot's :class:`Placement` says when and how it was placed, or why not.
"""

from __future__ import annotations

import bisect
from collections import deque
from dataclasses import asdict, dataclass

import numpy as np

from robots.models import wrap_angle
from schemas.contract import Event, OdomEvent, ScanEvent
from schemas.messages import RobotInfo
from services.mcl.config import MclConfig
from services.mcl.fleet import MclFleet
from services.mcl.meeting import MeetingDesk

START_POSES = ("known", "first", "none")


def withhold_start_poses(infos: list[RobotInfo], mode: str) -> list[RobotInfo]:
    """The robots' infos under ``mode``: ``known`` as they are, ``first`` only the first robot's start pose,
    ``none`` no start pose at all."""
    if mode not in START_POSES:
        raise ValueError(f"start poses must be one of {', '.join(START_POSES)}, not {mode!r}")
    keep = {"known": len(infos), "first": 1, "none": 0}[mode]
    return [info if k < keep else info.model_copy(update={"start_pose": None, "start_pose_cov": None})
            for k, info in enumerate(infos)]


def draw_start_poses(infos: list[RobotInfo], seed: int) -> list[RobotInfo]:
    """The robots' infos with each start pose drawn from its announced covariance (seed 0: as announced).

    A start pose is a measurement: a user who surveyed it knows it within its covariance, not exactly. An estimator
    that draws nothing at random (D-SLAM) gives one run per data set; drawing its start poses this way gives it
    seeds, so a change to it can be judged against a spread. Robots without a start pose or a covariance are kept.
    """
    if seed == 0:
        return list(infos)
    rng = np.random.default_rng(seed)
    drawn = []
    for info in infos:
        if info.start_pose is None or info.start_pose_cov is None:
            drawn.append(info)
            continue
        pose = rng.multivariate_normal(np.asarray(info.start_pose, float), np.asarray(info.start_pose_cov, float))
        pose[2] = wrap_angle(pose[2])
        drawn.append(info.model_copy(update={"start_pose": pose}))
    return drawn


def anchor_due(waiting: dict[str, float], now: float, after_s: float) -> str | None:
    """Live: the robot that anchors the world frame at the origin now (DESIGN §3), of the robots ``waiting`` for a pose
    (robot id → when it was announced, wall clock): the first announced, once it has waited ``after_s`` (a robot
    with a start pose announced meanwhile is placed instead); None while none is due."""
    if not waiting:
        return None
    announced, rid = min((t, rid) for rid, t in waiting.items())
    return rid if now - announced >= after_s else None


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
    mcl_restarts: int = 0  # global localizations MCL started again (a contradicted hypothesis, a lost robot)
    meetings: int = 0  # detections between the robot and a placed robot, kept for it
    meeting_restarts: int = 0  # localizations started again from a meeting (no particle agreed, or MCL's pose contradicted it)
    reason: str | None = None  # why the robot is not placed (at the end)

    def report(self, start: float) -> dict:
        """The JSON form, stamps made relative to the run's ``start``, and the delay from the first scan."""
        out = asdict(self)
        placed, first = out.pop("placed_stamp"), out.pop("first_scan_stamp")
        out["placed_s"] = None if placed is None else round(placed - start, 3)
        out["first_scan_s"] = None if first is None else round(first - start, 3)
        if self.placed_stamp is not None and self.first_scan_stamp is not None:
            out["placed_after_first_scan_s"] = round(self.placed_stamp - self.first_scan_stamp, 3)
        elif self.placed_stamp is not None and self.how == "meetings":
            out["placed_after_first_scan_s"] = 0.0  # placed by other robots' detections before its first scan
        return out


class PlacementCheck:
    """Whether a robot MCL placed must be placed again: MCL, localized, has put it farther than ``distance_m`` from
    the filter's pose at the same stamp for ``messages`` poses in a row. MCL's first ``localized`` can be a wrong
    hypothesis of a symmetric map that it later leaves by relocalizing; the filter never sees that on its own, since
    the robot's scans then build its own part of the map where it was put.

    MCL's poses are compared with the filter's poses of the same moment (:meth:`record`, the nearest within
    ``max_skew_s`` of robot time), not with its latest: an MCL service seconds behind a fast replay would otherwise
    find a moving robot metres from where the filter has it now, and have it placed again and again with stale
    poses. An MCL pose with no filter pose that near is not counted either way."""

    def __init__(self, distance_m: float, messages: int, max_skew_s: float = 1.0, history: int = 600):
        self.distance_m = distance_m
        self.messages = messages
        self.max_skew_s = max_skew_s
        self.history = history
        self.runs: dict[str, int] = {}
        self.tracks: dict[str, deque] = {}  # robot → (stamp, (x, y)) of the filter's poses, oldest first

    def record(self, robot_id: str, stamp: float, filter_pose) -> None:
        """The filter's pose of ``robot_id`` at ``stamp`` (kept for the last ``history`` poses)."""
        track = self.tracks.setdefault(robot_id, deque(maxlen=self.history))
        if track and stamp <= track[-1][0]:
            return
        track.append((float(stamp), np.asarray(filter_pose, float)[:2].copy()))

    def filter_at(self, robot_id: str, stamp: float) -> np.ndarray | None:
        """The recorded filter position nearest ``stamp``, or None when none is within ``max_skew_s``."""
        track = self.tracks.get(robot_id)
        if not track:
            return None
        index = bisect.bisect_left(track, stamp, key=lambda item: item[0])
        at, position = min((track[i] for i in (index - 1, index) if 0 <= i < len(track)),
                           key=lambda item: abs(item[0] - stamp))
        return position if abs(at - stamp) <= self.max_skew_s else None

    def observe(self, robot_id: str, stamp: float, mcl_pose) -> bool:
        """Count one localized MCL pose stamped ``stamp``; True (and the count starts again) when the robot must be
        placed again."""
        if self.messages <= 0:
            return False
        there = self.filter_at(robot_id, stamp)
        if there is None:
            return False
        apart = float(np.hypot(*(there - np.asarray(mcl_pose, float)[:2])))
        run = self.runs.get(robot_id, 0) + 1 if apart > self.distance_m else 0
        self.runs[robot_id] = run
        if run < self.messages:
            return False
        self.runs.pop(robot_id)
        return True

    def forget(self, robot_id: str) -> None:
        self.runs.pop(robot_id, None)
        self.tracks.pop(robot_id, None)


class FleetPlacer:
    """Hold back the events of robots the estimator has not placed, anchor the first, localize the others."""

    def __init__(self, estimator, infos: list[RobotInfo], config: MclConfig, use_signatures: bool,
                 map_refresh_s: float = 5.0, meetings: bool = True):
        self.estimator = estimator
        self.use_signatures = use_signatures
        self.meetings = meetings
        self.map_refresh_s = map_refresh_s
        self.min_landmarks = config.map_min(use_signatures)
        self.infos = {info.robot_id: info for info in infos}
        self.localizers = MclFleet(config, use_start_pose=False)  # a robot joins it at its first scan with a map
        self.map_stamp = -np.inf
        self.map_ready = False
        self.prior_map = len(estimator.landmark_map().means) > 0  # a saved map: its frame, no anchor
        self.placements = {info.robot_id: Placement(info.robot_id) for info in infos}
        self.desk = MeetingDesk()
        for info in infos:
            self.desk.add_robot(info)
            if not estimator.is_waiting(info.robot_id):
                self.placements[info.robot_id].how = "start pose"

    def holds(self, event: Event) -> bool:
        """Take the event if its robot waits for a pose (True); False: the estimator should have it."""
        rid = event.robot_id
        if self.meetings and isinstance(event, ScanEvent) and len(event.robot_ids):
            self._meet(event)
        if rid not in self.placements or not self.estimator.is_waiting(rid):
            return False
        record = self.placements[rid]
        if isinstance(event, OdomEvent):
            record.odometry_before += 1
            self.localizers.on_odometry(event)
            self.desk.move(event)
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
        record.mcl_restarts = max(self.localizers.robots[rid].mcl.restarts - 1, 0)
        if not report.localized:
            return self._hold(record, "not localized against the map yet")
        mcl = self.localizers.robots[rid].mcl
        pose, cov = mcl.best()
        if self.meetings and self.desk.contradicts(rid, pose):  # e.g. the twin of a symmetric map
            record.meeting_restarts += 1
            mcl.restart_from(self.desk.latest(rid))
            return self._hold(record, "MCL's pose contradicts the robot's meetings")
        return self._place(record, pose, cov, event.stamp, "mcl")

    def _localizing(self, rid: str) -> bool:
        return rid in self.placements and self.estimator.is_waiting(rid)

    def _placed(self, rid: str) -> bool:
        return rid in self.placements and not self.estimator.is_waiting(rid)

    def _meet(self, event: ScanEvent) -> None:
        """Keep the scan's detections between a robot being localized and a placed robot (the placed robot's pose
        now, from the estimator) for the robot being localized, check its localizer against them, and place it
        when its meetings fix its pose."""
        sightings = self.desk.sightings(event, self._localizing, self._placed)
        if not sightings:
            return
        poses = self.estimator.poses()
        for sighting in sightings:
            subject = sighting.subject
            if not self.estimator.is_waiting(subject):
                continue  # placed by an earlier sighting of this scan
            meeting = self.desk.meeting(sighting, *poses[sighting.other], event.noise_cov)
            record = self.placements[subject]
            record.meetings += 1
            state = self.localizers.robots.get(subject)
            restarted, fix = self.desk.meet(subject, meeting, state.mcl if state is not None else None)
            record.meeting_restarts += int(restarted)
            if fix is not None:
                self._place(record, fix.pose, fix.cov, event.stamp, "meetings")

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

    def report(self, start: float) -> dict:
        """Per robot: how and when it was placed, or why not."""
        return {rid: record.report(start) for rid, record in self.placements.items()}
