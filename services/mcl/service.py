"""``fleetslam mcl``: Monte Carlo localization of robots against a map, over Zenoh.

The map comes from the ``source`` setting: ``central`` (the latest
:class:`Estimate` on ``{prefix}/central/estimate``), ``dslam`` (the
:class:`MapEstimate` on ``{prefix}/dslam/map``), ``truth`` (the
:class:`WorldTruth` on ``{prefix}/world/truth``, asked for at start too) or
``file:PATH`` (a map saved by ``--map-out``, :mod:`schemas.mapfile`, whose landmark ids, if it has them,
are signatures as the scans' ids; or an ``(L, 2)`` array in a .npy or text file). A newer map
replaces the old one at most every ``map_period_s``.

Robots are followed through the shared roster (:meth:`ServiceShell.follow_robots`);
every robot whose :class:`RobotInfo` announces no start pose (every robot with
``all_robots``) joins the :class:`~services.mcl.fleet.MclFleet`, which gives
it a filter; its odometry moves the particles, each scan runs the variant's
update, and an :class:`MclPose` (every significant hypothesis, the best pose,
``localized``) goes to ``{prefix}/mcl/{rid}/pose``. The central FastSLAM
service takes a robot with an unknown start pose in on its first
``localized`` message.

Robots that detect each other (``robot_meetings``, on by default): every robot's odometry is dead-reckoned,
the central estimate's poses of the robots MCL does not localize are carried along it to each scan's instant
(:class:`~services.mcl.meeting.PlacedPoses`), and a detection between such a placed robot and a robot being
localized, either way, is a meeting (:class:`~services.mcl.meeting.MeetingDesk`, as offline): one that no
particle agrees with starts the localization again from where it puts the robot, a localization that
contradicts the robot's meetings is refused, and once its meetings fix its pose on their own the robot is placed
there and its MclPose says ``localized`` — on a symmetric map, MCL alone can settle on the twin.

The queryable ``{prefix}/mcl/localize`` answers a :class:`LocalizeRequest`
(one scan and its sensor) with the hypotheses of a one-shot global
localization, or a tracked robot's belief. A scan is checked on Zenoh's
callback thread (:func:`localize_refusal`: a sensor noise covariance that is
not positive definite is ``invalid``; more work than the ``max_localize_*``
settings allow is ``too_large``) and solved by a worker of a
:class:`~services.query_pool.QueryPool` (``busy`` at once when
``query_queue`` queries wait already, ``expired`` or ``deadline`` past
``query_deadline_s``), so the robots' tracking in the loop keeps its path; a
tracked robot's belief is read in the loop, between its events, for a
worker. Bad input — undecodable payloads,
out-of-order or duplicate stream messages, keys that disagree with the
message's robot id, a map of the wrong shape — is counted and dropped.
"""

from __future__ import annotations

import argparse
import logging
import math
import time
from concurrent.futures import Future, TimeoutError as FutureTimeout
from pathlib import Path

import numpy as np
import zenoh
from scipy.spatial import cKDTree

from schemas.codec import decode, encode
from schemas.mapfile import load_map
from schemas.config import MclSettings, add_settings_arguments, settings_from_args
from schemas.contract import OdomEvent
from schemas.mcl import LocalizeReply, LocalizeRequest
from schemas.messages import Estimate, MapEstimate, MclPose, PoseHypothesis, RobotInfo, SensorSpec, WorldTruth
from schemas.transport import StreamPublisher
from services.mcl.config import MclConfig
from services.mcl.core import MonteCarloLocalizer
from services.mcl.fleet import MclFleet, RobotState
from services.mcl.meeting import MeetingDesk, PlacedPoses
from services.query_pool import QueryPool, QueryRefused, Solve, decode_query
from services.mapfeed import MapFeed
from services.runtime import ServiceShell

log = logging.getLogger(__name__)

MAP_MESSAGES = {"central": Estimate, "dslam": MapEstimate, "truth": WorldTruth}
# meetings between two solves of a robot's pose: they come at the scan rate of every robot that sees it, and a solve
# over a full log takes tens of milliseconds
LIVE_SOLVE_EVERY = 5


