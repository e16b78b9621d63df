"""``fleetslam central``: the central multi-robot FastSLAM service (the centralised scheme of Howard,
"Multi-robot simultaneous localization and mapping using particle filters").

Robots are followed through the shared roster (:meth:`ServiceShell.follow_robots`:
liveliness, RobotInfo asked for when a token appears, streams checked for
order, new runs recognised) and every robot's odometry and scans go into one
filter (:class:`central.fastslam.FastSlam`):

- Across robots, events wait in the shell's :class:`~services.roster.ReorderBuffer` at
  most ``reorder_window_s`` (wall time) and are handled in stamp order once
  every stream of every live robot has passed their stamp.
- When no robot has been placed ``anchor_after_s`` after the first robot without a start pose was
  announced, that robot anchors the world frame at the origin (``anchor_first``; the offline runner anchors
  the first robot to scan).
- Any other robot whose start pose is unknown waits (its events held by the roster,
  at most ``waiting_mb`` of them) until ``{prefix}/mcl/{rid}/pose`` (MclPose)
  says ``localized``; it enters at MCL's best pose and covariance, and its
  held events older than that pose are dropped (counted). MCL's first ``localized`` can be a wrong hypothesis
  of a symmetric map: when a robot MCL placed has a localized MCL pose farther than ``replace_distance_m``
  from the filter's for ``replace_after`` poses in a row (MCL relocalized it), it leaves the filter (its
  landmarks stay) and is placed again (:class:`services.placement.PlacementCheck`, counted ``replaced``).
- A robot whose first odometry message arrives with seq > 0 (the service
  started after it) has lost its start pose: counted, and with ``late_join``
  = ``wait`` it waits for MCL like a robot without a start pose.
- Robot-to-robot detections in scans weight the particles (``robot_detections``, on by default; with the scan's
  noise covariance times ``robot_detection_noise_scale``, plus ``robot_detection_position_sd`` of relative
  position without landmark ids); they never update the map.

The estimate (every placed robot's weighted mean pose and covariance, the
map) is published on ``{prefix}/central/estimate`` at ``estimate_rate_hz``, its map by the tiles that changed
(:mod:`schemas.maptiles`: ``map_tile_m``, ``map_tolerance_m``; the first estimate is full), so that its steady
cost follows what the robots see, not the map's size; the queryable ``{prefix}/central/state`` answers with a
fresh, full one (how a late joiner, or a receiver that missed an estimate, gets the whole map): the queries that arrive meanwhile wait
together (at most ``max_state_queries``; more are answered ``busy`` at once) and all get the one estimate built
at the loop's next turn, so a flood of them costs the filter one estimate.

With ``map`` (``--map FILE``, :mod:`schemas.mapfile`) the filter starts from a saved map, in its frame: the
estimate is published from the start (the map alone, before any robot), and no robot anchors a new frame:
robots without a start pose wait for MCL to place them against that map. With ``map_out`` the map is saved
(atomically) every ``map_out_period_s`` and on exit.
"""

from __future__ import annotations

import argparse
import logging
import time
from collections import defaultdict, deque

import numpy as np
import zenoh

from central.fastslam.config import FastSlamConfig, available_cores
from central.fastslam.core import FastSlam
from schemas.codec import encode
from schemas.config import CentralSettings, add_settings_arguments, settings_from_args
from schemas.contract import OdomEvent
from schemas.maptiles import TileBlock, TileSender
from schemas.messages import Estimate, MclPose, RobotEstimate, RobotInfo
from services.mapfeed import StateQueries
from services.maps import MapSaver, seed_from_file, serve_mapping_service
from services.placement import PlacementCheck, anchor_due
from services.roster import StreamEvent
from services.runtime import ServiceShell

log = logging.getLogger("fleetslam.central")


