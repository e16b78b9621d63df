"""The thin asyncio shell every service runs in (DESIGN §1).

Zenoh callbacks only hand ``(tag, key, payload, arrival time, source)`` to the
service's :class:`~services.intake.Intake` (bounded in bytes, per-kind size
limits checked before anything decodes, one lane per robot session taken in
turn, so a flood only delays its own lane); the numeric core runs in the
service's handler, off the callback thread. The shell counts messages in,
rejections by reason and handling latency, publishes :class:`ServiceStats`
on ``{prefix}/{service}/stats`` and stops cleanly on SIGINT/SIGTERM, closing
the session.

A service subclasses :class:`ServiceShell`, declares its subscriptions and
queryables in :meth:`setup`, handles items in :meth:`handle`, and may run
periodic work in :meth:`tick`. A service fed by robots calls
:meth:`follow_robots` in its setup: the shell then subscribes every robot's
RobotInfo, odometry and scans and their session tokens, keeps the membership
in one :class:`~services.roster.Roster` (taking a robot's messages only from
the session that owns its id, asking a robot for its RobotInfo when it
appears, recognising a new run), hands the admitted robots' events to the
service in stamp order across every stream (a :class:`~services.roster.ReorderBuffer`,
``reorder_window_s``), and calls the service's hooks :meth:`robot_announced`,
:meth:`robot_event`, :meth:`robot_new_run`, :meth:`robot_joined_late`,
:meth:`robot_lost_odometry` and :meth:`robot_left`.

The loop takes the intake's items in batches (at most ``BATCH_ITEMS``) and releases the reorder buffer once per batch
rather than once per message, and before anything that is not a plain stream message: the service sees the same
events and hooks in the same order (``tests/unit/test_shell_batches.py``), for a release's cost that grows with the
fleet paid once per batch.

With ``state_dir`` (central, D-SLAM, MCL) the shell writes a checkpoint every
``checkpoint_period_s`` and on exit (:mod:`services.checkpoint`: the roster,
the events not yet handled, the counters and what the service's
:meth:`checkpoint_state` gives), and on start resumes from the newest valid one
before it subscribes; the robots' publisher caches then send what came after.
"""

from __future__ import annotations

import asyncio
import ctypes
import ctypes.util
import functools
import logging
import os
import signal
import threading
import time
from collections import Counter, deque
from typing import Any

import numpy as np
import zenoh
import zenoh.ext

from schemas.codec import DecodeError, decode
from schemas.config import FleetSettings
from schemas.keys import Keys
from schemas.messages import MclPose, Odometry, RobotInfo, Scan, ServiceStats
from schemas.streams import StreamLimits
from schemas.transport import ConnectError, StreamPublisher, history_query, open_session, replier_zid, sample_source
from services.checkpoint import CheckpointStore, encode_checkpoint
from services.intake import Intake
from services.roster import ReorderBuffer, Roster, StreamEvent, Takeover

ROBOT_TAGS = frozenset({"alive", "gone", "info", "odom", "scan", "refilled", "router_link"})
FIRST_RUN_S = 0.1  # the first stats and tick this soon after setup (s), then every period
ROUTER_LINK_GRACE_S = 2.0  # tokens that go this soon after the router link changed went with the link (s)
LISTENING_TICK_S = 0.05  # the loop tells the reorder buffer it runs this often: a longer gap is a stall (s)
TRIM_AFTER_BYTES = 8 << 20  # a backlog that held this much: once worked off, its freed heap goes back to the system
BATCH_ITEMS = 64  # items the loop takes from the intake per turn (one release of the reorder buffer after them)
STREAM_TAGS = frozenset({"odom", "scan"})
ROBOT_KEYS_CACHED = 4096  # parsed robot keys kept (a flood of made-up robot ids only empties the cache)

log = logging.getLogger(__name__)


@functools.cache
def _malloc_trim():
    """glibc's ``malloc_trim``, or None (musl, macOS)."""
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return None


def _warm_kernels(groups: tuple[str, ...]) -> tuple[float, bool]:
    """(seconds, whether numba compiled them) of :func:`services.compiled.warm_up` of the kernel ``groups``. Imported
    here, not at the top: numba and scipy cost a process about 60 MB and half a second, and the shell's services
    without kernels (monitor, evaluator, viewer) need neither."""
    from services import compiled

    return compiled.warm_up(groups), compiled.AVAILABLE


def release_free_memory() -> bool:
    """Give the heap's free pages back to the system (glibc's ``malloc_trim``); False without glibc. A backlog's
    memory, once worked off, is free but still the process's: a long-running service would keep its peak."""
    trim = _malloc_trim()
    return trim is not None and bool(trim(0))


