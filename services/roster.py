"""Robot membership and cross-robot ordering, written once for every service (no Zenoh here).

:class:`Roster` is what central FastSLAM, D-SLAM and MCL know about the fleet:
which robots are alive (liveliness), which have announced themselves
(RobotInfo), and which the service has taken in. It turns each stream message
into the core's event:

- a robot id belongs to one Zenoh session: the first that holds the robot's
  session token (:meth:`Keys.session_token`); the robot's RobotInfo and streams
  are taken from that session only (``not_owner``), a second session announcing
  a live id is refused (``second_announcer``), and the messages of an id no
  session holds wait at most ``unannounced_s`` within ``unannounced_bytes`` (all
  such ids together) for a token, then go (``unannounced_dropped``);
- the message's robot id must match its key, and its stream must be in order
  and plausible (:class:`~schemas.streams.StreamTracker`: duplicates, out-of-order,
  time going backwards and jumps in seq or stamp beyond its limits are refused
  with the reason, gaps counted; :func:`~schemas.streams.odometry_doubt`: a dt
  that disagrees with the stamps, a control beyond the announced limits);
- a robot whose stream starts again at seq 0 from another Zenoh session (a
  restarted process), or, the session unknown, after its token went away, is
  a new run: the roster forgets its RobotInfo and the service resets what it
  holds of it; a robot back after a link cut goes on with its seq numbers;
- a robot's events wait (at most ``waiting_bytes`` of them, the oldest dropped
  and counted) until it has announced itself and the service admits it — at
  once, or later (central waits for MCL to place a robot with no start pose);
- a gap in a stream (messages lost for good: more than the publishers' caches
  held) is reported with the message after it, so the service can re-place the
  robot;
- after a service restart from a checkpoint (:meth:`Roster.resume`), what the
  publishers' caches send again up to the checkpointed seq of each stream is
  recognised as already held and counted (``already_held``), not refused;
  while a robot's kept messages are being fetched (:meth:`Roster.refill`), a
  message past a gap is parked until the gap is filled or the fetch is over;
- it says when to ask a robot for its RobotInfo: when its token appears, and
  again every ``info_timeout_s`` while its messages come unannounced.

:class:`ReorderBuffer` releases events of several robots in stamp order,
holding each at most a wall-time window.
"""

from __future__ import annotations

import bisect
import heapq
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Callable, Iterable

from schemas.contract import OdomEvent, ScanEvent, event_nbytes, stream_event
from schemas.messages import Odometry, RobotInfo, Scan
from schemas.streams import StreamLimits, StreamTracker, Verdict, odometry_doubt

StreamEvent = OdomEvent | ScanEvent
# After a restart both the caches' history (at subscription) and the robot's history queryable send what came after
# the checkpoint, in no fixed order: for this long after the robot's answer is in, a repeat of a seq already taken
# from the same session is counted as already held, not refused as a duplicate.
REPEAT_GRACE_S = 10.0


@dataclass
class Member:
    """What the roster knows of one robot."""

    info: RobotInfo | None = None
    alive: bool = False
    admitted: bool = False
    waiting: deque = field(default_factory=deque)
    waiting_bytes: int = 0
    asked_at: float = float("-inf")


@dataclass
class Takeover:
    """A session now owns a robot id (its token appeared first, or the owner's went and it held one too): whether to
    ask the robot for its RobotInfo now, the messages that waited for a token that this session sent (to be taken
    now, in order, as ``(tag, message, source)``), and how many waiting ones other sessions sent (refused)."""

    ask_info: bool = False
    take: list = field(default_factory=list)
    not_owner: int = 0


@dataclass
class Arrival:
    """What became of one stream message: its event (None when refused or held), or the reason it was refused;
    whether it started a new run of its robot, whether the robot joined late (its first odometry has seq > 0),
    how many messages of the stream were lost just before it (``gap``), and whether the robot should be asked for
    its RobotInfo now."""

    event: StreamEvent | None = None
    refused: tuple[str, str] | None = None
    new_run: bool = False
    late: bool = False
    gap: int = 0
    ask_info: bool = False


