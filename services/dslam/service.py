"""``fleetslam dslam``: the D-SLAM map service (paper 003) over Zenoh.

Subscribes every robot (liveliness ``{prefix}/robots/*/alive``, info, odom and
scan), localises each robot, associates each scan (known ids, or by querying
``{prefix}/assoc/{method}`` with a timeout; while the queryable is unreachable
the failure is counted and the in-process ``associate`` answers, for
``assoc_retry_s`` before the service is asked again, so the stream never
waits on it), and fuses every robot's z_map into one map. Publishes
``MapEstimate`` on ``{prefix}/dslam/map`` every ``map_period_s`` (landmark
means, marginal covariances of the landmarks near the robots, information
matrix nnz, recovery iterations) and ``PoseEstimate`` on
``{prefix}/dslam/pose/{rid}`` after each scan. Stats on ``{prefix}/dslam/stats``
carry the core's figures in ``extra``.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import time
from collections import Counter, deque

import numpy as np
import zenoh

from robots.dataset import OdomEvent, ScanEvent
from schemas.association import AssociationReply, AssociationRequest
from schemas.codec import DecodeError, decode
from schemas.config import DslamSettings, add_settings_arguments, settings_from_args
from schemas.messages import MapEstimate, Odometry, PoseEstimate, RobotInfo, Scan
from schemas.streams import StreamTracker, Verdict
from schemas.transport import StreamPublisher
from services.association.client import AssociationClient, AssociationRefused
from services.dslam.estimator import DSlam, in_process_associate
from services.runtime import ServiceShell

log = logging.getLogger(__name__)


class DslamService(ServiceShell):
    """One D-SLAM map fed by every robot of the fleet."""

    name = "dslam"

    def __init__(self, settings: DslamSettings, instance: str | None = None):
        super().__init__(settings, instance)
        self.settings: DslamSettings = settings
        self.tick_period_s = settings.map_period_s
        self.core = DSlam(settings, associator=self.associate)
        self.tracker = StreamTracker()
        self.assoc_counts: Counter = Counter()
        self.alive: dict[str, bool] = {}
        self._client: AssociationClient | None = None
        self._remote_down_until = 0.0
        self._pose_pubs: dict[str, StreamPublisher] = {}
        self._pose_seq: Counter = Counter()
        self._map_seq = 0
        self._info_asked: dict[str, float] = {}
        self._waiting: dict[str, deque] = {}
        self.extra_counts: Counter = Counter()
        self._lock = asyncio.Lock()

    def setup(self, session: zenoh.Session) -> None:
        for stream in ("info", "odom", "scan"):
            self.subscribe(self.keys.all_robot_stream(stream), stream)
        self._declared.append(session.liveliness().declare_subscriber(self.keys.alive_any, self._on_alive, history=True))
        self._map_pub = self.publisher(self.keys.dslam_map)
        self._client = AssociationClient(session, self.keys, self.settings.assoc_timeout_s)

    def _on_alive(self, sample: zenoh.Sample) -> None:
        self.enqueue("alive" if sample.kind == zenoh.SampleKind.PUT else "gone", str(sample.key_expr), b"")

    # ------------------------------------------------------------ association
    def associate(self, request: AssociationRequest, method: str) -> AssociationReply:
        """Ask the queryable (bounded wait); on failure count it and associate in-process for a while."""
        now = time.monotonic()
        if self._client is not None and now >= self._remote_down_until:
            try:
                reply = self._client.associate(method, request)
                self.assoc_counts["assoc_remote"] += 1
                return reply
            except TimeoutError:
                self.assoc_counts["assoc_unreachable"] += 1
            except AssociationRefused as exc:
                self.assoc_counts[f"assoc_refused_{exc.reason}"] += 1
            except DecodeError:
                self.assoc_counts["assoc_bad_reply"] += 1
            self._remote_down_until = now + self.settings.assoc_retry_s
        self.assoc_counts["assoc_in_process"] += 1
        return in_process_associate(request, method)

    # ---------------------------------------------------------------- streams
    async def handle(self, tag: str, key: str, payload: bytes) -> None:
        parsed = self.keys.parse_robot_key(key)
        if parsed is None:
            self.reject("bad_key", key)
            return
        rid, _ = parsed
        if tag == "alive":
            self.alive[rid] = True
            if rid not in self.core.robots:
                self._info_asked[rid] = time.monotonic()
                asyncio.get_running_loop().create_task(self._ask_info(rid))
        elif tag == "gone":
            self.alive[rid] = False  # its last messages may still be on the way: they are used
            self.tracker.leave(rid)
            log.info("robot %s left (liveliness lost); its map contributions stay", rid)
        elif tag == "info":
            await self._take_info(rid, decode(payload, RobotInfo))
        elif tag in ("odom", "scan"):
            message = decode(payload, Odometry if tag == "odom" else Scan)
            if message.robot_id != rid:
                self.reject("robot_id_mismatch", f"{message.robot_id} on {rid}'s key")
            elif self.tracker.new_run(rid, tag, message.seq):
                self._restart(rid)
                self._wait_for_info(rid, tag, message)
            elif rid not in self.core.robots:
                self._wait_for_info(rid, tag, message)
            else:
                await self._process(rid, tag, message)

    def _restart(self, rid: str) -> None:
        """A robot that left is back with a new run (its streams start again at seq 0): its old pose and order
        state no longer apply, its RobotInfo says where it starts. (A robot back after a link cut goes on with
        its seq numbers and keeps its state.)"""
        log.info("robot %s started a new run; it rejoins from its RobotInfo", rid)
        self.core.robots.pop(rid, None)
        self._waiting.pop(rid, None)
        self._info_asked.pop(rid, None)
        self.extra_counts["robot_restarts"] += 1

    async def _take_info(self, rid: str, info: RobotInfo) -> None:
        if info.robot_id != rid:
            self.reject("robot_id_mismatch", f"{info.robot_id} on {rid}'s key")
            return
        if rid not in self.core.robots:
            self.core.add_robot(info)
            log.info("robot %s joined (%s, start pose %s)", rid, info.source, "known" if info.start_pose is not None else "unknown")
            for tag, message in self._waiting.pop(rid, ()):
                await self._process(rid, tag, message)

    def _wait_for_info(self, rid: str, tag: str, message) -> None:
        """Keep a robot's messages until its RobotInfo arrives (asked for at once); the oldest go past the limit."""
        waiting = self._waiting.setdefault(rid, deque(maxlen=self.settings.waiting_messages))
        if len(waiting) == waiting.maxlen:
            self.reject("no_robot_info", rid)
        waiting.append((tag, message))
        asked = self._info_asked.get(rid, -np.inf)
        if time.monotonic() - asked > 2.0:
            self._info_asked[rid] = time.monotonic()
            asyncio.get_running_loop().create_task(self._ask_info(rid))

    async def _process(self, rid: str, tag: str, message) -> None:
        """Order check, then the core: odometry in the loop, scans in a worker thread (the map lock held)."""
        verdict = self.tracker.check(rid, tag, message.seq, message.stamp)
        if verdict != Verdict.ACCEPT:
            self.reject(verdict.value, f"{rid}/{tag} seq {message.seq}")
            return
        if tag == "odom":
            self.core.on_odometry(OdomEvent(rid, message.seq, message.stamp, message.dt, message.control,
                                            message.control_cov))
            return
        async with self._lock:
            await asyncio.to_thread(self.core.on_scan, ScanEvent.from_message(message))
        self._publish_pose(rid, message.stamp)
        self.extra = self._extra()  # here, in the loop, while no worker thread touches the core

    async def _ask_info(self, rid: str) -> None:
        """Query a robot's RobotInfo (a robot answers late joiners) and queue what comes back."""
        session = self.session

        def query() -> list[bytes]:
            return [r.ok.payload.to_bytes() for r in session.get(self.keys.info(rid), timeout=2.0) if r.ok is not None]

        try:
            for payload in await asyncio.to_thread(query):
                self.enqueue("info", self.keys.info(rid), payload)
        except zenoh.ZError as exc:
            log.debug("info query for %s failed: %s", rid, exc)

    # ------------------------------------------------------------- publishing
    def _publish_pose(self, rid: str, stamp: float) -> None:
        robot = self.core.robots.get(rid)
        if robot is None or robot.pose is None:
            return
        pub = self._pose_pubs.get(rid)
        if pub is None:
            pub = self._pose_pubs[rid] = self.publisher(self.keys.dslam_pose(rid))
        cov = 0.5 * (robot.cov + robot.cov.T)
        pub.put(PoseEstimate(robot_id=rid, seq=self._pose_seq[rid], stamp=stamp, pose=robot.pose, cov=cov, source="dslam"))
        self._pose_seq[rid] += 1
        self.published += 1

    def map_message(self) -> MapEstimate:
        """The map: every landmark mean, the marginal covariances of the landmarks near the robots."""
        core = self.core
        ids = np.asarray(core.ids, np.int64)
        near, covs = core.map.cached_marginals()
        stamps = [r.stamp for r in core.robots.values() if np.isfinite(r.stamp)]
        return MapEstimate(
            seq=self._map_seq, stamp=max(stamps) if stamps else 0.0, landmarks=core.map.means.copy(), landmark_ids=ids,
            covariance_ids=ids[near] if near.size else np.zeros(0, np.int64), covariances=covs,
            info_nnz=core.map.matrix.nnz, recovery_iterations=core.map.recovery_iterations,
        )

    async def tick(self) -> None:
        async with self._lock:
            message = self.map_message()
            self.extra = self._extra()
        self._map_pub.put(message)
        self._map_seq += 1
        self.published += 1

    def _extra(self) -> dict[str, float]:
        return {**self.core.stats(), **{k: float(v) for k, v in (self.assoc_counts + self.extra_counts).items()},
                "robots_alive": float(sum(self.alive.values())), "missing": float(self.tracker.missing()),
                "waiting_for_info": float(sum(len(w) for w in self._waiting.values()))}

    def on_stop(self) -> None:
        self._map_pub.put(self.map_message())
        self.published += 1
        self.extra = self._extra()
        if self._client is not None:
            self._client.close()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, DslamSettings)


def main(args: argparse.Namespace) -> int:
    return DslamService(settings_from_args(DslamSettings, args)).serve()
