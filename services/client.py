"""A robot's link to fleetslam, for anything that is not a fleetslam process: ``RobotLink``.

A robot joins fleetslam by publishing on its own keys (DESIGN §2): its RobotInfo, then odometry and scans. The
link does what ``fleetslam robot`` does for a simulated or replayed robot, and ``fleetslam ros2`` for each ROS 2
robot, so that every robot reaches the services the same way:

- reliable, congestion-control BLOCK publishers; with ``cache`` > 0 advanced ones, whose cache and heartbeats let a
  late, cut-off or restarted service recover what it missed;
- a queryable answering its RobotInfo (a service that joins late asks it) and one answering the odometry and scans
  it kept (a restarted service asks it);
- the liveliness tokens last, so a service that sees them can query at once;
- RobotInfo again while the robot publishes: after ``info_period_s``, then after twice as long each time up to
  ``info_max_period_s`` (a new RobotInfo starts again from ``info_period_s``): services ask for it when they need it,
  so the re-publication is a fallback that should cost the robot's link little;
- optionally, the robot's estimates: its pose from the central FastSLAM, D-SLAM and MCL services
  (:meth:`RobotLink.estimates`).

Sequence numbers and stamps are kept per stream; a message the services would refuse (stamp going backwards,
NaN, wrong shape) is refused here first with a ValueError naming the reason, so a caller learns at once.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

import numpy as np
import zenoh

from schemas.codec import DecodeError, decode, encode
from schemas.config import FleetSettings
from schemas.contract import OdomEvent, ScanEvent, TruthEvent
from schemas.keys import Keys, check_robot_id
from schemas.messages import Estimate, GroundTruth, MclPose, Odometry, PoseEstimate, RobotInfo, Scan
from schemas.transport import (StreamPublisher, answer_history, declare_robot_tokens, open_session, stream_caches,
                               undeclare_all)

log = logging.getLogger("fleetslam.client")

STREAMS = ("info", "odom", "scan", "truth")


class InfoSchedule:
    """When a robot publishes its RobotInfo again: at once the first time, then after ``first_s``, then after twice
    as long each time, up to ``max_s``; :meth:`restart` (a new RobotInfo) starts again from ``first_s``."""

    def __init__(self, first_s: float, max_s: float, clock=time.monotonic):
        self.first_s = first_s
        self.max_s = max(first_s, max_s)
        self.clock = clock
        self.interval_s = first_s
        self.next_at: float | None = None

    def due(self) -> bool:
        return self.next_at is None or self.clock() >= self.next_at

    def published(self) -> None:
        self.next_at = self.clock() + self.interval_s
        self.interval_s = min(2.0 * self.interval_s, self.max_s)

    def restart(self) -> None:
        self.interval_s = self.first_s


@dataclass(frozen=True)
class PoseReport:
    """A pose of this robot as one service estimates it: (x, y, θ), its 3×3 covariance, its stamp, its source."""

    pose: np.ndarray
    cov: np.ndarray
    stamp: float
    source: str


class RobotLink:
    """One robot's streams into fleetslam, and its estimates back (see the module docstring).

    ``caches`` gives the samples each stream's advanced publisher keeps (0: a plain publisher); ``keep`` how many
    odometry and scans the history queryable answers with. ``follow_estimates`` subscribes to the services' poses
    of this robot. ``session`` is used as given and left open; :meth:`connect` opens one the link closes.
    ``info_max_period_s`` and ``heartbeat_s`` (the advanced publishers' heartbeat period; the RobotInfo's
    heartbeats are sporadic: only after a publication) default to the settings ``info_max_period_s`` and
    ``heartbeat_period_s``.
    """

    def __init__(self, session: zenoh.Session, info: RobotInfo, prefix: str = "fleet",
                 caches: dict[str, int] | None = None, keep: int | None = None, info_period_s: float = 1.0,
                 follow_estimates: bool = False, info_max_period_s: float | None = None,
                 heartbeat_s: float | None = None):
        self.session = session
        self.info = info
        self.robot_id = check_robot_id(info.robot_id)
        self.keys = Keys(prefix)
        if info_max_period_s is None:
            info_max_period_s = FleetSettings.model_fields["info_max_period_s"].default
        self.info_schedule = InfoSchedule(info_period_s, info_max_period_s)
        self.counts = {name: 0 for name in STREAMS}
        self._owns_session = False
        self._last_stamp: dict[str, float] = {}
        self._estimates: dict[str, PoseReport] = {}
        self._estimates_lock = threading.Lock()
        caches = {name: 64 for name in STREAMS} | (caches or {})
        self._info_payload = encode(info)
        self.publishers = {name: StreamPublisher(session, self.keys.robot(self.robot_id, name), cache=caches[name],
                                                 keep=(caches[name] if keep is None else keep)
                                                 if name in ("odom", "scan") else 0,
                                                 heartbeat_s=heartbeat_s, sporadic=name == "info")
                           for name in STREAMS}
        self._entities: list = [
            session.declare_queryable(self.keys.info(self.robot_id), self._answer_info),
            answer_history(session, self.keys.history(self.robot_id), [self.publishers["odom"], self.publishers["scan"]]),
        ]
        if follow_estimates:
            self._entities += [
                session.declare_subscriber(self.keys.central_estimate, self._on_central),
                session.declare_subscriber(self.keys.dslam_pose(self.robot_id), self._on_pose("dslam", PoseEstimate)),
                session.declare_subscriber(self.keys.mcl_pose(self.robot_id), self._on_pose("mcl", MclPose)),
            ]
        self._entities += declare_robot_tokens(session, self.keys, self.robot_id)  # last: alive means it answers

    @classmethod
    def connect(cls, info: RobotInfo, settings: FleetSettings | None = None, follow_estimates: bool = True,
                **options) -> "RobotLink":
        """A link over a session of its own, to the router ``settings`` name (default: the ``FLEETSLAM_*``
        environment, else ``tcp/127.0.0.1:7447``); the link closes that session."""
        settings = settings or FleetSettings()
        rates = {"info": 1.0, "odom": info.odom_rate_hz, "scan": info.scan_rate_hz, "truth": info.odom_rate_hz}
        caches = stream_caches(settings, rates)
        options = {"info_max_period_s": settings.info_max_period_s, "heartbeat_s": settings.heartbeat_period_s,
                   **options}
        session = open_session(settings)
        try:
            link = cls(session, info, settings.prefix, caches=caches, follow_estimates=follow_estimates, **options)
        except BaseException:
            session.close()
            raise
        link._owns_session = True
        return link

    # ------------------------------------------------------------------ publishing
    def publish_info(self, info: RobotInfo | None = None) -> None:
        """Publish the RobotInfo now (a new one replaces the old for queries too, and the re-publication starts
        again from ``info_period_s``); then again after each period, doubled each time up to
        ``info_max_period_s``."""
        if info is not None:
            if info.robot_id != self.robot_id:
                raise ValueError(f"bad_robot_id: this link is robot {self.robot_id!r}, not {info.robot_id!r}")
            self.info, self._info_payload = info, encode(info)
            self.info_schedule.restart()
        self.publishers["info"].put(self._info_payload)
        self.counts["info"] += 1
        self.info_schedule.published()

    def odometry(self, dt: float, control, control_cov, stamp: float | None = None) -> Odometry:
        """Publish one control ``(v, ω)`` (unicycle) or ``(speed, steering)`` (Ackermann) applied over ``dt`` s and
        ending at ``stamp`` (default: now, in seconds since the epoch), with its 2×2 covariance."""
        message = Odometry(robot_id=self.robot_id, seq=self.counts["odom"], stamp=self._stamp("odom", stamp), dt=dt,
                           control=np.asarray(control, float), control_cov=np.asarray(control_cov, float))
        self._put("odom", message)
        return message

    def scan(self, ranges, bearings, noise_cov=None, stamp: float | None = None, landmark_ids=None) -> Scan:
        """Publish one scan's landmark detections: ranges (m) from the sensor and bearings (rad) in the body frame
        (DESIGN §3), with their 2×2 covariance (default: the sensor's in RobotInfo)."""
        noise_cov = self.info.sensor.noise_cov if noise_cov is None else np.asarray(noise_cov, float)
        message = Scan(robot_id=self.robot_id, seq=self.counts["scan"], stamp=self._stamp("scan", stamp),
                       ranges=np.asarray(ranges, float), bearings=np.asarray(bearings, float),
                       landmark_ids=None if landmark_ids is None else np.asarray(landmark_ids, np.int64),
                       noise_cov=noise_cov)
        self._put("scan", message)
        return message

    def truth(self, pose, stamp: float | None = None) -> GroundTruth:
        """Publish a true pose (a simulation's, or a motion-capture system's), for the evaluator."""
        event = TruthEvent(self.robot_id, self.counts["truth"], self._stamp("truth", stamp), np.asarray(pose, float))
        message = event.to_message()
        self._put("truth", message)
        return message

    def put_event(self, event: OdomEvent | ScanEvent | TruthEvent, with_ids: bool = True) -> None:
        """Publish an event of a :class:`~robots.dataset.RobotLog` as it is (its own seq and stamp)."""
        self._put(*self._event_message(event, with_ids))

    def put_events(self, events, with_ids: bool = True) -> None:
        """Publish events of one instant (odometry and the scan taken with it) back to back: every message is built
        and encoded before the first is put, so that they leave within microseconds and share Zenoh batches, and
        packets on the links, more often than when each is built between two puts."""
        ready = [(stream, message, encode(message))
                 for stream, message in (self._event_message(event, with_ids) for event in events)]
        for stream, message, payload in ready:
            self._put(stream, message, payload)

    @staticmethod
    def _event_message(event: OdomEvent | ScanEvent | TruthEvent, with_ids: bool) -> tuple[str, object]:
        if isinstance(event, OdomEvent):
            return "odom", event.to_message()
        if isinstance(event, ScanEvent):
            return "scan", event.to_message(with_ids=with_ids)
        return "truth", event.to_message()

    def _stamp(self, stream: str, stamp: float | None) -> float:
        stamp = time.time() if stamp is None else float(stamp)
        last = self._last_stamp.get(stream)
        if last is not None and stamp < last:
            raise ValueError(f"time_backwards: {stream} stamp {stamp:.6f} is before the last one, {last:.6f}")
        return stamp

    def _put(self, stream: str, message: Odometry | Scan | GroundTruth, payload: bytes | None = None) -> None:
        if self.info_schedule.due():
            self.publish_info()
        self.publishers[stream].put(message, payload)
        self.counts[stream] += 1
        self._last_stamp[stream] = message.stamp

    def _answer_info(self, query: zenoh.Query) -> None:
        query.reply(self.keys.info(self.robot_id), self._info_payload)

    # ------------------------------------------------------------------ estimates
    def estimates(self) -> dict[str, PoseReport]:
        """The latest pose of this robot from each service that has one: ``central``, ``dslam``, ``mcl``
        (empty until a service has fused the robot; needs ``follow_estimates``)."""
        with self._estimates_lock:
            return dict(self._estimates)

    def wait_for_estimate(self, source: str = "central", timeout_s: float = 30.0,
                          at_least: float | None = None) -> PoseReport | None:
        """The latest estimate from ``source`` once there is one (stamped at ``at_least`` or later, if given: the
        service has fused the robot up to then), waiting at most ``timeout_s``; None if none came."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            report = self.estimates().get(source)
            if report is not None and (at_least is None or report.stamp >= at_least - 1e-9):
                return report
            time.sleep(0.05)
        return None

    def _keep(self, source: str, report: PoseReport) -> None:
        with self._estimates_lock:
            self._estimates[source] = report

    def _on_central(self, sample: zenoh.Sample) -> None:
        try:
            estimate = decode(sample.payload.to_bytes(), Estimate)
        except DecodeError as error:
            log.debug("central estimate not decoded: %s", error)
            return
        for robot in estimate.robots:
            if robot.robot_id == self.robot_id:
                self._keep("central", PoseReport(robot.pose, robot.cov, robot.stamp, estimate.method or "central"))

    def _on_pose(self, source: str, kind: type[PoseEstimate] | type[MclPose]):
        def callback(sample: zenoh.Sample) -> None:
            try:
                message = decode(sample.payload.to_bytes(), kind)
            except DecodeError as error:
                log.debug("%s pose not decoded: %s", source, error)
                return
            if message.robot_id != self.robot_id:
                return
            if isinstance(message, MclPose):
                if message.localized:
                    self._keep(source, PoseReport(message.best_pose, message.best_cov, message.stamp, source))
            else:
                self._keep(source, PoseReport(message.pose, message.cov, message.stamp, source))
        return callback

    # ------------------------------------------------------------------ closing
    def close(self) -> None:
        """Undeclare everything (tokens first: the robot is gone), and close the session if the link opened it."""
        undeclare_all([*reversed(self._entities), *self.publishers.values()])
        self._entities = []
        if self._owns_session:
            try:
                self.session.close()
            except Exception:  # noqa: BLE001 - closing after a lost link must not mask the caller's error
                log.debug("session close failed", exc_info=True)

    def __enter__(self) -> "RobotLink":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