class Roster:
    """Membership of every robot a service hears of (see the module docstring)."""

    def __init__(self, waiting_bytes: int = 64 << 20, info_timeout_s: float = 2.0,
                 clock: Callable[[], float] = time.monotonic, unannounced_bytes: int = 8 << 20,
                 unannounced_s: float = 30.0, limits: StreamLimits = StreamLimits(), dt_tolerance_s: float = 0.1):
        self.waiting_bytes = waiting_bytes
        self.info_timeout_s = info_timeout_s
        self.clock = clock
        self.unannounced_bytes = unannounced_bytes
        self.unannounced_s = unannounced_s
        self.dt_tolerance_s = dt_tolerance_s
        self.tracker = StreamTracker(limits=limits)
        self.holders: dict[str, list[str]] = {}  # robot → Zenoh sessions holding its session token, first = owner
        self.last_owner: dict[str, str] = {}  # robot → the session that owned it last (its tail may come after its token)
        self.pending: dict[str, deque] = {}  # robot no session holds → (since, tag, message, source, nbytes) waiting
        self.pending_bytes = 0
        self.members: dict[str, Member] = {}
        self.counts: Counter = Counter()
        self.resumed: dict[tuple[str, str], int] = {}  # (robot, stream) → last seq held by the checkpoint resumed from
        self.refilling: set[str] = set()  # robots whose kept messages were asked for after a restart, not yet in
        self.repeats_until: dict[str, float] = {}  # robot → until when a repeat of a taken seq is already held
        self.parked: dict[tuple[str, str], dict[int, tuple[Odometry | Scan, str | None]]] = {}  # past a gap, waiting

    # ------------------------------------------------------------ queries
    def member(self, robot_id: str) -> Member:
        return self.members.setdefault(robot_id, Member())

    def info(self, robot_id: str) -> RobotInfo | None:
        member = self.members.get(robot_id)
        return None if member is None else member.info

    def is_admitted(self, robot_id: str) -> bool:
        member = self.members.get(robot_id)
        return member is not None and member.admitted

    def alive_ids(self) -> list[str]:
        return [rid for rid, member in self.members.items() if member.alive]

    def alive_and_live(self) -> tuple[set[str], set[str]]:
        """(the robots alive, those of them admitted): whose streams the reorder buffer waits for."""
        alive, live = set(), set()
        for rid, member in self.members.items():
            if member.alive:
                alive.add(rid)
                if member.admitted:
                    live.add(rid)
        return alive, live

    def waiting_count(self) -> int:
        return sum(len(member.waiting) for member in self.members.values())

    def missing(self) -> int:
        return self.tracker.missing()

    def __setstate__(self, state: dict) -> None:
        """A roster from a checkpoint written before identity checks existed gets their empty state."""
        defaults = {"unannounced_bytes": 8 << 20, "unannounced_s": 30.0, "dt_tolerance_s": 0.1, "holders": {},
                    "last_owner": {}, "pending": {}, "pending_bytes": 0}
        self.__dict__.update({**defaults, **state})

    def resume(self) -> None:
        """This roster was just restored from a checkpoint in a new process: no robot has been asked for its
        RobotInfo yet, and what the publishers' caches send again up to each stream's seq in the checkpoint is
        already held (counted as ``already_held``, not refused). Robots stay alive as they were: their recovered
        streams are waited for, and a robot that went meanwhile no longer holds events back once its streams have
        been silent for the reorder buffer's recovery window (its token is simply not seen again)."""
        for member in self.members.values():
            member.asked_at = float("-inf")
        self.resumed = {key: state.last_seq for key, state in self.tracker.streams.items()}
        for rid, holders in self.holders.items():  # the tokens are seen afresh (liveliness history) in this process
            self.last_owner[rid] = holders[0]
        self.holders = {}

    # ------------------------------------------------------------ liveliness
    def on_gone(self, robot_id: str) -> None:
        """A robot's token went away: its state stays (its last messages may still be queued, or it is back
        after a link cut); a new run of it is recognised when its streams start again at seq 0."""
        self.member(robot_id).alive = False
        self.tracker.leave(robot_id)
        self.counts["robots_lost"] += 1

    # ------------------------------------------------------------ identity
    def owner(self, robot_id: str) -> str | None:
        """The Zenoh session that owns the robot id now (None when no session holds its token)."""
        holders = self.holders.get(robot_id)
        return holders[0] if holders else None

    def on_token(self, robot_id: str, zid: str) -> tuple[Takeover | None, tuple[str, str] | None]:
        """Session ``zid`` declared the robot's session token: (the takeover when it now owns the robot, the
        refusal when another session owns it already)."""
        holders = self.holders.setdefault(robot_id, [])
        if zid in holders:
            return None, None
        holders.append(zid)
        if len(holders) > 1:
            return None, ("second_announcer", f"{robot_id} belongs to session {holders[0]}; {zid} announced it too")
        self.member(robot_id).alive = True
        return self._take_over(robot_id), None

    def on_token_gone(self, robot_id: str, zid: str) -> tuple[Takeover | None, bool]:
        """Session ``zid`` no longer holds the robot's token: (the takeover when another session holding it now owns
        the robot, True when no session holds it any more: the robot left)."""
        holders = self.holders.get(robot_id, [])
        if zid not in holders:
            return None, False
        was_owner = holders[0] == zid
        holders.remove(zid)
        if holders:
            return (self._take_over(robot_id) if was_owner else None), False
        del self.holders[robot_id]
        self.on_gone(robot_id)
        return None, True

    def _take_over(self, robot_id: str) -> Takeover:
        owner = self.holders[robot_id][0]
        self.last_owner[robot_id] = owner
        takeover = Takeover()
        member = self.member(robot_id)
        takeover.ask_info = member.info is None and self._ask(member)
        for _since, tag, message, source, nbytes in self.pending.pop(robot_id, ()):
            self.pending_bytes -= nbytes
            if source == owner:
                takeover.take.append((tag, message, source))
            else:
                takeover.not_owner += 1
        return takeover

    def identify(self, robot_id: str, tag: str, message, source: str | None, nbytes: int) -> tuple[str, tuple | None]:
        """Whose message is this: ``("own", None)`` from the robot's owner (or, no session holding its token now,
        from its last owner: a tail recovered after its token went), ``("held", None)`` kept until a session holds
        the robot's token, ``("refused", reason)`` otherwise."""
        owner = self.owner(robot_id)
        if owner is None and source == self.last_owner.get(robot_id):
            owner = source
        if owner is not None:
            if source == owner:
                return "own", None
            if source is None:
                return "refused", ("no_source", f"a {tag} message for {robot_id} names no publishing session")
            return "refused", ("not_owner", f"a {tag} message for {robot_id} from session {source}, not its owner {owner}")
        if nbytes > self.unannounced_bytes:
            return "refused", ("unannounced_dropped", f"{robot_id} is held by no session and its {tag} is too large")
        self.pending.setdefault(robot_id, deque()).append((self.clock(), tag, message, source, nbytes))
        self.pending_bytes += nbytes
        dropped = self._drop_pending(lambda since: self.pending_bytes > self.unannounced_bytes)
        if dropped:
            return "held", ("unannounced_dropped", f"{dropped} message(s) of robot ids no session holds went (over "
                            f"{self.unannounced_bytes / 2**20:g} MB)", dropped)
        return "held", None

    def expire_pending(self) -> int:
        """Drop what waited longer than ``unannounced_s`` for a session to hold its robot id; how many went."""
        horizon = self.clock() - self.unannounced_s
        return self._drop_pending(lambda since: since < horizon)

    def _drop_pending(self, drop: Callable[[float], bool]) -> int:
        """Drop the oldest waiting messages while ``drop(their arrival)`` holds; counted as ``unannounced_dropped``."""
        dropped = 0
        while self.pending:
            rid, queue = min(self.pending.items(), key=lambda item: item[1][0][0])
            if not drop(queue[0][0]):
                break
            self.pending_bytes -= queue.popleft()[4]
            dropped += 1
            if not queue:
                del self.pending[rid]
        self.counts["unannounced_dropped"] += dropped
        return dropped

    def pending_count(self) -> int:
        return sum(len(queue) for queue in self.pending.values())

    # ------------------------------------------------------------ announcements
    def on_info(self, key_robot_id: str, info: RobotInfo) -> tuple[bool, tuple[str, str] | None]:
        """A RobotInfo on ``key_robot_id``'s key: (True when the robot is announced for the first time of its
        run — the service then decides whether to admit it, refusal reason or None)."""
        if info.robot_id != key_robot_id:
            return False, ("robot_id_mismatch", f"{info.robot_id} on the info key of {key_robot_id}")
        member = self.member(key_robot_id)
        if member.info is not None:
            return False, None
        member.info = info
        return True, None

    def admit(self, robot_id: str, after: float | None = None) -> tuple[list[StreamEvent], int]:
        """The service took the robot in: its events flow from now on. Returns the events it held, in order,
        and how many were dropped: with ``after``, those not after that stamp (a robot placed at that time)."""
        member = self.member(robot_id)
        member.admitted = True
        held = list(member.waiting)
        member.waiting.clear()
        member.waiting_bytes = 0
        kept = held if after is None else [event for event in held if event.stamp > after]
        return kept, len(held) - len(kept)

    def hold(self, robot_id: str) -> None:
        """Keep the robot's events again until :meth:`admit` (a robot taken out to be placed afresh)."""
        self.member(robot_id).admitted = False

    # ------------------------------------------------------------ streams
    def on_stream(self, key_robot_id: str, stream: str, message: Odometry | Scan, source: str | None = None) -> Arrival:
        """Check one stream message and say what to do with it (see :class:`Arrival`). ``source``: the Zenoh
        session that published it, when known (a robot process restarted is another session)."""
        if message.robot_id != key_robot_id:
            return Arrival(refused=("robot_id_mismatch", f"{message.robot_id} on the {stream} key of {key_robot_id}"))
        arrival = Arrival()
        member = self.member(key_robot_id)
        held = self.resumed.get((key_robot_id, stream), -1)
        if key_robot_id in self.refilling or self.clock() < self.repeats_until.get(key_robot_id, float("-inf")):
            held = max(held, self.tracker.last_seq(key_robot_id, stream))  # the robot's and the caches' history
        if message.seq <= held and self.tracker.same_source(key_robot_id, stream, source):
            self.counts["already_held"] += 1
            return arrival
        if self.tracker.new_run(key_robot_id, stream, message.seq, source):
            self._forget_run(key_robot_id)
            member = self.member(key_robot_id)
            arrival.new_run = True
        last = self.tracker.last_seq(key_robot_id, stream)
        if key_robot_id in self.refilling and last >= 0 and message.seq > last + 1:
            self.parked.setdefault((key_robot_id, stream), {})[message.seq] = (message, source)
            return arrival  # past a gap that the robot's history may still fill: it waits (refilled)
        info = member.info
        rate = None if info is None else (info.odom_rate_hz if stream == "odom" else info.scan_rate_hz)
        verdict = self.tracker.classify(key_robot_id, stream, message.seq, message.stamp, rate,
                                        None if info is None else info.stamp)
        if verdict is not Verdict.ACCEPT:
            arrival.refused = (verdict.value, f"{key_robot_id}/{stream} seq {message.seq} stamp {message.stamp:g} "
                               f"after seq {last} stamp {self.tracker.last_stamp(key_robot_id, stream)}")
            return arrival
        if stream == "odom":
            arrival.refused = odometry_doubt(message, info, self.tracker.last_stamp(key_robot_id, stream),
                                             message.seq == last + 1, self.dt_tolerance_s)
            if arrival.refused:
                return arrival
        state = self.tracker.streams.get((key_robot_id, stream))  # a commit changes this stream's state only:
        missing_before = 0 if state is None else state.missing  # its count of missing is the robot's change
        self.tracker.commit(key_robot_id, stream, message.seq, message.stamp, source)
        arrival.gap = self.tracker.streams[(key_robot_id, stream)].missing - missing_before
        if stream == "odom" and message.seq > 0 and self.tracker.received(key_robot_id, "odom") == 1:
            arrival.late = True
            self.counts["robots_joined_late"] += 1
        event = stream_event(message)
        if member.admitted:
            arrival.event = event
            return arrival
        arrival.refused = self.keep(event)
        arrival.ask_info = member.info is None and self._ask(member)
        return arrival

    def unparked(self, robot_id: str, stream: str) -> list[Arrival]:
        """The parked messages of a stream that follow on from its last seq now (a gap filled), in order."""
        parked = self.parked.get((robot_id, stream), {})
        arrivals = []
        while (seq := self.tracker.last_seq(robot_id, stream) + 1) in parked:
            arrivals.append(self.on_stream(robot_id, stream, *parked.pop(seq)))
        return arrivals

    def refill(self, robot_id: str) -> None:
        """The robot was asked for the messages it kept (after a restart): until :meth:`refilled`, a message past a
        gap in one of its streams is parked instead of taken, so that the gap can still be filled in order."""
        self.refilling.add(robot_id)

    def refilled(self, robot_id: str) -> list[tuple[Arrival, str]]:
        """The robot's kept messages are in (or the query is over): its parked messages are taken, in order, with
        any gap that is left counted as lost; (arrival, stream) of each."""
        self.refilling.discard(robot_id)
        self.repeats_until[robot_id] = self.clock() + REPEAT_GRACE_S
        arrivals = []
        for key in [key for key in self.parked if key[0] == robot_id]:
            for _seq, (message, source) in sorted(self.parked.pop(key).items()):
                arrivals.append((self.on_stream(key[0], key[1], message, source), key[1]))
        return arrivals

    def keep(self, event: StreamEvent) -> tuple[str, str] | None:
        """Hold an event of a robot not admitted (yet, or again); past ``waiting_bytes`` the oldest held events
        go and the refusal reason is returned (once, with how many went)."""
        member = self.member(event.robot_id)
        member.waiting.append(event)
        member.waiting_bytes += event_nbytes(event)
        dropped = 0
        while member.waiting_bytes > self.waiting_bytes and len(member.waiting) > 1:
            member.waiting_bytes -= event_nbytes(member.waiting.popleft())
            dropped += 1
        if not dropped:
            return None
        self.counts["waiting_dropped"] += dropped
        return ("waiting_overflow", f"{event.robot_id} holds {self.waiting_bytes / 2**20:g} MB of messages waiting "
                f"to join; its {dropped} oldest went")

    def _forget_run(self, robot_id: str) -> None:
        self.resumed = {key: seq for key, seq in self.resumed.items() if key[0] != robot_id}
        self.parked = {key: parked for key, parked in self.parked.items() if key[0] != robot_id}
        alive = self.members[robot_id].alive if robot_id in self.members else False
        self.members[robot_id] = Member(alive=alive)
        self.counts["robot_restarts"] += 1

    def _ask(self, member: Member) -> bool:
        now = self.clock()
        if now - member.asked_at < self.info_timeout_s:
            return False
        member.asked_at = now
        return True


