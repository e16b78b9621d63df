"""``fleetslam central``: the central multi-robot FastSLAM service (the centralised scheme of Howard,
"Multi-robot simultaneous localization and mapping using particle filters").

Robots are found by their liveliness tokens (``{prefix}/robots/*/alive``) and
their RobotInfo (published periodically, and asked for by a query when a token
appears). Every robot's odometry and scans go into one filter
(:class:`central.fastslam.FastSlam`):

- Each stream is checked by a :class:`~schemas.streams.StreamTracker` on
  arrival (gaps counted, duplicates / out-of-order / time going backwards
  rejected), so nothing reaches the filter out of order within a robot.
- Across robots, messages wait in a reorder buffer at most
  ``reorder_window_s`` (wall time) and are released in stamp order once every
  live robot's stream has passed their stamp.
- Messages of a robot whose RobotInfo has not arrived, or whose start pose is
  unknown, are kept (at most ``waiting_messages``, the excess counted). Such a
  robot is placed on the first ``{prefix}/mcl/{rid}/pose`` (MclPose) with
  ``localized`` true, at its best pose and covariance; its kept messages older
  than that pose are dropped (counted), the rest processed.
- A robot whose first odometry message arrives with seq > 0 (the service
  started after it) has lost its start pose: counted, and with ``late_join``
  = ``wait`` it waits for MCL like a robot without a start pose.
- Robot-to-robot detections in scans are ignored unless ``robot_detections``
  is on (they then weight particles; they never update the map).

The estimate (every placed robot's weighted mean pose and covariance, the
map) is published on ``{prefix}/central/estimate`` at ``estimate_rate_hz``;
the queryable ``{prefix}/central/state`` answers with a fresh one.
"""

from __future__ import annotations

import argparse
import heapq
import itertools
import logging
import time
from collections import defaultdict, deque

import numpy as np
import zenoh

from central.fastslam import FastSlam, FastSlamConfig
from schemas.contract import OdomEvent, ScanEvent
from schemas.codec import decode, encode
from schemas.config import CentralSettings, add_settings_arguments, settings_from_args
from schemas.messages import Estimate, MclPose, Odometry, RobotEstimate, RobotInfo, Scan
from schemas.streams import StreamTracker, Verdict
from services.runtime import ServiceShell

log = logging.getLogger("fleetslam.central")