def load_map_file(path: str) -> np.ndarray:
    """An ``(L, 2)`` landmark array from a .npy or whitespace/comma-separated text file."""
    file = Path(path)
    if file.suffix == ".npy":
        data = np.asarray(np.load(file), float)
    else:
        data = np.asarray(np.loadtxt(file, delimiter="," if file.suffix == ".csv" else None), float)
    if data.size == 0:
        return np.zeros((0, 2))
    data = data.reshape(1, -1) if data.ndim == 1 else data
    if data.ndim != 2 or data.shape[1] != 2:
        raise ValueError(f"{path}: expected an (L, 2) array, got shape {data.shape}")
    if not np.all(np.isfinite(data)):
        raise ValueError(f"{path}: the map holds NaN or infinite values")
    return data


def load_source_file(path: str) -> tuple[np.ndarray, np.ndarray | None]:
    """(landmarks ``(L, 2)``, ids or None) of ``file:PATH``: a fleetslam-map .json file, else an array file."""
    if Path(path).suffix == ".json":
        view = load_map(path).view()
        return view.means, view.ids
    return load_map_file(path), None


def localize_refusal(observations: int, particles: int, sensor: SensorSpec, landmarks: np.ndarray, config: MclConfig,
                     max_particles: int, max_cells: int, max_map_cells: int) -> tuple[str, str] | None:
    """Why a one-shot localization of ``observations`` with ``particles`` may not run, as (reason, detail), or None.

    Checked before any work: the sensor's noise covariance (scaled by ``noise_scale``) must be positive definite,
    as the likelihood inverts it (``invalid``); the particles at most ``max_particles``, observations × particles
    at most ``max_cells``, and what the sensor makes of the map — the cells of the landmark lookup grids its gate
    and range need, plus the landmark pairs within twice its range — at most ``max_map_cells`` (``too_large``).
    """
    noise = np.asarray(sensor.noise_cov, float) * config.noise_scale**2
    (a, b), (c, d) = noise
    if not (np.all(np.isfinite(noise)) and a > 0 and d > 0 and a * d - b * c > 0):
        return "invalid", f"the sensor's noise covariance {np.asarray(sensor.noise_cov).tolist()} is not positive definite"
    if particles > max_particles:
        return "too_large", f"{particles} particles exceed max_localize_particles {max_particles}"
    if observations * particles > max_cells:
        return "too_large", (f"{observations} observations × {particles} particles = {observations * particles} cells "
                             f"exceed max_localize_cells {max_cells}")
    span = np.ptp(landmarks, axis=0) if len(landmarks) else np.zeros(2)
    radius = config.match_sigmas * math.hypot(math.sqrt(a), sensor.max_range * math.sqrt(d))
    view_cell = max(config.lookup_cell, sensor.max_range / 8)
    grid = float(np.prod(np.ceil((span + 2 * radius + 6 * config.lookup_cell) / config.lookup_cell)))
    grid += float(np.prod(np.ceil((span + 2 * sensor.max_range + 6 * view_cell) / view_cell)))
    if grid > max_map_cells:
        return "too_large", (f"the sensor's gate ({radius:.3g} m) and range ({sensor.max_range:g} m) need lookup grids of "
                             f"{grid:.0f} cells on this map, above max_localize_map_cells {max_map_cells}")
    if len(landmarks) > 1:
        tree = cKDTree(landmarks)
        pairs = int(tree.count_neighbors(tree, 2 * sensor.max_range)) - len(landmarks)
        if grid + pairs > max_map_cells:
            return "too_large", (f"the sensor's range ({sensor.max_range:g} m) pairs {pairs} landmarks of this map "
                                 f"(with {grid:.0f} grid cells), above max_localize_map_cells {max_map_cells}")
    return None