_STREAM_NAMES = ("odom", "scan")  # a robot's streams (ReorderBuffer.push)


@dataclass
class _Held:
    """One held event; the heap orders it by :meth:`entry`, a plain tuple (compared in C: a dataclass's generated
    ordering cost a service seconds a minute at a few hundred events a second)."""

    stamp: float
    rank: int  # at equal stamps odometry (0) before scans (1): a control ends at its stamp
    robot: str  # then by robot id, not by arrival: robots on one clock share stamps, and runs must not differ
    order: int  # then in arrival order; unique, so the heap never compares two _Held
    arrived: float
    event: StreamEvent

    def entry(self) -> tuple:
        return (self.stamp, self.rank, self.robot, self.order, self)


class ReorderBuffer:
    """Releases the events of several robots in stamp order.

    An event waits for the streams (odometry and scans, per robot) of the live robots whose newest stamp is still
    behind it, each as long as that stream is heard from:

    - the other stream of its own robot, up to ``recovery_window_s`` of silence (5 s): a robot's odometry always
      runs up to its scans, so a scan waits for it while it is being recovered (after a link cut or a router
      restart one stream of a robot may come back seconds after the other), and its robot's later events with it,
      while the other robots' events go on;
    - the other robots' streams, up to ``window_s`` of silence (0: no waiting);
    - the streams of a robot that has announced itself (its session token, :meth:`announce`) and sent nothing yet,
      up to ``join_wait_s`` after the announcement: robots of one fleet start at slightly different wall times with
      stamps on one clock, and without this the first robot's events would go before a second robot's older ones
      whenever it happened to start first, so two runs of the same data would differ;
    - for ``recovery_window_s`` after a restart from a checkpoint (:meth:`restart_clock`) or a change of the link to
      the router (:meth:`link_changed`), every known stream, up to ``recovery_window_s`` of silence, whether its
      robot's session token is seen or not: the publishers' caches send what was missed in several parts, and a
      router restart takes every token away at once while the streams come back one by one; without this the
      first one back would run ahead;
    - a robot with messages received and not yet handled (``queued`` in :meth:`release`), up to
      ``recovery_window_s``: a service working off a backlog has not heard what waits in its intake.

    With ``partition_wait_s`` (0: off), the other robots' streams are waited for that long of silence instead of
    ``window_s``, also those of a robot whose session token went away: a robot behind a cut link (silent while its
    token lasts, then gone) or behind a restarting router sends what it missed from its caches when it is back, and
    its events still go in stamp order among the others'. A robot heard again after a silence of
    ``recovery_window_s`` or more has its other stream waited for from then on: the publishers' caches send what
    was missed stream by stream, and one stream's backlog must not run ahead of the other's.

    Another robot's stream more than ``clock_skew_s`` (600 s) behind an event is not waited for: the two robots'
    stamps are on different clocks (a simulated robot's start at 0, a real robot's Unix time), and waiting for the
    one behind would hold the other's events for as long as it streams.

    Silence is counted only while the service listens: the service calls :meth:`listening` every few tens of
    milliseconds, and a longer gap between two calls (its process descheduled on a loaded machine, its loop held)
    is a stall of the service itself, during which no stream could be heard; every stream's silence, the join
    waits and the recovery window are moved on by the stall. Without this a stall longer than ``window_s`` would let
    the first robot heard after it run ahead of the others, whose messages were waiting in the network buffers.

    :meth:`release` with ``flush`` releases everything.
    """

    stall_s = 0.2  # a gap between two :meth:`listening` calls longer than this is a stall of the service
    _listened: float | None = None  # the clock at the last :meth:`listening` call (None: not listening yet)

    def __init__(self, window_s: float, clock: Callable[[], float] = time.perf_counter,
                 recovery_window_s: float = 5.0, join_wait_s: float = 1.0, clock_skew_s: float = 600.0,
                 partition_wait_s: float = 0.0):
        self.window_s = window_s
        self.partition_wait_s = partition_wait_s
        self.clock_skew_s = clock_skew_s
        self.recovery_window_s = recovery_window_s
        self.join_wait_s = join_wait_s
        self.expected: dict[tuple[str, str], float] = {}  # (robot, stream) announced, nothing pushed → when announced
        self.clock = clock
        self._heap: list[tuple] = []  # _Held.entry() of every held event
        self._order = 0  # ties in stamp, kind and robot go out in arrival order
        self.newest: dict[tuple[str, str], float] = {}  # (robot, stream) → newest stamp pushed
        self._by_stamp: list[tuple[float, tuple[str, str]]] = []  # (newest stamp, stream) of each stream, sorted
        self.heard: dict[tuple[str, str], float] = {}  # (robot, stream) → wall time of its last push
        self.resuming: set[tuple[str, str]] = set()  # streams being recovered after a restart or a link change
        self.resuming_until = float("-inf")  # ... until then (wall clock)

    def __setstate__(self, state: dict) -> None:
        """Unpickle (a service checkpoint); one written when the heap held the events themselves gets their
        entries."""
        self.__dict__.update({"partition_wait_s": 0.0, **state})
        self._heap = [held.entry() if isinstance(held, _Held) else held for held in self._heap]
        heapq.heapify(self._heap)
        self._sort_streams()

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state.pop("_by_stamp", None)  # derived from newest: not in checkpoints
        return state

    def _sort_streams(self) -> None:
        self._by_stamp = sorted((stamp, stream) for stream, stamp in self.newest.items())

    def __len__(self) -> int:
        return len(self._heap)

    def push(self, event: StreamEvent, arrived: float | None = None) -> None:
        is_odom = isinstance(event, OdomEvent)
        stream = (event.robot_id, "odom" if is_odom else "scan")
        arrived = self.clock() if arrived is None else arrived
        if arrived - self.heard.get(stream, arrived) >= self.recovery_window_s:
            # heard again after a silence (a cut link): its other stream is being recovered too, in parts of its
            # own, and is waited for from now, as after a link change; else its events would run ahead of the other's
            for other in (other for other in self.newest if other[0] == event.robot_id and other != stream):
                self.heard[other] = max(self.heard.get(other, arrived), arrived)
        old = self.newest.get(stream)
        newest = self.newest[stream] = max(float("-inf") if old is None else old, event.stamp)
        if newest != old:  # the stream moves in the streams sorted by stamp
            by_stamp = self._by_stamp
            index = 0 if old is None else bisect.bisect_left(by_stamp, (old, stream))
            if old is None or (index < len(by_stamp) and by_stamp[index] == (old, stream)):
                if old is not None:
                    del by_stamp[index]
                bisect.insort(by_stamp, (newest, stream))
            else:  # not where it should have been: sorted afresh
                self._sort_streams()
        self.heard[stream] = arrived
        self.expected.pop(stream, None)
        self._hold(event, arrived)

    def _hold(self, event: StreamEvent, arrived: float) -> None:
        """Into the heap, after every event held so far at the same stamp, rank and robot."""
        self._order += 1
        heapq.heappush(self._heap, _Held(event.stamp, 0 if isinstance(event, OdomEvent) else 1, event.robot_id,
                                         self._order, arrived, event).entry())

    def listening(self) -> float:
        """The service's loop is running now; returns the stall (s) since the previous call, 0 if none: a gap longer
        than ``stall_s`` is not counted as any stream's silence."""
        now = self.clock()
        gap = 0.0 if self._listened is None else now - self._listened
        self._listened = now
        if gap <= self.stall_s:
            return 0.0
        self.heard = {stream: at + gap for stream, at in self.heard.items()}
        self.expected = {stream: at + gap for stream, at in self.expected.items()}
        self.resuming_until += gap
        return gap

    def announce(self, robot_id: str) -> None:
        """A robot declared its session token: until it sends (at most ``join_wait_s``), the other robots' later
        events wait for its streams."""
        now = self.clock()
        for stream in ((robot_id, "odom"), (robot_id, "scan")):
            if stream not in self.newest:
                self.expected[stream] = now

    def restart_clock(self) -> None:
        """Restored from a checkpoint in a new process (whose clock started afresh): held events arrived now, and
        every known stream is waited for ``recovery_window_s`` from now."""
        now = self.clock()
        for entry in self._heap:
            entry[-1].arrived = now
        self._listened = None
        self.link_changed()
        self.expected = {stream: now for stream in self.expected}

    def link_changed(self) -> None:
        """The link to the router closed or opened again: every known stream is waited for ``recovery_window_s``
        from now, until it is heard from."""
        now = self.clock()
        self.heard = {stream: now for stream in self.newest}
        self.resuming = set(self.newest)
        self.resuming_until = now + self.recovery_window_s

    def drop_robot(self, robot_id: str) -> None:
        """Forget a robot's held events and its streams (a new run of it)."""
        self._heap = [entry for entry in self._heap if entry[-1].event.robot_id != robot_id]
        heapq.heapify(self._heap)
        for table in (self.newest, self.heard):
            for stream in [stream for stream in table if stream[0] == robot_id]:
                del table[stream]
        self._sort_streams()
        self.resuming = {stream for stream in self.resuming if stream[0] != robot_id}
        self.expected = {stream: at for stream, at in self.expected.items() if stream[0] != robot_id}

    def _waited_for(self, stream: tuple[str, str], own: bool, now: float, recovering: set[tuple[str, str]],
                    queued: set[str]) -> bool:
        """Is ``stream`` still waited for: heard from within its patience, or within the recovery window while it is
        being recovered or with messages of its robot queued, not yet handled (a robot whose lane is full of messages
        that never advance the stream holds the others back no longer than that)?"""
        if own:
            patience = self.recovery_window_s
        else:  # a robot being recovered or with a backlog queued is waited for longer, never shorter
            patience = max(self.window_s, self.partition_wait_s,
                           self.recovery_window_s if stream in recovering or stream[0] in queued else 0.0)
        return now - self.heard.get(stream, float("-inf")) < patience

    def put_back(self, released: list[tuple[StreamEvent, float]]) -> None:
        """Hold again events that :meth:`release` gave out, as ``(event, arrival time)``, and that were not handled
        (a stop came between them): they go out again first, in their order. The streams' records stay as they are:
        those events were heard already."""
        for event, arrived in released:
            self._hold(event, arrived)

    def release(self, live: Iterable[str], flush: bool = False, announced: Iterable[str] = (),
                queued: Iterable[str] = ()) -> list[tuple[StreamEvent, float]]:
        """(event, arrival time) of every event due now, oldest stamp first within each robot. ``live``: the
        robots whose streams are waited for (alive and taken in); ``announced``: the robots alive, whose streams
        are waited for from their announcement on even before they are taken in; ``queued``: the robots with
        messages received and not yet handled (a service busy with a backlog must not count them as silent).

        The same as :meth:`release_reference`, which asks every stream about every event it looks at (a cost of
        streams × events per call: quadratic in the fleet's size, once per message). Here the events, taken in stamp
        order, look at the streams in stamp order too: each stream behind the latest event looked at is asked once
        per call whether it holds other robots' events back, and an event's own robot's streams are looked up."""
        if flush or self.window_s == 0:
            out = [(entry[-1].event, entry[-1].arrived) for entry in sorted(self._heap)]
            self._heap = []
            return out
        if not self._heap:
            return []
        live = live if isinstance(live, (set, frozenset)) else set(live)
        now = self.clock()
        recovering = self.resuming if now < self.resuming_until else set()
        announced = announced if isinstance(announced, (set, frozenset)) else set(announced)
        queued = queued if isinstance(queued, (set, frozenset)) else set(queued)
        if self.expected and any(stream[0] in announced and now - at < (self.recovery_window_s if stream[0] in queued
                                                                         else self.join_wait_s)
                                 for stream, at in self.expected.items()):
            return []  # a robot that announced itself is still awaited
        window, recovery, skew = self.window_s, self.recovery_window_s, self.clock_skew_s
        partition = self.partition_wait_s
        newest, heard, streams = self.newest, self.heard, self._by_stamp  # streams: (newest stamp, stream), sorted
        ahead = 0  # streams[:ahead] were looked at: they are behind an event looked at
        waited: list[tuple[float, str]] = []  # (stamp, robot) of those that hold back other robots' events, in order
        newest_held = streams[-1][0] if streams else float("-inf")  # no held event is later than this
        out, kept, waiting_robots = [], [], set()
        blocked_at = None  # the stamp of the first event that waits for another robot: the ones near it wait too
        while self._heap:
            if blocked_at is not None and newest_held - blocked_at <= skew:
                break  # nothing held is on another clock: the rest waits, in stamp order
            held = heapq.heappop(self._heap)[-1]
            rid, stamp = held.robot, held.stamp
            if rid in waiting_robots or (blocked_at is not None and stamp - blocked_at <= skew):
                kept.append(held)
                continue
            own_behind = False  # its own other stream behind it and heard from within the recovery window
            for name in _STREAM_NAMES:
                own = (rid, name)
                behind = newest.get(own)
                if behind is not None and behind < stamp and (rid in live or own in recovering) and \
                        now - heard.get(own, float("-inf")) < recovery:
                    own_behind = True
                    break
            if own_behind:
                waiting_robots.add(rid)  # its own other stream is being recovered: it waits, the others go on
                kept.append(held)
                continue
            # another robot's stream behind this event (and on the same clock) still waited for? The streams not
            # looked at yet, up to its stamp (events come in stamp order: so do streams), then those found before,
            # the latest first (the rounding of a difference moves with its operands: the first one too far back
            # ends the search)
            blocked = False
            while ahead < len(streams) and streams[ahead][0] < stamp:
                behind, stream = streams[ahead]
                ahead += 1
                other = stream[0]
                if (other in live or stream in recovering or partition > 0) and now - heard.get(
                        stream, float("-inf")) < max(window, partition,
                                                     recovery if stream in recovering or other in queued else 0.0):
                    waited.append((behind, other))
                    if other != rid and stamp - behind <= skew:
                        blocked = True
                        break
            index = -1 if blocked else len(waited) - 1
            while index >= 0 and stamp - waited[index][0] <= skew:
                if waited[index][1] != rid:
                    blocked = True
                    break
                index -= 1
            if not blocked:
                out.append((held.event, held.arrived))
                continue
            kept.append(held)
            blocked_at = stamp if blocked_at is None else blocked_at
        for held in kept:
            heapq.heappush(self._heap, held.entry())
        return out

    def release_reference(self, live: Iterable[str], flush: bool = False, announced: Iterable[str] = (),
                          queued: Iterable[str] = ()) -> list[tuple[StreamEvent, float]]:
        """:meth:`release` as first written, asking every stream about every event (the reference its tests hold it
        to)."""
        if flush or self.window_s == 0:
            out = [(entry[-1].event, entry[-1].arrived) for entry in sorted(self._heap)]
            self._heap = []
            return out
        live = set(live)
        now = self.clock()
        recovering = self.resuming if now < self.resuming_until else set()
        streams = [(stamp, stream) for stream, stamp in self.newest.items()
                   if stream[0] in live or stream in recovering or self.partition_wait_s > 0]
        announced = set(announced)
        queued = set(queued)
        joining = any(stream[0] in announced and now - at < (self.recovery_window_s if stream[0] in queued
                                                              else self.join_wait_s)
                      for stream, at in self.expected.items())
        out, kept, waiting_robots = [], [], set()
        if joining:
            return out
        newest_held = max(self.newest.values(), default=float("-inf"))  # no held event is later than this
        blocked_at = None  # the stamp of the first event that waits for another robot: the ones near it wait too
        while self._heap:
            if blocked_at is not None and newest_held - blocked_at <= self.clock_skew_s:
                break  # nothing held is on another clock: the rest waits, in stamp order
            held = heapq.heappop(self._heap)[-1]
            rid = held.event.robot_id
            if rid in waiting_robots or (blocked_at is not None and held.stamp - blocked_at <= self.clock_skew_s):
                kept.append(held)
                continue
            behind = [(stream, stream[0] == rid) for stamp, stream in streams
                      if stamp < held.stamp and (stream[0] == rid or held.stamp - stamp <= self.clock_skew_s)]
            if any(own and self._waited_for(stream, True, now, recovering, queued) for stream, own in behind):
                waiting_robots.add(rid)  # its own other stream is being recovered: it waits, the others go on
                kept.append(held)
                continue
            if any(not own and self._waited_for(stream, False, now, recovering, queued) for stream, own in behind):
                kept.append(held)
                blocked_at = held.stamp if blocked_at is None else blocked_at
                continue
            out.append((held.event, held.arrived))
        for held in kept:
            heapq.heappush(self._heap, held.entry())
        return out
