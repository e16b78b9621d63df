"""``fleetslam dslam``: the D-SLAM map service over Zenoh (Wang, Huang, Dissanayake,
"Implementation Issues and Experimental Evaluation of D-SLAM"; the filter is :mod:`services.dslam.core`).

Follows every robot through the shared roster (:meth:`ServiceShell.follow_robots`:
liveliness, RobotInfo, odometry and scans, new runs), localizes each robot, associates each scan (known ids, or by querying
``{prefix}/assoc/{method}`` with a timeout; while the queryable is unreachable
the failure is counted and the in-process ``associate`` answers, for
``assoc_retry_s`` before the service is asked again, so the stream never
waits on it), and fuses every robot's z_map into one map. Between scans a worker
thread solves the covariance columns of the landmarks the robots are about to see
(:meth:`DSlam.column_prefetch`), so that a large map's first sighting of them does
not stall a scan (10^5 landmarks: about 160 ms a column). Publishes
``MapEstimate`` on ``{prefix}/dslam/map`` every ``map_period_s`` (landmark
means by the tiles that changed, :mod:`schemas.maptiles`; marginal covariances of the landmarks near the robots,
information matrix nnz, recovery iterations; the queryable ``{prefix}/dslam/state`` answers with a full map) and ``PoseEstimate`` on
``{prefix}/dslam/pose/{rid}`` after each scan. Stats on ``{prefix}/dslam/stats``
carry the core's figures in ``extra``.

Robots without a start pose (as ``fleetslam central`` does): when no robot has been placed ``anchor_after_s``
after the first of them was announced, it anchors the world frame at the origin (``anchor_first``; its map starts
as from a known start pose, phase I). The others are placed by ``{prefix}/mcl/{rid}/pose`` (MclPose) once it
says ``localized`` (the MCL service localizes against this map by default), each starting as from a known start
pose with that covariance (``placement_bootstrap``; off: widened by ``placement_floor``); without landmark ids
their events wait in the roster until then, and those older than the MCL pose are dropped (counted). With
landmark ids a robot also places itself, from a scan that sees two mapped landmarks, whichever comes first.

With ``map`` (``--map FILE``, :mod:`schemas.mapfile`) the map starts from a saved one, its landmarks entered
as prior information (:meth:`DSlam.load_landmarks`) and published from the first tick; no robot anchors a frame,
and a robot without a start pose is placed against that map as above. With ``map_out`` the map is saved
(atomically) every ``map_out_period_s`` and on exit.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import time
from collections import Counter

import numpy as np
import zenoh

from schemas.association import AssociationReply, AssociationRequest
from schemas.codec import DecodeError, encode
from schemas.config import DslamSettings, add_settings_arguments, settings_from_args
from schemas.contract import OdomEvent
from schemas.maptiles import TileSender
from schemas.messages import MapEstimate, MclPose, PoseEstimate, RobotInfo
from schemas.transport import StreamPublisher
from services.association.client import AssociationClient, AssociationRefused
from services.dslam.config import DslamConfig
from services.dslam.core import DSlam, in_process_associate
from services.mapfeed import StateQueries
from services.maps import MapSaver, seed_from_file, serve_mapping_service
from services.placement import anchor_due
from services.runtime import ServiceShell

log = logging.getLogger(__name__)


class DslamService(ServiceShell):
    """One D-SLAM map fed by every robot of the fleet."""

    name = "dslam"
    uses_kernels = ("association",)  # JCBB when it associates in-process

    def __init__(self, settings: DslamSettings, instance: str | None = None):
        super().__init__(settings, instance)
        self.settings: DslamSettings = settings
        self.tick_period_s = settings.map_period_s
        self.core = DSlam(settings.core(DslamConfig), associator=self.associate)
        self.core.prefetching = settings.column_prefetch_margin > 0  # its worker thread solves columns between scans
        self.assoc_counts: Counter = Counter()
        self._client: AssociationClient | None = None
        self._remote_down_until = 0.0
        self._pose_pubs: dict[str, StreamPublisher] = {}
        self._pose_seq: Counter = Counter()
        self._map_seq = 0
        self.map_tiles = TileSender(settings.map_tile_m, settings.map_tolerance_m, settings.map_cov_tolerance)
        self.state_queries = StateQueries(self, self.keys.dslam_state, settings.max_state_queries)
        self._lock = asyncio.Lock()
        self._prefetch: asyncio.Task | None = None  # the covariance columns being solved between scans
        self.waiting: dict[str, float] = {}  # robots announced without a pose: when (wall clock)
        seed_from_file(self.core, settings.map, self.core.config.association)
        self.map_saver = MapSaver(settings.map_out, {"estimator": "dslam", "association": self.core.config.association,
                                                     "service": "dslam", "from_map": settings.map},
                                  settings.map_out_period_s)

    def setup(self, session: zenoh.Session) -> None:
        self.follow_robots()
        self.subscribe(f"{self.settings.prefix}/mcl/*/pose", "mcl", recover=False)
        self._map_pub = self.publisher(self.keys.dslam_map)
        self.state_queries.declare(session)
        self._client = AssociationClient(session, self.keys, self.settings.assoc_timeout_s)

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

    # ---------------------------------------------------------------- robots
    async def robot_announced(self, info: RobotInfo) -> None:
        """Into the core; a robot without a start pose waits to anchor the frame or for MCL, its events held
        meanwhile unless it can place itself by landmark ids."""
        rid = info.robot_id
        self.core.add_robot(info)
        if info.start_pose is None:
            self.waiting.setdefault(rid, time.monotonic())
            if self.core.config.association != "known":  # its events wait in the roster until it is placed
                log.info("robot %s waits for a pose from MCL", rid)
                return
        await self.admit(rid)

    async def _anchor(self) -> None:
        """With ``anchor_first``, on an empty map no robot has been placed in: the first robot announced without a
        start pose anchors the world frame at the origin once it has waited ``anchor_after_s``."""
        if not self.settings.anchor_first or self.core.robot_count or not self.core.map_is_empty():
            return
        rid = anchor_due({rid: t for rid, t in self.waiting.items() if self.core.is_waiting(rid)},
                         time.monotonic(), self.settings.anchor_after_s)
        if rid is None:
            return
        async with self._lock:
            placed = self.core.place_robot(rid, np.zeros(3), np.zeros((3, 3)))
        if placed:
            log.info("no robot has a start pose: robot %s anchors the world frame at the origin", rid)
            await self._placed(rid)

    async def handle(self, tag: str, key: str, payload) -> None:
        if tag == "state":
            await self._answer_state_queries()
        elif tag == "mcl" and (message := self.localized_mcl_pose(payload, key)) is not None:
            await self._on_mcl(message)
        await self.release_events()

    async def _on_mcl(self, message: MclPose) -> None:
        """A localized MCL pose places a robot that waits for one (:meth:`DSlam.place_robot`)."""
        rid = message.robot_id
        if not self.core.is_waiting(rid):
            return
        async with self._lock:
            placed = self.core.place_robot(rid, message.best_pose, message.best_cov, stamp=message.stamp)
        if not placed:
            self.reject("bad_placement", f"MCL pose of {rid}")
            return
        log.info("robot %s placed by MCL at %s", rid, np.round(message.best_pose, 3).tolist())
        await self._placed(rid, after=message.stamp)

    async def _placed(self, rid: str, after: float | None = None) -> None:
        """A waiting robot has its pose: the events the roster held for it, those after ``after``, go to the core."""
        self.waiting.pop(rid, None)
        if self.roster is not None and not self.roster.is_admitted(rid):
            await self.admit(rid, after=after)

    def robot_new_run(self, robot_id: str) -> None:
        """Its old pose no longer applies; its RobotInfo says where the new run starts (the map stays)."""
        self.core.remove_robot(robot_id)
        self.waiting.pop(robot_id, None)

    def robot_lost_odometry(self, robot_id: str) -> None:
        """Its pose is unknown until it is localized against the map again (:meth:`DSlam.lose_pose`)."""
        self.core.lose_pose(robot_id)

    # ------------------------------------------------------------ checkpoints
    def checkpoint_state(self) -> dict:
        return {"core": self.core, "assoc_counts": self.assoc_counts, "pose_seq": self._pose_seq,
                "map_seq": self._map_seq}

    def restore_state(self, state: dict) -> None:
        self.core = state["core"]
        self.core.associator = self.associate
        self.core.prefetching = self.settings.column_prefetch_margin > 0
        self.assoc_counts.update(state["assoc_counts"])
        self._pose_seq.update(state["pose_seq"])
        self._map_seq = state["map_seq"]
        now = time.monotonic()  # robots without a pose wait afresh (to anchor the frame, or for MCL)
        self.waiting = {rid: now for rid in self.core.robots if self.core.is_waiting(rid)}
        self.extra = self._extra()

    def checkpoint_summary(self) -> dict:
        return {"robots": len(self.core.robots), "landmarks": len(self.core.ids)}

    async def snapshot(self) -> bytes:
        """Taken with the map lock held: no scan is half-fused in a worker thread meanwhile."""
        async with self._lock:
            return await super().snapshot()

    async def robot_event(self, event) -> None:
        """Odometry in the loop; scans in a worker thread with the map lock held, then the robot's pose. A stop
        meanwhile waits for the scan (shielded): the lock stays held until the scan is in the core, so the last
        flush and checkpoint come after it, and no scan is half-fused or dropped."""
        if isinstance(event, OdomEvent):
            self.core.on_odometry(event)
            return
        await asyncio.shield(self._fuse_scan(event))

    async def _fuse_scan(self, event) -> None:
        async with self._lock:
            await asyncio.to_thread(self.core.on_scan, event)
            self._start_prefetch()
        self._publish_pose(event.robot_id, event.stamp)
        self.extra = self._extra()  # here, in the loop, while no worker thread touches the core

    def _start_prefetch(self) -> None:
        """Solve the covariance columns the robots will soon need in a worker thread, unless one is at it (the
        map lock held: :meth:`DSlam.column_prefetch` reads the core)."""
        if self._prefetch is not None and not self._prefetch.done():
            return
        job = self.core.column_prefetch()
        if job is not None:
            self._prefetch = asyncio.create_task(self._prefetch_columns(job))

    async def _prefetch_columns(self, job) -> None:
        """The solve without the lock (scans go on meanwhile; SuperLU releases the GIL), then the cache takes the
        columns under it, made exact for the updates of those scans."""
        try:
            solved = await asyncio.to_thread(job.run)
            async with self._lock:
                self.core.take_prefetched(job, solved)
        except Exception:  # a failed prefetch costs only time: the scan that needs the columns solves them
            self.core.counts["column_prefetch_failed"] += 1
            log.exception("solving covariance columns between scans failed")

    # ------------------------------------------------------------- publishing
    def _publish_pose(self, rid: str, stamp: float) -> None:
        estimate = self.core.robot_pose(rid)
        if estimate is None or self.core.before_placement(rid, stamp):
            return
        pose, cov = estimate
        pub = self._pose_pubs.get(rid)
        if pub is None:
            pub = self._pose_pubs[rid] = self.publisher(self.keys.dslam_pose(rid))
        cov = 0.5 * (cov + cov.T)
        pub.put(PoseEstimate(robot_id=rid, seq=self._pose_seq[rid], stamp=stamp, pose=pose, cov=cov, source="dslam"))
        self._pose_seq[rid] += 1
        self.published += 1

    def map_message(self, publish: bool = True) -> MapEstimate:
        """The map: every landmark mean by the tiles that changed since the last published map (:mod:`schemas.maptiles`;
        ``publish`` false: a full map for a state query, repeating the next number), and the marginal covariances
        of the landmarks near the robots."""
        snap = self.core.map_snapshot()
        tiles = (self.map_tiles.delta if publish else self.map_tiles.snapshot)(snap.means, None, snap.ids)
        return MapEstimate(
            seq=self._map_seq, stamp=snap.stamp, landmarks=tiles.means, landmark_ids=tiles.ids, full=tiles.full,
            tile_size=tiles.tile_size, tiles=tiles.tiles, tile_counts=tiles.counts,
            covariance_ids=snap.covariance_ids, covariances=snap.covariances, info_nnz=snap.info_nnz,
            recovery_iterations=snap.recovery_iterations,
        )

    async def tick(self) -> None:
        await self._anchor()
        async with self._lock:
            message = self.map_message()
            self.extra = self._extra()
            view = self.core.landmark_map() if self.map_saver.due() else None
        if view is not None:
            self.map_saver.save(view)
        self._map_pub.put(message)
        self._map_seq += 1
        self.published += 1

    async def _answer_state_queries(self) -> None:
        """Answer every waiting state query with one full map, built and encoded once."""
        async with self._lock:
            message = self.map_message(publish=False)
        self.state_queries.answer(encode(message))

    def _extra(self) -> dict[str, float]:
        return {**self.core.stats(), **{k: float(v) for k, v in self.assoc_counts.items()}}

    def on_stop(self) -> None:
        if self._prefetch is not None:
            self._prefetch.cancel()
        self._map_pub.put(self.map_message())
        self.published += 1
        self.extra = self._extra()
        self.map_saver.save(self.core.landmark_map())
        if self._client is not None:
            self._client.close()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, DslamSettings)


def main(args: argparse.Namespace) -> int:
    return serve_mapping_service(lambda: DslamService(settings_from_args(DslamSettings, args)))