class ServiceShell:
    """Base of every service process: session, queue, stats, clean stop."""

    name = "service"
    tick_period_s: float | None = None
    uses_kernels: tuple[str, ...] = ()  # numba kernel groups (services.compiled) warmed up before the first subscription

    def __init__(self, settings: FleetSettings, instance: str | None = None):
        self.settings = settings
        self.keys = Keys(settings.prefix)
        self.instance = instance or f"{self.name}-{os.getpid()}"
        self.messages_in: Counter = Counter()
        self.rejected: Counter = Counter()
        self.extra: dict[str, float] = {}
        self.published = 0
        self._latencies_ms: deque[float] = deque(maxlen=2000)
        self._started = time.monotonic()
        self._stop: asyncio.Event | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._wake: asyncio.Event | None = None
        kb = 1024
        self.intake = Intake(int(settings.lane_mb * 2**20), int(settings.queue_mb * 2**20),
                             {"scan": settings.max_scan_kb * kb, "odom": settings.max_message_kb * kb,
                              "info": settings.max_message_kb * kb}, on_first=self._wake_up)
        self._router_link_changed_at = float("-inf")
        self._backlog_bytes = 0  # the most the intake held since memory was last given back
        self._robot_head = f"{settings.prefix}/robots/"
        self._robot_keys: dict[str, tuple[str, str] | None] = {}  # key → Keys.parse_robot_key(key)
        self._in_batch = False  # a batch of the intake's items is being handled (:meth:`_consume_batch`)
        self._release_due = False  # events were pushed into the reorder buffer since its last release
        self._in_hand: list = []  # the batch's (lane, item) pairs ...
        self._in_hand_from = 0  # ... of which these are not handled yet
        self.session: zenoh.Session | None = None
        self._declared: list[Any] = []
        self.roster: Roster | None = None
        self.reorder = ReorderBuffer(settings.reorder_window_s, join_wait_s=settings.join_wait_s,
                                     partition_wait_s=settings.partition_wait_s)
        self._refill_on_return: set[str] = set()  # robots out of reach when asked for their history: asked on return
        self._refill_asked_again: set[str] = set()
        self._release_lock = asyncio.Lock()
        self.hold_ms: deque[float] = deque(maxlen=5000)
        state_dir = getattr(settings, "state_dir", None)
        self.checkpoints = CheckpointStore(state_dir, self.name) if state_dir else None

    def setup(self, session: zenoh.Session) -> None:
        """Declare subscriptions (:meth:`subscribe`), queryables and publishers."""

    async def handle(self, tag: str, key: str, payload: bytes) -> None:
        """Handle one queued sample (decode, validate, call the core, publish)."""

    async def tick(self) -> None:
        """Periodic work (publish an estimate), every ``tick_period_s`` seconds."""

    def on_stop(self) -> None:
        """Last work before the session closes (final publication, report)."""

    # ------------------------------------------------------------ checkpoints
    def checkpoint_state(self) -> dict:
        """What the service holds beyond the roster and the shell's counters (its core, with its random generator),
        for a checkpoint; the objects are pickled as they are, so they must not be touched meanwhile."""
        return {}

    def restore_state(self, state: dict) -> None:
        """Take back what :meth:`checkpoint_state` gave (in a new process, before the session opens)."""

    def checkpoint_summary(self) -> dict:
        """A few figures for the checkpoint's header and the resume log line (robots, landmarks)."""
        return {}

    async def snapshot(self) -> bytes:
        """The service's whole state as checkpoint bytes (a service whose core runs in a worker thread overrides this
        to hold its lock)."""
        state = {"roster": self.roster, "reorder": self.reorder, "messages_in": self.messages_in,
                 "rejected": self.rejected, "published": self.published, "service": self.checkpoint_state()}
        return encode_checkpoint(self.name, state, self.checkpoint_summary())

    async def _write_checkpoint(self) -> None:
        async with self._release_lock:  # not between a release and its events' handling: each is held or handled
            data = await self.snapshot()
        started = time.perf_counter()
        await asyncio.to_thread(self.checkpoints.save, data)
        self.extra["checkpoint_write_ms"] = (time.perf_counter() - started) * 1e3
        self.extra["checkpoint_bytes"] = float(len(data))
        self.count_extra("checkpoints")

    def resume(self) -> None:
        """Take the newest valid checkpoint of ``state_dir`` back, if there is one (files refused on the way are
        logged with their reasons and counted). The robots' publisher caches then send what came after it."""
        found = self.checkpoints.load()
        self.extra["checkpoints_refused"] = float(len(self.checkpoints.refused))
        if found is None:
            log.info("%s: no checkpoint in %s%s: starting afresh", self.name, self.checkpoints.directory,
                     f" ({len(self.checkpoints.refused)} refused)" if self.checkpoints.refused else "")
            return
        state = found.state
        self.roster = state["roster"]
        if self.roster is not None:
            self.roster.resume()
        self.reorder = state["reorder"]
        self.reorder.window_s = self.settings.reorder_window_s
        self.reorder.join_wait_s = self.settings.join_wait_s
        self.reorder.partition_wait_s = self.settings.partition_wait_s
        self.messages_in.update(state["messages_in"])
        self.rejected.update(state["rejected"])
        self.published = state["published"]
        self.restore_state(state["service"])
        self.extra["resumed_checkpoint_age_s"] = found.age_s
        summary = ", ".join(f"{k} {v}" for k, v in found.header.get("summary", {}).items())
        log.info("%s resumed from %s, written %.1f s ago (%s)", self.name, found.path, found.age_s, summary or "empty")

    # ------------------------------------------------------------ robots
    def follow_robots(self) -> None:
        """Subscribe every robot's info, odometry and scans and their session tokens; membership in :attr:`roster`."""
        assert self.session is not None
        if self.roster is None:
            self.roster = Roster()
        settings, roster = self.settings, self.roster
        roster.waiting_bytes = int(settings.waiting_mb * 2**20)
        roster.info_timeout_s = settings.info_timeout_s
        roster.unannounced_bytes = int(settings.unannounced_mb * 2**20)
        roster.unannounced_s = settings.unannounced_s
        roster.dt_tolerance_s = settings.dt_tolerance_s
        roster.tracker.limits = StreamLimits(max_stamp_jump_s=settings.max_stamp_jump_s)
        self.subscribe(self.keys.all_robot_stream("info"), "info", recover=False)
        self.subscribe(self.keys.all_robot_stream("odom"), "odom")
        self.subscribe(self.keys.all_robot_stream("scan"), "scan")

        def on_token(sample: zenoh.Sample) -> None:
            self.enqueue("alive" if sample.kind == zenoh.SampleKind.PUT else "gone", str(sample.key_expr), b"")

        self._declared.append(self.session.liveliness().declare_subscriber(self.keys.session_tokens_any, on_token,
                                                                           history=True))

        def on_transport(event: zenoh.TransportEvent) -> None:
            if event.transport.whatami == zenoh.WhatAmI.ROUTER:
                self._router_link_changed_at = time.monotonic()  # now, for the tokens that go with the link
                self.enqueue("router_link", "open" if event.kind == zenoh.SampleKind.PUT else "closed", b"")

        self._declared.append(self.session.info.declare_transport_events_listener(on_transport))
        # the buffer's times count from now: a resumed one's were the old process's clock, and its recovery window
        # starts when the caches can send (for a fresh buffer this changes nothing)
        self.reorder.restart_clock()
        if self.roster.resumed:
            self.refill_from_robots()

    def _router_link_lost(self) -> bool:
        """Whether this session has no router now, or its link to one changed in the last
        ``ROUTER_LINK_GRACE_S``: a token going away then says nothing about its robot."""
        if time.monotonic() - self._router_link_changed_at < ROUTER_LINK_GRACE_S:
            return True
        try:
            return not list(self.session.info.routers_zid())
        except zenoh.ZError:
            return True

    def ask_info(self, robot_id: str) -> None:
        """Query a robot's RobotInfo (a robot answers late joiners); replies come back through the queue."""
        assert self.session is not None

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is not None:
                self.enqueue("info", str(reply.ok.key_expr), reply.ok.payload.to_bytes(), replier_zid(reply))

        try:
            self.session.get(self.keys.info(robot_id), on_reply, timeout=self.settings.info_timeout_s)
        except zenoh.ZError as exc:
            log.debug("%s: info query for %s failed: %s", self.name, robot_id, exc)

    async def admit(self, robot_id: str, after: float | None = None) -> None:
        """Take a robot in: the events it held go to :meth:`robot_event` in order (with ``after``, only those
        after that stamp; the others are counted)."""
        await self.admit_all([robot_id], after)

    async def admit_all(self, robot_ids: list[str], after: float | None = None) -> None:
        """Take several robots in at once: their held events go out in stamp order together, not one robot's
        backlog before the other's."""
        for robot_id in robot_ids:
            events, dropped = self.roster.admit(robot_id, after)
            if dropped:
                self.rejected["before_placement"] += dropped
            for event in events:
                self.reorder.push(event)
        await self.release_events()

    async def release_events(self, flush: bool = False) -> None:
        """Hand :meth:`robot_event` the events the reorder buffer releases: in stamp order across the streams of
        the robots alive and admitted, each once the streams behind it have passed it or stopped being waited for
        (:class:`~services.roster.ReorderBuffer` says how long each is; every one when ``flush``)."""
        async with self._release_lock:  # one release at a time: a robot's events are handled one after the other
            self._release_due = False
            alive, live = self.roster.alive_and_live()
            queued = {lane[0] for lane in self.intake.lanes() if isinstance(lane, tuple)}
            queued.update(lane[0] for lane, _ in self._in_hand[self._in_hand_from:] if isinstance(lane, tuple))
            due = self.reorder.release(live, flush, announced=alive, queued=queued)
            for index, (event, arrived) in enumerate(due):
                self.hold_ms.append((time.perf_counter() - arrived) * 1e3)
                try:
                    await self.robot_event(event)
                except asyncio.CancelledError:  # a stop between two events: the rest is held again for the last flush
                    self.reorder.put_back(due[index + 1:])
                    raise

    async def _listening(self) -> None:
        """Tell the reorder buffer the loop runs; a stall of this service (``stalls``, the longest in
        ``stall_ms_max``) is not counted as silence of the robots' streams."""
        stall = self.reorder.listening()
        if stall:
            self.count_extra("stalls")
            self.extra["stall_ms_max"] = max(self.extra.get("stall_ms_max", 0.0), stall * 1e3)

    async def robot_announced(self, info: RobotInfo) -> None:
        """A robot announced itself (first RobotInfo of its run): take it in (:meth:`admit`) now or later."""
        await self.admit(info.robot_id)

    async def robot_event(self, event: StreamEvent) -> None:
        """One odometry or scan event of an admitted robot, in stamp order (:meth:`release_events`). An override that
        awaits must still handle the event when its task is cancelled meanwhile (a stop: D-SLAM shields its scan),
        since the events after it are held again and this one is not."""

    def robot_new_run(self, robot_id: str) -> None:
        """A robot that left started a new run (seq 0 again): forget what the core holds of it."""

    def robot_joined_late(self, robot_id: str) -> None:
        """A robot's first odometry arrived with seq > 0: its announced start pose no longer holds."""

    def robot_left(self, robot_id: str) -> None:
        """A robot's liveliness token went away (it may be back after a link cut)."""

    def robot_lost_odometry(self, robot_id: str) -> None:
        """Odometry of a robot was lost for good (more than the publishers' caches held): the pose the service
        holds for it no longer follows the robot."""

    def _stream_gap(self, robot_id: str, stream: str, lost: int) -> None:
        """A stream skipped ``lost`` messages for good: counted (the roster's ``missing``), said, and a gap in the
        odometry handed to :meth:`robot_lost_odometry`."""
        log.warning("%s: robot %s lost %d %s message(s) for good (more than the publishers' caches held)%s", self.name,
                    robot_id, lost, stream, "; its pose is placed again" if stream == "odom" else "")
        if stream == "odom":
            self.roster.counts["odometry_gaps"] += 1
            self.robot_lost_odometry(robot_id)

    async def _robot_item(self, tag: str, key: str, payload: bytes, source: str | None = None) -> None:
        roster = self.roster
        if tag == "router_link":
            log.info("%s: the link to the router %s; every robot stream is waited for while it is recovered",
                     self.name, "opened again" if key == "open" else "closed")
            self.reorder.link_changed()
            return
        if tag in ("alive", "gone"):
            token = self.keys.parse_session_token(key)
            if token is None:
                self.reject("bad_key", key)
            elif tag == "alive":
                takeover, refused = roster.on_token(*token)
                if refused:
                    self.reject(*refused)
                else:
                    self.reorder.announce(token[0])
                await self._take_over(token[0], takeover)
            else:
                takeover, left = roster.on_token_gone(*token)
                if left:
                    log.info("%s: robot %s left (its state stays, for a return after a link cut)", self.name, token[0])
                    self.robot_left(token[0])
                    if self._router_link_lost():  # every token goes with the router: its streams will come back
                        self.reorder.link_changed()
                    await self.release_events()
                await self._take_over(token[0], takeover)
            return
        parsed = self._robot_keys.get(key, False)
        if parsed is False:
            if len(self._robot_keys) >= ROBOT_KEYS_CACHED:
                self._robot_keys.clear()
            parsed = self._robot_keys[key] = self.keys.parse_robot_key(key)
        if parsed is None:
            self.reject("bad_key", key)
            return
        rid = parsed[0]
        if tag == "refilled":  # the robot's kept messages first, then the gaps still left are counted as lost
            replies, dropped = payload
            if dropped:
                self.reject("history_overflow", f"{rid}: {dropped} kept message(s) past {self.intake.lane_bytes} bytes",
                            dropped)
            for stream, reply_key, reply, replier in replies:
                self.messages_in[stream] += 1
                try:
                    await self._robot_item(stream, reply_key, reply, replier)
                except DecodeError as error:
                    self.reject_decode(error)
                except Exception:  # noqa: BLE001 - as in the loop: one bad reply must not keep the gaps parked
                    self.reject("handler_error")
                    log.exception("%s: handler failed on %s (history of %s)", self.name, reply_key, rid)
                await asyncio.sleep(0)  # a long answer (a minute of a robot's stream) must not hold stats and ticks
            if not replies and rid not in self._refill_asked_again:
                # nobody answered: the robot is out of reach (a link cut: a query routed into it is lost), not
                # without history; its messages past the gap stay parked and it is asked once more as soon as one of
                # its messages arrives (it is in reach again); the second answer is final
                log.info("%s: robot %s did not answer for its history (out of reach?); asked again when it is heard",
                         self.name, rid)
                self._refill_on_return.add(rid)
                return
            self._refill_asked_again.discard(rid)
            for arrival, stream in roster.refilled(rid):
                await self._take(rid, stream, arrival)
            return
        if rid in self._refill_on_return and tag in STREAM_TAGS:  # heard again: asked once more for its history
            self._refill_on_return.discard(rid)
            self._refill_asked_again.add(rid)
            log.info("%s: robot %s is heard again: asked once more for its history", self.name, rid)
            self.refill_robot(rid)
        message = decode(payload, RobotInfo if tag == "info" else Odometry if tag == "odom" else Scan)
        whose, refused = roster.identify(rid, tag, message, source, len(payload))
        if refused:
            self.reject(*refused)
        if whose == "own":
            await self._owned_item(rid, tag, message, source)

    async def _take_over(self, rid: str, takeover: Takeover | None) -> None:
        """A session now owns robot ``rid``: take what it sent while no session held the id."""
        if takeover is None:
            return
        if takeover.not_owner:
            self.rejected["not_owner"] += takeover.not_owner
        if takeover.ask_info:
            self.ask_info(rid)
        for tag, message, source in takeover.take:
            await self._owned_item(rid, tag, message, source)

    async def _owned_item(self, rid: str, tag: str, message, source: str | None) -> None:
        """A RobotInfo, odometry or scan from the session that owns ``rid``."""
        roster = self.roster
        if tag == "info":
            announced, refused = roster.on_info(rid, message)
            if refused:
                self.reject(*refused)
            elif announced:
                log.info("%s: robot %s announced (%s, start pose %s)", self.name, rid, message.source,
                         "known" if message.start_pose is not None else "unknown")
                await self.robot_announced(message)
            return
        if message.seq == 0:  # it may start a new run, which takes the robot out before _take acts on it
            await self._release_deferred()
        arrival = roster.on_stream(rid, tag, message, source)
        await self._take(rid, tag, arrival)
        for follower in roster.unparked(rid, tag):
            await self._take(rid, tag, follower)

    async def _take(self, rid: str, stream: str, arrival) -> None:
        """Act on what the roster made of one stream message (:class:`~services.roster.Arrival`)."""
        roster = self.roster
        if arrival.new_run or arrival.late or arrival.gap:  # the service acts: on the events due before, as always
            await self._release_deferred()
        if arrival.new_run:
            log.info("%s: robot %s started a new run; it rejoins from its RobotInfo", self.name, rid)
            self.reorder.drop_robot(rid)
            self.robot_new_run(rid)
        if arrival.refused:
            self.reject(*arrival.refused)
        if arrival.late:
            log.warning("%s: robot %s: its first odometry messages were missed", self.name, rid)
            self.robot_joined_late(rid)
        elif arrival.gap:
            self._stream_gap(rid, stream, arrival.gap)
        if arrival.ask_info:
            self.ask_info(rid)
        if arrival.event is not None:
            if roster.is_admitted(rid):
                self.reorder.push(arrival.event)
                self._release_due = True
                if not self._in_batch:  # in a batch: released after it, or before the service acts otherwise
                    await self.release_events()
            else:
                refused = roster.keep(arrival.event)
                if refused:
                    self.reject(*refused)

    def refill_from_robots(self) -> None:
        """Restored from a checkpoint: ask every robot the roster knows for the odometry and scans it kept, so that
        what came after the checkpoint arrives whole even when the caches' history misses some of it at
        subscription; messages past a gap wait (:meth:`Roster.refill`) until the answer is in.

        The replies are gathered and queued as one ``refilled`` item when the query is over, handled before the gaps
        left are counted: queued one by one, in the lane of the robot's session, they could still wait behind its
        live messages when the end of the query, in another lane, was taken, and a gap the robot had filled was
        counted as lost. What is gathered is bounded by a lane's bytes (past them counted ``history_overflow``)."""
        for rid in sorted(self.roster.members):
            self.refill_robot(rid)

    def refill_robot(self, rid: str) -> None:
        """Ask one robot for what it kept (see :meth:`refill_from_robots`)."""
        timeout_s = self.reorder.recovery_window_s
        self.roster.refill(rid)
        key = self.keys.history(rid)
        replies: list[tuple[str, str, bytes, str | None]] = []
        budget = {"bytes": self.intake.lane_bytes, "dropped": 0}

        def on_payload(reply_key: str, payload: bytes, replier: str | None) -> None:
            parsed = self.keys.parse_robot_key(reply_key)
            if parsed is None or parsed[1] not in STREAM_TAGS:
                return
            if len(payload) > budget["bytes"]:
                budget["dropped"] += 1
                return
            budget["bytes"] -= len(payload)
            replies.append((parsed[1], reply_key, payload, replier))

        def on_done() -> None:
            self.enqueue("refilled", key, (replies, budget["dropped"]))

        try:
            history_query(self.session, key, on_payload, on_done, timeout_s)
        except zenoh.ZError as exc:
            log.warning("%s: cannot ask %s for its history: %s", self.name, rid, exc)
            self.enqueue("refilled", key, ([], 0))

    def subscribe(self, key: str, tag: str, recover: bool = True) -> None:
        """Subscribe ``key``; each sample is queued as ``(tag, key, payload)``.

        With the setting ``subscriber_recovery`` on (and ``recover``), this is
        an advanced subscriber: at start it fetches the publishers' caches (what
        a service that starts late or restarts missed), and heartbeats tell it
        which samples it missed later (a link cut, a router restart), which it
        then queries from the caches, so every stream arrives complete and in order.

        Late publishers are found by their heartbeats, not by zenoh-ext's
        ``detect_late_publishers``: with it, under load, the start-up history of
        a publisher was lost in 5 of 56 trials (its liveliness-triggered query
        races the initial one); without it, in none of 112.
        """
        assert self.session is not None and self._loop is not None
        if recover and self.settings.subscriber_recovery:
            subscriber = zenoh.ext.declare_advanced_subscriber(
                self.session, key, self._enqueuer(tag),
                history=zenoh.ext.HistoryConfig(detect_late_publishers=False),
                recovery=zenoh.ext.RecoveryConfig(heartbeat=True),
                subscriber_detection=True,
            )
        else:
            subscriber = self.session.declare_subscriber(key, self._enqueuer(tag))
        self._declared.append(subscriber)

    def _enqueuer(self, tag: str):
        intake = self.intake

        def callback(sample: zenoh.Sample) -> None:
            if intake.oversize(tag, len(sample.payload)):  # refused before it is even copied
                return
            self.enqueue(tag, str(sample.key_expr), sample.payload.to_bytes(), sample_source(sample))

        return callback

    def enqueue(self, tag: str, key: str, payload, source: str | None = None, nbytes: int | None = None) -> None:
        """Queue an item from any thread (subscriptions, liveliness, replies, queries...): a robot's messages in the
        lane of (robot, publishing session), anything else in the lane of its tag; counted when refused. ``nbytes``
        sizes a payload that is not bytes (default: its length if bytes, else 0)."""
        head = self._robot_head
        lane = (key[len(head):].split("/", 1)[0], source) if tag in ROBOT_TAGS and key.startswith(head) else tag
        if nbytes is None:
            nbytes = len(payload) if isinstance(payload, (bytes, bytearray)) else 0
        self.intake.put(tag, lane, (tag, key, payload, time.perf_counter(), source), nbytes)

    def _wake_up(self) -> None:
        """The intake was empty and got an item: wake the consumer (from any thread)."""
        if self._loop is not None and self._wake is not None:
            try:
                self._loop.call_soon_threadsafe(self._wake.set)
            except RuntimeError:
                pass  # the loop is closing: the service is stopping

    def publisher(self, key: str) -> StreamPublisher:
        """A publisher of the service's output; unless ``publisher_cache`` says otherwise it caches its latest
        sample, for a receiver that starts late or was cut off."""
        assert self.session is not None
        cache = 1 if self.settings.publisher_cache is None else self.settings.publisher_cache
        pub = StreamPublisher(self.session, key, cache=cache)
        self._declared.append(pub)
        return pub

    def count_extra(self, name: str) -> None:
        """One more of an event the stats' ``extra`` counts (a checkpoint written, a robot placed again...)."""
        self.extra[name] = self.extra.get(name, 0.0) + 1.0

    def reject(self, reason: str, detail: str = "", count: int = 1) -> None:
        """Count ``count`` rejected messages by reason (and log the first few of each)."""
        before = self.rejected[reason]
        self.rejected[reason] += count
        if before < 3:
            log.warning("%s rejected a message (%s)%s", self.name, reason, f": {detail}" if detail else "")

    def localized_mcl_pose(self, payload: bytes, key: str) -> MclPose | None:
        """An MclPose that says its robot is localized (DecodeError if malformed); None otherwise, and counted
        ``robot_id_mismatch`` when it is not on its robot's key (the mapping services place robots with it)."""
        message = decode(payload, MclPose)
        if not self.key_names_robot(key, message.robot_id, 1):  # {prefix}/mcl/{rid}/pose
            return None
        return message if message.localized else None

    def key_names_robot(self, key: str, robot_id: str, position: int) -> bool:
        """Whether ``key`` names the message's robot (``position`` counts segments after the prefix); a message on
        another robot's key is refused as ``robot_id_mismatch``."""
        parts = key[len(self.settings.prefix) + 1:].split("/")
        if len(parts) <= position or parts[position] != robot_id:
            self.reject("robot_id_mismatch", f"{key} carries {robot_id}")
            return False
        return True

    def reject_decode(self, error: DecodeError) -> None:
        self.reject(error.reason, error.detail)

    def call_in_loop(self, work, *args) -> None:
        """Run ``work(*args)`` in the service's loop, where its state and counters live, from any thread (at once
        when no loop runs: tests of a service's parts); nothing when the loop is closing."""
        if self._loop is None:
            work(*args)
            return
        try:
            self._loop.call_soon_threadsafe(work, *args)
        except RuntimeError:
            pass  # the loop is closing: the service is stopping

    def put_timing(self, name: str, values_ms) -> None:
        """``{name}_median`` and ``{name}_p99`` of recent durations into the stats' extra (nothing while empty)."""
        if values_ms:
            array = np.asarray(values_ms)
            self.extra[f"{name}_median"] = float(np.median(array))
            self.extra[f"{name}_p99"] = float(np.percentile(array, 99))

    def stats(self) -> ServiceStats:
        lat = np.asarray(self._latencies_ms) if self._latencies_ms else np.zeros(1)
        self.rejected.update(self.intake.take_refused())
        self.extra["intake_bytes"] = float(self.intake.held_bytes)
        self.extra["intake_peak_bytes"] = float(self.intake.peak_bytes)
        if self.roster is not None:
            self.extra["unannounced_waiting"] = float(self.roster.pending_count())
            self.extra.update({k: float(v) for k, v in self.roster.counts.items()})
            self.extra["missing"] = float(self.roster.missing())
            self.extra["waiting"] = float(self.roster.waiting_count())
            self.extra["robots_alive"] = float(len(self.roster.alive_ids()))
            self.extra["buffered"] = float(len(self.reorder))
            self.put_timing("hold_ms", self.hold_ms)
        return ServiceStats(
            service=self.name,
            instance=self.instance,
            stamp=time.time(),
            uptime_s=time.monotonic() - self._started,
            messages_in=dict(self.messages_in),
            rejected=dict(self.rejected),
            published=self.published,
            latency_ms_median=float(np.median(lat)),
            latency_ms_p99=float(np.percentile(lat, 99)),
            queue_depth=len(self.intake),
            extra=dict(self.extra),
        )

    def stop(self) -> None:
        if self._loop is not None and self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)

    async def _consume(self) -> None:
        assert self._wake is not None
        while True:
            await asyncio.sleep(0)  # a non-empty intake never suspends: yield so stop, ticks and stats still run
            self._wake.clear()
            batch = self.intake.get_many(BATCH_ITEMS)
            if not batch:
                await self._wake.wait()
                continue
            await self._consume_batch(batch)

    async def _consume_batch(self, batch: list) -> None:
        """Handle a batch of the intake's items, in order, with one release of the reorder buffer after the odometry
        and scans, not one per message (a release asks every robot's streams, a cost that grows with the fleet):
        every other item (tokens, RobotInfo, the service's own) and every stream message that makes the service act
        (a new run, a late join, a gap) first releases what is due, as a release after each message would have. The
        batch's items not handled yet count as queued for their robots, as they did in the intake. The latency of
        each item runs to the end of the batch: its event handed on."""
        self._in_hand, self._in_batch = batch, True
        try:
            for index, (_lane, (tag, key, payload, _arrived, source)) in enumerate(batch):
                self._in_hand_from = index + 1
                self.messages_in[tag] += 1
                try:
                    if tag not in STREAM_TAGS:
                        await self._release_deferred()
                    if self.roster is not None and tag in ROBOT_TAGS:
                        await self._robot_item(tag, key, payload, source)
                    else:
                        await self.handle(tag, key, payload)
                except DecodeError as error:
                    self.reject_decode(error)
                except Exception:  # noqa: BLE001 - one bad message must never kill the service
                    self.reject("handler_error")
                    log.exception("%s: handler failed on %s", self.name, key)
            self._in_batch = False
            await self._release_deferred()
        finally:
            self._in_hand, self._in_hand_from, self._in_batch = [], 0, False
        now = time.perf_counter()
        self._latencies_ms.extend((now - item[3]) * 1e3 for _lane, item in batch)

    async def _release_deferred(self) -> None:
        """Release the reorder buffer if events were pushed since its last release (:meth:`_consume_batch`); a
        failure is counted as the message that pushed them would have been (``handler_error``)."""
        if self._release_due:
            try:
                await self.release_events()
            except Exception:  # noqa: BLE001 - one bad message must never kill the service
                self.reject("handler_error")
                log.exception("%s: handler failed on a release of events", self.name)

    async def _every(self, period: float, work, first_after: float | None = None) -> None:
        """Run ``work`` every ``period`` seconds; the first time after ``first_after`` (default: one period)."""
        delay = period if first_after is None else first_after
        while True:
            await asyncio.sleep(delay)
            delay = period
            try:
                await work()
            except Exception:  # noqa: BLE001
                log.exception("%s: periodic work failed", self.name)

    async def _publish_stats(self) -> None:
        self._backlog_bytes = max(self._backlog_bytes, self.intake.take_high_water())
        if self._backlog_bytes >= TRIM_AFTER_BYTES and len(self.intake) == 0:
            self._backlog_bytes = 0
            if release_free_memory():
                self.count_extra("memory_trims")
        if self.roster is not None:
            dropped = self.roster.expire_pending()
            if dropped:
                self.reject("unannounced_dropped", f"{dropped} message(s) of robot ids no session held for "
                            f"{self.roster.unannounced_s:g} s", dropped)
        self._stats_pub.put(self.stats())

    def _install_signal_handlers(self) -> dict:
        """SIGINT/SIGTERM stop the service.

        Python-level handlers, not ``loop.add_signal_handler``: under a flood of
        samples the loop's self-pipe is full of wake-ups, the signal byte is lost
        and a loop-level handler never runs; a Python-level handler always does.
        """
        if threading.current_thread() is not threading.main_thread():
            return {}  # tests drive stop() instead
        previous = {}
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, lambda *_: self.stop())
        return previous

    def serve(self) -> int:
        """Run until a signal (or the settings' ``duration``): the exit code, 2 when the router cannot be reached."""
        try:
            asyncio.run(self.run(getattr(self.settings, "duration", None)))
        except ConnectError as exc:
            log.error("%s", exc)
            return 2
        return 0

    async def run(self, duration: float | None = None) -> None:
        """Open the session, set up, consume until a signal (or ``duration``), close."""
        self._loop = asyncio.get_running_loop()
        self._wake = asyncio.Event()
        self._stop = asyncio.Event()
        previous_handlers = self._install_signal_handlers()
        # the kernels load (or compile) while the checkpoint is read and the router reached; nothing that uses them
        # runs before setup subscribes
        warming = asyncio.create_task(asyncio.to_thread(_warm_kernels, self.uses_kernels)) if self.uses_kernels \
            else None
        if self.checkpoints is not None:
            self.resume()
        try:
            self.session = await asyncio.to_thread(open_session, self.settings)
        finally:
            if warming is not None:
                warm_up_s, with_numba = await warming
                self.extra["kernel_warm_up_s"] = warm_up_s
                log.info("%s: kernels ready in %.2f s (%s)", self.name, warm_up_s,
                         "numba" if with_numba else "numpy references: numba is not installed")
        tasks: list[asyncio.Task] = []
        try:
            self._stats_pub = StreamPublisher(self.session, self.keys.stats(self.name))
            self.setup(self.session)
            log.info("%s ready (%s)", self.instance, self.settings.zenoh_connect)
            tasks.append(asyncio.create_task(self._consume()))
            # the first stats and estimate soon after setup: a restarted service shows itself and its resumed state
            tasks.append(asyncio.create_task(self._every(self.settings.stats_period_s, self._publish_stats,
                                                         first_after=min(FIRST_RUN_S, self.settings.stats_period_s))))
            if self.tick_period_s:
                tasks.append(asyncio.create_task(self._every(self.tick_period_s, self.tick,
                                                             first_after=min(FIRST_RUN_S, self.tick_period_s))))
            if self.checkpoints is not None:
                tasks.append(asyncio.create_task(self._every(self.settings.checkpoint_period_s, self._write_checkpoint)))
            if self.roster is not None:  # events whose wait ran out while no message came
                tasks.append(asyncio.create_task(self._every(max(self.settings.reorder_window_s, 0.02),
                                                             self.release_events)))
                tasks.append(asyncio.create_task(self._every(LISTENING_TICK_S, self._listening)))
            if duration is not None:
                self._loop.call_later(duration, self._stop.set)
            await self._stop.wait()
            log.info("%s stopping", self.instance)
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            try:
                if self.roster is not None:
                    await self.release_events(flush=True)
                self.on_stop()
                if self.checkpoints is not None:
                    path = await asyncio.to_thread(self.checkpoints.save, await self.snapshot())
                    log.info("%s: final checkpoint %s", self.name, path)
                self._stats_pub.put(self.stats())
            except Exception:  # noqa: BLE001
                log.exception("%s: final work failed", self.name)
            for entity in self._declared:
                try:
                    entity.undeclare()
                except Exception:  # noqa: BLE001
                    pass
            self.session.close()
            for sig, handler in previous_handlers.items():
                signal.signal(sig, handler)
