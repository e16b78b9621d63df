"""Robot membership and cross-robot ordering, written once for every service (no Zenoh here).

:class:`Roster` is what central FastSLAM, D-SLAM and MCL know about the fleet:
which robots are alive (liveliness), which have announced themselves
(RobotInfo), and which the service has taken in. It turns each stream message
into the core's event:

- the message's robot id must match its key, and its stream must be in order
  (:class:`~schemas.streams.StreamTracker`: duplicates, out-of-order and time
  going backwards are refused with the reason, gaps counted);
- a robot that left (its token went away) and starts again at seq 0 is a new
  run: the roster forgets its RobotInfo and the service resets what it holds
  of it; a robot back after a link cut goes on with its seq numbers;
- a robot's events wait (at most ``waiting_limit``, the oldest dropped and
  counted) until it has announced itself and the service admits it — at once,
  or later (central waits for MCL to place a robot with no start pose);
- it says when to ask a robot for its RobotInfo: when its token appears, and
  again every ``info_timeout_s`` while its messages come unannounced.

:class:`ReorderBuffer` releases events of several robots in stamp order,
holding each at most a wall-time window.
"""

from __future__ import annotations

import heapq
import itertools
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Callable

from schemas.contract import OdomEvent, ScanEvent, stream_event
from schemas.messages import Odometry, RobotInfo, Scan
from schemas.streams import StreamTracker, Verdict

StreamEvent = OdomEvent | ScanEvent


@dataclass
class Member:
    """What the roster knows of one robot."""

    info: RobotInfo | None = None
    alive: bool = False
    admitted: bool = False
    waiting: deque = field(default_factory=deque)
    asked_at: float = float("-inf")


@dataclass
class Arrival:
    """What became of one stream message: its event (None when refused or held), or the reason it was refused;
    whether it started a new run of its robot, whether the robot joined late (its first odometry has seq > 0),
    and whether the robot should be asked for its RobotInfo now."""

    event: StreamEvent | None = None
    refused: tuple[str, str] | None = None
    new_run: bool = False
    late: bool = False
    ask_info: bool = False


class Roster:
    """Membership of every robot a service hears of (see the module docstring)."""

    def __init__(self, waiting_limit: int = 2000, info_timeout_s: float = 2.0,
                 clock: Callable[[], float] = time.monotonic):
        self.waiting_limit = waiting_limit
        self.info_timeout_s = info_timeout_s
        self.clock = clock
        self.tracker = StreamTracker()
        self.members: dict[str, Member] = {}
        self.counts: Counter = Counter()

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

    def waiting_count(self) -> int:
        return sum(len(member.waiting) for member in self.members.values())

    def missing(self) -> int:
        return self.tracker.missing()

    # ------------------------------------------------------------ liveliness
    def on_alive(self, robot_id: str) -> bool:
        """A robot's liveliness token appeared; True when its RobotInfo should be asked for now."""
        member = self.member(robot_id)
        member.alive = True
        return member.info is None and self._ask(member)

    def on_gone(self, robot_id: str) -> None:
        """A robot's token went away: its state stays (its last messages may still be queued, or it is back
        after a link cut); a new run of it is recognised when its streams start again at seq 0."""
        self.member(robot_id).alive = False
        self.tracker.leave(robot_id)
        self.counts["robots_lost"] += 1

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
        kept = held if after is None else [event for event in held if event.stamp > after]
        return kept, len(held) - len(kept)

    def hold(self, robot_id: str) -> None:
        """Keep the robot's events again until :meth:`admit` (a robot taken out to be placed afresh)."""
        self.member(robot_id).admitted = False

    # ------------------------------------------------------------ streams
    def on_stream(self, key_robot_id: str, stream: str, message: Odometry | Scan) -> Arrival:
        """Check one stream message and say what to do with it (see :class:`Arrival`)."""
        if message.robot_id != key_robot_id:
            return Arrival(refused=("robot_id_mismatch", f"{message.robot_id} on the {stream} key of {key_robot_id}"))
        arrival = Arrival()
        member = self.member(key_robot_id)
        if self.tracker.new_run(key_robot_id, stream, message.seq):
            self._forget_run(key_robot_id)
            member = self.member(key_robot_id)
            arrival.new_run = True
        verdict = self.tracker.check(key_robot_id, stream, message.seq, message.stamp)
        if verdict is not Verdict.ACCEPT:
            arrival.refused = (verdict.value, f"{key_robot_id}/{stream} seq {message.seq}")
            return arrival
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

    def keep(self, event: StreamEvent) -> tuple[str, str] | None:
        """Hold an event of a robot not admitted (yet, or again); past ``waiting_limit`` the oldest held event
        goes and the refusal reason is returned."""
        member = self.member(event.robot_id)
        refused = None
        if len(member.waiting) >= self.waiting_limit:
            member.waiting.popleft()
            refused = ("waiting_overflow", f"{event.robot_id} has {self.waiting_limit} messages waiting to join")
        member.waiting.append(event)
        return refused

    def _forget_run(self, robot_id: str) -> None:
        alive = self.members[robot_id].alive if robot_id in self.members else False
        self.members[robot_id] = Member(alive=alive)
        self.counts["robot_restarts"] += 1

    def _ask(self, member: Member) -> bool:
        now = self.clock()
        if now - member.asked_at < self.info_timeout_s:
            return False
        member.asked_at = now
        return True


@dataclass(order=True)
class _Held:
    stamp: float
    order: int
    arrived: float = field(compare=False)
    event: StreamEvent = field(compare=False)


class ReorderBuffer:
    """Releases events of several robots in stamp order.

    An event is released once every live robot's stream has passed its stamp (the watermark: the oldest of
    the live robots' newest stamps), or once it has waited ``window_s`` of wall time (0: at once), or on
    :meth:`release` with ``flush``.
    """

    def __init__(self, window_s: float, clock: Callable[[], float] = time.perf_counter):
        self.window_s = window_s
        self.clock = clock
        self._heap: list[_Held] = []
        self._order = itertools.count()
        self.newest: dict[str, float] = {}

    def __len__(self) -> int:
        return len(self._heap)

    def push(self, event: StreamEvent, arrived: float | None = None) -> None:
        self.newest[event.robot_id] = max(self.newest.get(event.robot_id, float("-inf")), event.stamp)
        heapq.heappush(self._heap, _Held(event.stamp, next(self._order), self.clock() if arrived is None else arrived,
                                         event))

    def drop_robot(self, robot_id: str) -> None:
        """Forget a robot's held events and its newest stamp (a new run of it)."""
        self._heap = [held for held in self._heap if held.event.robot_id != robot_id]
        heapq.heapify(self._heap)
        self.newest.pop(robot_id, None)

    def release(self, live: list[str], flush: bool = False) -> list[tuple[StreamEvent, float]]:
        """(event, arrival time) of every event due now, oldest stamp first. ``live``: the robots whose streams
        the watermark waits for (alive and taken in)."""
        stamps = [self.newest[rid] for rid in live if rid in self.newest]
        watermark = min(stamps) if stamps else float("inf")
        deadline = self.clock() - self.window_s
        out = []
        while self._heap:
            held = self._heap[0]
            if not (flush or self.window_s == 0 or held.stamp <= watermark or held.arrived <= deadline):
                break
            heapq.heappop(self._heap)
            out.append((held.event, held.arrived))
        return out