class CentralService(ServiceShell):
    """Decode, order, feed the filter, publish estimates and answer state queries."""

    name = "central"

    def __init__(self, settings: CentralSettings, instance: str | None = None):
        super().__init__(settings, instance)
        self.settings: CentralSettings = settings
        self.tick_period_s = 1.0 / settings.estimate_rate_hz
        self.slam = FastSlam(settings.core(FastSlamConfig))
        self.tracker = StreamTracker()
        self.alive: set[str] = set()
        self.asked: set[str] = set()
        self.latest: dict[str, float] = {}  # robot -> newest stamp received
        self.waiting: dict[str, deque] = defaultdict(lambda: deque(maxlen=settings.waiting_messages))
        self.buffer: list = []  # heap of (stamp, order, arrival, event)
        self.order = itertools.count()
        self.processed: dict[str, int] = defaultdict(int)
        self.hold_ms: deque[float] = deque(maxlen=5000)
        self.compute_ms: deque[float] = deque(maxlen=5000)
        self.estimate_seq = 0
        self.last_stamp = 0.0

    # ------------------------------------------------------------ wiring
    def setup(self, session: zenoh.Session) -> None:
        self.subscribe(self.keys.all_robot_stream("info"), "info", recover=False)
        self.subscribe(self.keys.all_robot_stream("odom"), "odom")
        self.subscribe(self.keys.all_robot_stream("scan"), "scan")
        self.subscribe(f"{self.settings.prefix}/mcl/*/pose", "mcl", recover=False)
        self._estimate_pub = self.publisher(self.keys.central_estimate)
        self._declared.append(session.liveliness().declare_subscriber(self.keys.alive_any, self._on_token, history=True))
        self._declared.append(session.declare_queryable(self.keys.central_state,
                                                        lambda query: self.enqueue("state", self.keys.central_state, query)))

    def _on_token(self, sample: zenoh.Sample) -> None:
        tag = "alive" if sample.kind == zenoh.SampleKind.PUT else "gone"
        self.enqueue(tag, str(sample.key_expr), b"")

    def _ask_info(self, robot_id: str) -> None:
        """Query a robot's RobotInfo (it answers late joiners); replies come back through the queue."""
        assert self.session is not None
        self.asked.add(robot_id)

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is not None:
                self.enqueue("info", str(reply.ok.key_expr), reply.ok.payload.to_bytes())

        self.session.get(self.keys.info(robot_id), on_reply, timeout=5.0)

    # ------------------------------------------------------------ handling
    async def handle(self, tag: str, key: str, payload) -> None:
        if tag == "state":
            self._answer_state(payload)
            return
        if tag in ("alive", "gone"):
            self._on_liveliness(tag, key)
            return
        parsed = self.keys.parse_robot_key(key) if tag != "mcl" else None
        if tag == "info":
            self._on_info(decode(payload, RobotInfo), parsed)
        elif tag == "mcl":
            self._on_mcl(decode(payload, MclPose), key)
        elif tag in ("odom", "scan"):
            message = decode(payload, Odometry if tag == "odom" else Scan)
            if parsed is None or parsed[0] != message.robot_id:
                self.reject("robot_id_mismatch", f"{message.robot_id} on {key}")
                return
            self._on_stream(tag, message)
        self._release(flush=False)

    def _on_liveliness(self, tag: str, key: str) -> None:
        parsed = self.keys.parse_robot_key(key)
        if parsed is None:
            return
        robot_id = parsed[0]
        if tag == "alive":
            self.alive.add(robot_id)
            if not self.slam.has_robot(robot_id) and not self.slam.is_waiting(robot_id) and robot_id not in self.asked:
                self._ask_info(robot_id)
        else:
            self.alive.discard(robot_id)
            self.tracker.leave(robot_id)
            self.extra["robots_lost"] = self.extra.get("robots_lost", 0.0) + 1.0
            self._release(flush=False)

    def _on_info(self, info: RobotInfo, parsed) -> None:
        if parsed is not None and parsed[0] != info.robot_id:
            self.reject("robot_id_mismatch", f"{info.robot_id} on info of {parsed[0]}")
            return
        rid = info.robot_id
        if self.slam.has_robot(rid) or self.slam.is_waiting(rid):
            return
        placed = self.slam.add_robot(info)
        log.info("robot %s joined (%s)", rid, "placed" if placed else "waiting for a pose from MCL")
        if placed:
            self._requeue(rid, after=None)

    def _on_mcl(self, message: MclPose, key: str) -> None:
        rid = message.robot_id
        if key != self.keys.mcl_pose(rid):
            self.reject("robot_id_mismatch", f"{rid} on {key}")
            return
        if not self.slam.is_waiting(rid) or not message.localized:
            return
        if self.slam.place_robot(rid, message.best_pose, message.best_cov, stamp=message.stamp):
            log.info("robot %s placed by MCL at %s", rid, np.round(message.best_pose, 3).tolist())
            self._requeue(rid, after=message.stamp)
        else:
            self.reject("bad_placement", f"MCL pose of {rid}")

    def _on_stream(self, stream: str, message) -> None:
        rid = message.robot_id
        if self.tracker.new_run(rid, stream, message.seq):
            self._restart(rid)
        verdict = self.tracker.check(rid, stream, message.seq, message.stamp)
        if verdict is not Verdict.ACCEPT:
            self.reject(verdict.value, f"{rid}/{stream} seq {message.seq}")
            return
        self.latest[rid] = max(self.latest.get(rid, -np.inf), message.stamp)
        if stream == "odom" and self.tracker.received(rid, "odom") == 1 and message.seq > 0:
            self._joined_late(rid, message.seq)
        event = OdomEvent.from_message(message) if stream == "odom" else ScanEvent.from_message(message)
        if not self.slam.has_robot(rid):
            queue = self.waiting[rid]
            if len(queue) == queue.maxlen:
                self.reject("waiting_overflow", f"{rid} has no RobotInfo or no pose yet")
            queue.append(event)
            if not self.slam.is_waiting(rid) and rid not in self.asked and self.session is not None:
                self._ask_info(rid)
            return
        heapq.heappush(self.buffer, (event.stamp, next(self.order), time.perf_counter(), event))

    def _restart(self, robot_id: str) -> None:
        """A robot that left is back with a new run (its streams start again at seq 0): it leaves the filter
        (its landmarks stay) and rejoins from its RobotInfo. A robot back after a link cut goes on with its
        seq numbers and keeps its place."""
        log.info("robot %s started a new run; it rejoins from its RobotInfo", robot_id)
        self.slam.remove_robot(robot_id)
        self.waiting.pop(robot_id, None)
        self.asked.discard(robot_id)
        self.latest.pop(robot_id, None)
        self.buffer = [entry for entry in self.buffer if entry[3].robot_id != robot_id]
        heapq.heapify(self.buffer)
        self.extra["robot_restarts"] = self.extra.get("robot_restarts", 0.0) + 1.0

    def _joined_late(self, robot_id: str, missed: int) -> None:
        """The first odometry of a robot arrived with seq > 0: its start pose no longer says where it is.

        With ``late_join`` = ``wait`` it is taken out (or kept out) of the filter until MCL places it;
        with ``start_pose`` it keeps its announced start pose (counted; the map may suffer).
        """
        self.extra["robots_joined_late"] = self.extra.get("robots_joined_late", 0.0) + 1.0
        log.warning("robot %s: its first %d odometry messages were missed", robot_id, missed)
        if self.settings.late_join == "wait" and not self.slam.is_waiting(robot_id):
            info = self.slam.unplace(robot_id)
            if info is not None:
                log.info("robot %s waits for a pose from MCL", robot_id)

    def _requeue(self, robot_id: str, after: float | None) -> None:
        """Move a robot's waiting messages into the reorder buffer (those not after ``after`` are dropped)."""
        for event in self.waiting.pop(robot_id, ()):
            if after is not None and event.stamp <= after:
                self.reject("before_placement")
                continue
            heapq.heappush(self.buffer, (event.stamp, next(self.order), time.perf_counter(), event))

    def _release(self, flush: bool) -> None:
        """Process buffered messages in stamp order: those every live robot's stream has passed, and any that
        waited longer than the reorder window (all of them when ``flush``)."""
        live = [self.latest[rid] for rid in self.alive if rid in self.latest and self.slam.has_robot(rid)]
        watermark = min(live) if live else np.inf
        deadline = time.perf_counter() - self.settings.reorder_window_s
        while self.buffer:
            stamp, _, arrived, event = self.buffer[0]
            if not (flush or stamp <= watermark or arrived <= deadline or self.settings.reorder_window_s == 0):
                break
            heapq.heappop(self.buffer)
            started = time.perf_counter()
            self.hold_ms.append((started - arrived) * 1e3)
            accepted = self.slam.on_odometry(event) if isinstance(event, OdomEvent) else self.slam.on_scan(event)
            self.compute_ms.append((time.perf_counter() - started) * 1e3)
            if accepted:
                self.processed[event.robot_id] += 1
                self.last_stamp = max(self.last_stamp, event.stamp)

    # ------------------------------------------------------------ output
    def estimate(self, publish: bool = True) -> Estimate | None:
        """The current estimate as a message (None when a number is not finite: never published).

        Published estimates are numbered 0, 1, 2...; a state query's reply repeats the next number.
        """
        robots = []
        for rid, (pose, cov) in self.slam.poses().items():
            stamp = self.slam.pose_stamp(rid)
            stamp = stamp if stamp is not None else self.last_stamp
            robots.append(RobotEstimate(robot_id=rid, stamp=stamp, pose=pose, cov=0.5 * (cov + cov.T)))
        view = self.slam.landmark_map()
        values = [view.means, view.covs] + [r.pose for r in robots] + [r.cov for r in robots]
        if not all(np.all(np.isfinite(v)) for v in values):
            self.reject("estimate_not_finite")
            return None
        message = Estimate(seq=self.estimate_seq, stamp=self.last_stamp, robots=robots, landmarks=view.means,
                           landmark_covs=view.covs, landmark_ids=view.ids, particles=self.slam.particle_count,
                           effective_particles=self.slam.effective_particles(),
                           method=f"fastslam-{self.slam.config.association}")
        self.estimate_seq += int(publish)
        return message

    def _answer_state(self, query: zenoh.Query) -> None:
        try:
            message = self.estimate(publish=False)
            if message is None:
                query.reply_err(b"estimate_not_finite")
            else:
                query.reply(self.keys.central_state, encode(message))
        finally:
            query.drop()

    def _update_stats(self) -> None:
        self.extra.update({k: v for k, v in self.slam.stats().items()})
        self.extra["missing"] = float(self.tracker.missing())
        self.extra["buffered"] = float(len(self.buffer))
        self.extra["waiting"] = float(sum(len(q) for q in self.waiting.values()))
        self.extra["processed"] = float(sum(self.processed.values()))
        for name, values in (("hold_ms", self.hold_ms), ("compute_ms", self.compute_ms)):
            if values:
                array = np.asarray(values)
                self.extra[f"{name}_median"] = float(np.median(array))
                self.extra[f"{name}_p99"] = float(np.percentile(array, 99))

    async def tick(self) -> None:
        self._release(flush=False)
        self._update_stats()
        if not self.slam.poses():
            return
        message = self.estimate()
        if message is not None:
            self._estimate_pub.put(message)
            self.published += 1

    def on_stop(self) -> None:
        self._release(flush=True)
        self._update_stats()
        if self.slam.poses():
            message = self.estimate()
            if message is not None:
                self._estimate_pub.put(message)
                self.published += 1
        log.info("central: processed %s; rejected %s", dict(self.processed), dict(self.rejected))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, CentralSettings)


def main(args: argparse.Namespace) -> int:
    settings = settings_from_args(CentralSettings, args)
    try:
        service = CentralService(settings)
    except ValueError as exc:  # a SettingsError too
        log.error("bad settings: %s", exc)
        return 2
    return service.serve()