class CentralService(ServiceShell):
    """Order every robot's events, feed the filter, publish estimates and answer state queries."""

    name = "central"
    uses_kernels = ("fastslam", "association")  # shared association runs JCBB

    def __init__(self, settings: CentralSettings, instance: str | None = None):
        super().__init__(settings, instance)
        self.settings: CentralSettings = settings
        self.tick_period_s = 1.0 / settings.estimate_rate_hz
        self.slam = FastSlam(settings.core(FastSlamConfig))
        log.info("central: %d particles, per-particle kernels on %d worker%s (--workers; cores here: %d)",
                 self.slam.config.particles, self.slam.workers, "" if self.slam.workers == 1 else "s",
                 available_cores())
        self.processed: dict[str, int] = defaultdict(int)
        self.compute_ms: deque[float] = deque(maxlen=5000)
        self.estimate_seq = 0
        self.last_stamp = 0.0
        self.map_tiles = TileSender(settings.map_tile_m, settings.map_tolerance_m, settings.map_cov_tolerance)
        self.announced_waiting: dict[str, float] = {}  # robots announced without a pose: when (wall clock)
        self.placed_by_mcl: set[str] = set()
        self.placement_check = PlacementCheck(settings.replace_distance_m, settings.replace_after)
        self.joining: dict[str, RobotInfo] = {}  # robots announced with a start pose, before their first event
        self.state_queries = StateQueries(self, self.keys.central_state, settings.max_state_queries)
        self.prior_landmarks = seed_from_file(self.slam, settings.map, self.slam.config.association)
        self.map_saver = MapSaver(settings.map_out, {
            "estimator": "fastslam", "association": self.slam.config.association,
            "particles": self.slam.config.particles, "seed": self.slam.config.seed, "service": "central",
            "from_map": settings.map}, settings.map_out_period_s)

    # ------------------------------------------------------------ wiring
    def setup(self, session: zenoh.Session) -> None:
        self.follow_robots()
        self.subscribe(f"{self.settings.prefix}/mcl/*/pose", "mcl", recover=False)
        self._estimate_pub = self.publisher(self.keys.central_estimate)
        self.state_queries.declare(session)

    # ------------------------------------------------------------ robots
    async def robot_announced(self, info: RobotInfo) -> None:
        rid = info.robot_id
        if info.start_pose is not None and not self.slam.has_robot(rid) and not self.slam.is_waiting(rid):
            self.joining[rid] = info  # into the filter at its first event (:meth:`robot_event`)
            await self.admit(rid)
        elif self.slam.add_robot(info):
            await self.admit(rid)
        else:
            self.announced_waiting.setdefault(rid, time.monotonic())
            log.info("robot %s waits for a pose from MCL", rid)

    async def _anchor(self) -> None:
        """With ``anchor_first``: when no robot has been placed ``anchor_after_s`` after the first robot without a
        start pose was announced, that robot anchors the world frame at the origin (a robot with a start pose
        announced meanwhile is placed instead, and the frame stays the one its start pose is given in)."""
        if not self.settings.anchor_first or self.slam.robot_count or self.joining or self.prior_landmarks:
            return
        rid = anchor_due({rid: t for rid, t in self.announced_waiting.items() if self.slam.is_waiting(rid)},
                         time.monotonic(), self.settings.anchor_after_s)
        if rid is not None and self.slam.place_robot(rid, np.zeros(3), np.zeros((3, 3))):
            log.info("no robot has a start pose: robot %s anchors the world frame at the origin", rid)
            await self.admit(rid)

    async def robot_event(self, event: StreamEvent) -> None:
        """Into the filter, in stamp order across every robot; a robot announced with its start pose enters the
        filter here, at its first event: its particles' start poses are drawn in stamp order, not in the order the
        robots' RobotInfo happened to arrive, so two runs of the same data draw the same numbers."""
        if event.robot_id in self.joining:
            self.slam.add_robot(self.joining.pop(event.robot_id))
        started = time.perf_counter()
        accepted = self.slam.on_odometry(event) if isinstance(event, OdomEvent) else self.slam.on_scan(event)
        self.compute_ms.append((time.perf_counter() - started) * 1e3)
        if accepted:
            self.processed[event.robot_id] += 1
            self.last_stamp = max(self.last_stamp, event.stamp)

    def robot_new_run(self, robot_id: str) -> None:
        """It leaves the filter (the landmarks it mapped stay) and rejoins from its RobotInfo."""
        self.slam.remove_robot(robot_id)
        self.announced_waiting.pop(robot_id, None)
        self.joining.pop(robot_id, None)
        self.placed_by_mcl.discard(robot_id)
        self.placement_check.forget(robot_id)

    def robot_joined_late(self, robot_id: str) -> None:
        """With ``late_join`` = ``wait`` it is taken out (or kept out) of the filter until MCL places it; with
        ``start_pose`` it keeps its announced start pose (counted; the map may suffer)."""
        if self.settings.late_join != "wait":
            return
        joining = self.joining.pop(robot_id, None)
        if joining is not None:
            self.slam.add_robot(joining.model_copy(update={"start_pose": None, "start_pose_cov": None}))
        if joining is not None or self.slam.unplace(robot_id) is not None:
            self.roster.hold(robot_id)
            log.info("robot %s waits for a pose from MCL", robot_id)

    def robot_lost_odometry(self, robot_id: str) -> None:
        """Its pose no longer follows it: it leaves the filter (the landmarks it mapped stay) and waits for MCL to
        place it again (MCL localizes a robot whose odometry was lost, whatever its start pose)."""
        if self.slam.unplace(robot_id) is not None:
            self._wait_for_mcl(robot_id)

    def _wait_for_mcl(self, robot_id: str) -> None:
        """A robot just sent back to wait in the filter: its events are held until MCL places it."""
        self.roster.hold(robot_id)
        self.announced_waiting.setdefault(robot_id, time.monotonic())
        log.info("robot %s waits for a pose from MCL", robot_id)

    # ------------------------------------------------------------ checkpoints
    def checkpoint_state(self) -> dict:
        return {"slam": self.slam, "processed": self.processed,
                "estimate_seq": self.estimate_seq, "last_stamp": self.last_stamp,
                "waiting_robots": sorted(self.announced_waiting), "joining": self.joining,
                "placed_by_mcl": sorted(self.placed_by_mcl)}

    def restore_state(self, state: dict) -> None:
        """The filter (particles, maps, random generator); robots waiting for a pose wait afresh."""
        workers = self.slam.workers  # the count this process chose: the checkpoint's was another process's
        self.slam = state["slam"]
        self.slam.workers = workers
        self.processed.update(state["processed"])
        self.estimate_seq = state["estimate_seq"]
        self.last_stamp = state["last_stamp"]
        self.joining = state["joining"]
        self.placed_by_mcl = set(state.get("placed_by_mcl", ()))
        now = time.monotonic()
        self.announced_waiting = {rid: now for rid in state["waiting_robots"]}

    def checkpoint_summary(self) -> dict:
        return {"robots": self.slam.robot_count, "landmarks_best": int(self.slam.stats()["landmarks_best"]),
                "processed": int(sum(self.processed.values())), "stamp": round(self.last_stamp, 3)}

    # ------------------------------------------------------------ handling
    async def handle(self, tag: str, key: str, payload) -> None:
        if tag == "state":
            self._answer_state_queries()
        elif tag == "mcl" and (message := self.localized_mcl_pose(payload, key)) is not None:
            await self._on_mcl(message)
        await self.release_events()

    async def _on_mcl(self, message: MclPose) -> None:
        rid = message.robot_id
        if not self.slam.is_waiting(rid):
            self._check_placement(rid, message)
            return
        if self.slam.place_robot(rid, message.best_pose, message.best_cov, stamp=message.stamp):
            log.info("robot %s placed by MCL at %s", rid, np.round(message.best_pose, 3).tolist())
            self.placed_by_mcl.add(rid)
            self.placement_check.forget(rid)
            await self.admit(rid, after=message.stamp)
        else:
            self.reject("bad_placement", f"MCL pose of {rid}")

    def _check_placement(self, rid: str, message: MclPose) -> None:
        """A robot MCL placed, whose localized MCL pose has stayed far from the filter's pose of the same stamp
        (``replace_after``, ``replace_distance_m``; :class:`services.placement.PlacementCheck`): it leaves the
        filter (its landmarks stay) and the next localized pose places it again, counted as ``replaced``."""
        if rid not in self.placed_by_mcl or not self.placement_check.observe(rid, message.stamp, message.best_pose):
            return
        there = self.placement_check.filter_at(rid, message.stamp)
        log.warning("robot %s: MCL has put it %.1f m from the filter's pose of the same moment for %d localized poses "
                    "in a row: it is placed again", rid, float(np.hypot(*(there - np.asarray(message.best_pose)[:2]))),
                    self.settings.replace_after)
        self.count_extra("replaced")
        info = self.slam.remove_robot(rid)
        self.slam.add_robot(info.model_copy(update={"start_pose": None, "start_pose_cov": None}))
        self._wait_for_mcl(rid)

    # ------------------------------------------------------------ output
    def estimate(self, publish: bool = True) -> Estimate | None:
        """The current estimate as a message (None when a number is not finite: never published).

        Published estimates are numbered 0, 1, 2... and carry the map tiles that changed since the one before
        (:mod:`schemas.maptiles`; the first is full); a state query's reply (``publish`` false) is a full estimate
        that repeats the next number.
        """
        robots = []
        for rid, (pose, cov) in self.slam.poses().items():
            stamp = self.slam.pose_stamp(rid)
            if rid in self.placed_by_mcl and stamp is not None:
                self.placement_check.record(rid, stamp, pose)  # MCL's later poses are compared with this
            robots.append(RobotEstimate(robot_id=rid, stamp=self.last_stamp if stamp is None else stamp, pose=pose,
                                        cov=0.5 * (cov + cov.T)))
        view = self.slam.landmark_map()
        values = [view.means, view.covs] + [r.pose for r in robots] + [r.cov for r in robots]
        if not all(np.all(np.isfinite(v)) for v in values):
            self.reject("estimate_not_finite")
            return None
        tiles: TileBlock = (self.map_tiles.delta if publish else self.map_tiles.snapshot)(view.means, view.covs, view.ids)
        message = Estimate(seq=self.estimate_seq, stamp=self.last_stamp, robots=robots, landmarks=tiles.means,
                           landmark_covs=tiles.covs, landmark_ids=tiles.ids, full=tiles.full,
                           tile_size=tiles.tile_size, tiles=tiles.tiles, tile_counts=tiles.counts,
                           particles=self.slam.particle_count, effective_particles=self.slam.effective_particles(),
                           method=f"fastslam-{self.slam.config.association}")
        self.estimate_seq += int(publish)
        return message

    def _answer_state_queries(self) -> None:
        """Answer every waiting state query with one full estimate, built and encoded once."""
        message = self.estimate(publish=False)
        self.state_queries.answer(None if message is None else encode(message), b"estimate_not_finite")

    def _update_stats(self) -> None:
        self.extra.update({k: v for k, v in self.slam.stats().items()})
        self.extra["processed"] = float(sum(self.processed.values()))
        self.extra["state_answered"] = float(self.state_queries.answered)
        self.put_timing("compute_ms", self.compute_ms)

    def _publish_estimate(self) -> None:
        message = self.estimate()
        if message is not None:
            self._estimate_pub.put(message)
            self.published += 1

    async def tick(self) -> None:
        await self._anchor()
        await self.release_events()
        self._update_stats()
        if self.slam.robot_count or self.prior_landmarks:
            self._publish_estimate()
        if self.map_saver.due():
            self.map_saver.save(self.slam.landmark_map())

    def on_stop(self) -> None:
        self._update_stats()
        if self.slam.robot_count or self.prior_landmarks:
            self._publish_estimate()
        self.map_saver.save(self.slam.landmark_map())
        log.info("central: processed %s; rejected %s", dict(self.processed), dict(self.rejected))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, CentralSettings)


def main(args: argparse.Namespace) -> int:
    return serve_mapping_service(lambda: CentralService(settings_from_args(CentralSettings, args)))