def hypotheses_message(mcl: MonteCarloLocalizer) -> tuple[np.ndarray, np.ndarray, list[PoseHypothesis]]:
    """(best pose, best covariance, hypotheses) of a filter, ready for a message."""
    found = mcl.hypotheses()
    hypotheses = [PoseHypothesis(mean=h.mean, cov=0.5 * (h.cov + h.cov.T), weight=min(max(h.weight, 0.0), 1.0),
                                 particles=h.particles) for h in found]
    if not hypotheses:
        return np.zeros(3), np.diag([1e6, 1e6, 1e2]), []
    return hypotheses[0].mean, hypotheses[0].cov, hypotheses


class MclService(ServiceShell):
    """Localizes robots with unknown start poses against the chosen map; answers localization queries."""

    name = "mcl"
    uses_kernels = ("mcl",)

    def __init__(self, settings: MclSettings, instance: str | None = None):
        super().__init__(settings, instance)
        self.settings: MclSettings = settings
        self.source = settings.source.partition(":")[0]
        state_key = {"central": self.keys.central_state, "dslam": self.keys.dslam_state}.get(self.source)
        self.map_feed = None if state_key is None else MapFeed(self, MAP_MESSAGES[self.source], state_key, "map_state")
        self.map_applied = float("-inf")
        landmarks, ids = load_source_file(settings.source.partition(":")[2]) if self.source == "file" else (None, None)
        self.fleet = MclFleet(settings.core(MclConfig), landmarks, landmark_ids=ids)
        self.pose_pubs: dict[str, StreamPublisher] = {}
        self.pose_seq: dict[str, int] = {}  # kept when a robot leaves: its MclPose stream goes on where it stopped
        self.desk = MeetingDesk(LIVE_SOLVE_EVERY)  # every robot's dead reckoning and, for the robots MCL localizes, their meetings
        self.placed = PlacedPoses()  # where the robots MCL does not localize are, from the central estimate
        self.pool = QueryPool(self, settings.query_workers, settings.query_queue, settings.query_deadline_s,
                              settings.query_nice)

    # ----------------------------------------------------------------- wiring

    def setup(self, session: zenoh.Session) -> None:
        keys = self.keys
        self.follow_robots()
        map_key = {"central": keys.central_estimate, "dslam": keys.dslam_map, "truth": keys.world_truth}.get(self.source)
        if map_key is not None:
            self.subscribe(map_key, "map")
        if self.map_feed is not None:
            self.map_feed.ask()  # the whole map now, not at the next message
        elif map_key is not None:
            session.get(map_key, self._on_map_reply)
        if self.settings.robot_meetings and self.source != "central":
            self.subscribe(keys.central_estimate, "poses", recover=False)
        self._declared.append(session.declare_queryable(keys.mcl_localize, self._on_query))

    def _on_map_reply(self, reply: zenoh.Reply) -> None:
        if reply.ok is not None:
            self.enqueue("map", str(reply.ok.key_expr), reply.ok.payload.to_bytes())

    def _on_query(self, query: zenoh.Query) -> None:
        self.pool.admit(query, "localize", lambda: self._prepare(query))

    # ---------------------------------------------------------------- handling

    async def handle(self, tag: str, key: str, payload) -> None:
        if tag == "poses":
            self._take_poses(decode(payload, Estimate))
        elif tag in ("map", "map_state"):
            had_map = self.fleet.landmarks is not None
            message = decode(payload, MAP_MESSAGES[self.source])
            if self.source == "central":
                self._take_poses(message)
            if self.map_feed is not None:  # a map sent by tiles: the whole map once it has every tile
                message = self.map_feed.take(message, reply=tag == "map_state")
            if message is not None:
                self._on_map(message)
            if not had_map and self.fleet.landmarks is not None:
                waited = sorted(rid for rid in self.fleet.robots if not self.roster.is_admitted(rid))
                await self.admit_all(waited)  # the robots that waited for the map, with what they sent meanwhile
        self._refresh_extra()

    def _on_map(self, message) -> None:
        if self.source == "central":
            self._release_anchored({robot.robot_id for robot in message.robots})
        landmarks = np.asarray(message.landmarks, float).reshape(-1, 2)
        now = time.monotonic()
        if landmarks.shape[0] == 0:
            self.reject("empty_map")
            return
        if self.fleet.landmarks is not None and now - self.map_applied < self.settings.map_period_s:
            return
        # ids are signatures only where they are the scans' own landmark ids: the central map's (it carries ids with
        # known association) and the world truth's; D-SLAM numbers the features it discovers itself
        ids = None if self.source == "dslam" else getattr(message, "landmark_ids", None)
        signed = ids is not None and len(ids) > 0
        least = self.settings.map_min(signed)
        if self.fleet.landmarks is None and landmarks.shape[0] < least:  # too few to tell poses apart: robots wait
            if not self.extra.get("maps_too_small"):
                log.info("the %s map holds %d landmarks %s ids: robots wait for %d", self.source, landmarks.shape[0],
                         "with" if signed else "without", least)
            self.count_extra("maps_too_small")
            return
        self.map_applied = now
        self.fleet.set_map(landmarks, ids)

    def _release_anchored(self, placed: set[str]) -> None:
        """Stop localizing a robot that the central estimate holds although MCL never localized it: the central
        placed it another way (it anchors the world frame), and its scans would only take time from the robots
        that wait for MCL."""
        for rid in sorted(placed & set(self.fleet.robots)):
            if self.fleet.robots[rid].localized_s is None:
                self.fleet.remove_robot(rid)
                self.count_extra("robots_released")
                log.info("robot %s is in the central map without MCL (it anchors the frame): not localized further", rid)

    # ------------------------------------------------------------------ robots

    async def robot_announced(self, info: RobotInfo) -> None:
        """Localize a robot that announces no start pose (every robot with ``all_robots``); the others' events
        flow past untouched."""
        rid = info.robot_id
        self.desk.add_robot(info)
        if info.start_pose is None or self.settings.all_robots:
            log.info("localizing robot %s (%s start pose)", rid, "unknown" if info.start_pose is None else "known")
            self.fleet.add_robot(info)
            self._pose_pub(rid)
            if self.fleet.landmarks is None:  # its events wait for the map (within waiting_mb), not dropped
                log.info("robot %s waits for the map", rid)
                self._refresh_extra()
                return
        await self.admit(rid)
        self._refresh_extra()

    def robot_new_run(self, robot_id: str) -> None:
        """Localized from scratch once its new run announces itself (its MclPose stream goes on)."""
        self.fleet.remove_robot(robot_id)
        self.placed.forget(robot_id)

    def robot_lost_odometry(self, robot_id: str) -> None:
        """Its odometry was lost for good: localized globally afresh, whatever its start pose (the central service
        waits for this to place it again)."""
        info = self.roster.info(robot_id)
        if info is None:
            return
        log.info("robot %s lost odometry: global localization again", robot_id)
        self.fleet.remove_robot(robot_id)
        self.fleet.add_robot(info.model_copy(update={"start_pose": None, "start_pose_cov": None}))
        self.count_extra("robots_relocalized")

    # ------------------------------------------------------------ checkpoints
    def checkpoint_state(self) -> dict:
        return {"fleet": self.fleet, "pose_seq": self.pose_seq, "desk": self.desk, "placed": self.placed}

    def restore_state(self, state: dict) -> None:
        """The filters (particles, random generators), the map and the robots' meetings; each tracked robot gets
        its publisher back. A checkpoint written before meetings restores without them."""
        self.fleet = state["fleet"]
        self.pose_seq = dict(state["pose_seq"])
        self.desk = state.get("desk", MeetingDesk(LIVE_SOLVE_EVERY))
        self.placed = state.get("placed", PlacedPoses())
        self._refresh_extra()

    def checkpoint_summary(self) -> dict:
        return {"robots": len(self.fleet.robots), "localized": self.fleet.localized_count()}

    async def robot_event(self, event) -> None:
        if self.settings.robot_meetings:
            self._meet(event)
        state = self.fleet.robots.get(event.robot_id)
        if state is None:
            return
        if state.mcl is None:
            self.rejected["no_map_yet"] += 1
            return
        if isinstance(event, OdomEvent):
            self.fleet.on_odometry(event)
            return
        was_localized = state.localized
        report = self.fleet.on_scan(event)
        if report.kidnapped:
            log.warning("robot %s: no hypothesis explains its scans; global localization again", event.robot_id)
        localized = report.localized
        if localized and not was_localized and self.desk.contradicts(event.robot_id, state.mcl.best()[0]):
            log.info("robot %s: MCL's pose %s contradicts its meetings with placed robots; localized again from the "
                     "latest", event.robot_id, np.round(state.mcl.best()[0], 2))
            state.mcl.restart_from(self.desk.latest(event.robot_id))
            state.localized = localized = False
            self.count_extra("meeting_refusals")
        changed = localized != was_localized
        if localized and changed:
            log.info("robot %s localized at %s after %d scans", event.robot_id, np.round(state.mcl.best()[0], 2),
                     state.scans)
        if changed or state.scans % self.settings.publish_every == 0:
            self._publish(event.robot_id, state, event.stamp)
        self._refresh_extra()

    # ---------------------------------------------------------------- meetings

    def _take_poses(self, estimate: Estimate) -> None:
        """The central estimate's poses of the robots MCL does not localize: they place the others at meetings."""
        for robot in estimate.robots:
            if robot.robot_id not in self.fleet.robots:
                self.placed.estimate(robot.robot_id, robot.stamp, robot.pose, robot.cov)

    def _localizing(self, rid: str) -> bool:
        state = self.fleet.robots.get(rid)
        return state is not None and state.mcl is not None and rid in self.desk.logs

    def _placed(self, rid: str) -> bool:
        return rid not in self.fleet.robots and rid in self.placed and rid in self.desk.logs

    def _meet(self, event) -> None:
        """Every robot's odometry moves its dead reckoning; a scan's detections between a robot MCL localizes and a
        placed robot are meetings (:mod:`services.mcl.meeting`): one that no particle agrees with starts the
        localization again from where it puts the robot, and once a robot's meetings fix its pose on their own it
        is placed there, localized (as the offline placer does)."""
        rid = event.robot_id
        if isinstance(event, OdomEvent):
            self.desk.move(event)
            if rid not in self.fleet.robots and rid in self.desk.logs:
                self.placed.move(rid, event.stamp, self.desk.logs[rid].odometry)
            return
        if not len(event.robot_ids):
            return
        for sighting in self.desk.sightings(event, self._localizing, self._placed):
            subject = sighting.subject
            state = self.fleet.robots[subject]
            other = self.placed.pose_at(sighting.other, event.stamp)
            if other is None:
                self.count_extra("meetings_unaligned")
                continue
            meeting = self.desk.meeting(sighting, *other, event.noise_cov)
            restarted, fix = self.desk.meet(subject, meeting, state.mcl, solve=not state.mcl.localized)
            self.count_extra("meetings")
            if restarted:
                self.count_extra("meeting_restarts")
                log.info("robot %s: no hypothesis agrees with its meeting with %s; localized again from it", subject,
                         sighting.other)
            if fix is not None:
                state.mcl.place(fix.pose, fix.cov)
                state.localized = True
                self.count_extra("meeting_placements")
                log.info("robot %s placed at %s by %d meetings with placed robots", subject, np.round(fix.pose, 2),
                         fix.meetings)
                self._publish(subject, state, event.stamp)

    def _pose_pub(self, rid: str) -> StreamPublisher:
        """The publisher of a robot's MclPose, declared on first use."""
        if rid not in self.pose_pubs:
            self.pose_pubs[rid] = self.publisher(self.keys.mcl_pose(rid))
        return self.pose_pubs[rid]

    def _publish(self, rid: str, state: RobotState, stamp: float) -> None:
        mcl = state.mcl
        best, cov, hypotheses = hypotheses_message(mcl)
        seq = self.pose_seq.get(rid, 0)
        message = MclPose(robot_id=rid, seq=seq, stamp=stamp, best_pose=best, best_cov=cov,
                          localized=mcl.localized, hypotheses=hypotheses, particles=mcl.count, variant=mcl.variant)
        self._pose_pub(rid).put(message)
        self.pose_seq[rid] = seq + 1
        self.published += 1

    # ---------------------------------------------------------------- queries
    def _prepare(self, query: zenoh.Query) -> Solve:
        """Zenoh's thread: decode; the solve of a tracked robot's belief, or of a scan (checked now)."""
        request = decode_query(query, LocalizeRequest)
        if request.ranges.size == 0 and request.robot_id is not None:
            return self._track_solve(request)
        return self._scan_solve(request)

    def _track_solve(self, request: LocalizeRequest) -> Solve:
        """A tracked robot's belief, read in the loop between two of its events (the worker waits for it); a robot
        the service does not track yet gets a one-shot localization instead."""
        def read(future: Future) -> None:
            state = self.fleet.robots.get(request.robot_id)
            try:
                tracked = state is not None and state.mcl is not None and state.mcl.initialized
                future.set_result(encode(self._reply(request, state.mcl, "track")) if tracked else None)
            except Exception as exc:  # noqa: BLE001 - handed to the worker, which answers solve_error
                future.set_exception(exc)

        def solve(budget_s: float) -> tuple[str, bytes]:
            started = time.monotonic()
            future: Future = Future()
            self.call_in_loop(read, future)
            try:
                payload = future.result(timeout=budget_s)
            except FutureTimeout:
                raise QueryRefused("deadline", f"the robots' loop did not get to the belief within {budget_s:.3g} s") from None
            if payload is not None:
                return self.keys.mcl_localize, payload
            return self._scan_solve(request)(budget_s - (time.monotonic() - started))

        return solve

    def _scan_solve(self, request: LocalizeRequest) -> Solve:
        """Check a one-shot localization (QueryRefused now) and return its solve, against the map of now."""
        state = self.fleet.robots.get(request.robot_id) if request.robot_id else None
        sensor = request.sensor or (state.info.sensor if state else None)
        if sensor is None:
            raise QueryRefused("no_sensor", "a scan needs its sensor (or the id of a robot the service tracks)")
        landmarks = self.fleet.landmarks
        if landmarks is None:
            raise QueryRefused("no_map", f"no map from source {self.settings.source!r} yet")
        s = self.settings
        count = request.particles or s.localize_particles
        refusal = localize_refusal(request.ranges.size, count, sensor, landmarks, self.fleet.config,
                                   s.max_localize_particles, s.max_localize_cells, s.max_localize_map_cells)
        if refusal is not None:
            raise QueryRefused(*refusal)

        def solve(budget_s: float) -> tuple[str, bytes]:
            try:
                mcl = self.fleet.localize_once(request.observations, sensor, count, request.seed,
                                               request.robot_id or "query", landmarks, time_budget_s=budget_s)
            except TimeoutError as exc:
                raise QueryRefused("deadline", str(exc)) from None
            return self.keys.mcl_localize, encode(self._reply(request, mcl, "scan"))

        return solve

    def _reply(self, request: LocalizeRequest, mcl: MonteCarloLocalizer, source: str) -> LocalizeReply:
        best, cov, hypotheses = hypotheses_message(mcl)
        return LocalizeReply(request_id=request.request_id, robot_id=request.robot_id, stamp=time.time(), source=source,
                             best_pose=best, best_cov=cov,
                             localized=mcl.localized if source == "track" else mcl.dominant(),
                             hypotheses=hypotheses, particles=mcl.count, map_landmarks=mcl.map.count,
                             variant=mcl.variant)

    def stats(self):
        self.pool.put_stats()
        return super().stats()

    def on_stop(self) -> None:
        self.pool.close()

    def _refresh_extra(self) -> None:
        self.extra["robots"] = float(len(self.fleet.robots))
        self.extra["localized"] = float(self.fleet.localized_count())
        self.extra["map_landmarks"] = float(0 if self.fleet.landmarks is None else self.fleet.landmarks.shape[0])


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, MclSettings)


def main(args: argparse.Namespace) -> int:
    settings = settings_from_args(MclSettings, args)
    try:
        service = MclService(settings)
    except (OSError, ValueError) as exc:
        log.error("cannot load the map: %s", exc)
        return 2
    return service.serve()
