"""Per-stream order checking: every receiver detects gaps, duplicates and time
going backwards from (seq, stamp), counts them, and decides whether to use a
message, so none of them can corrupt a filter's state (DESIGN §2)."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from enum import Enum


class Verdict(str, Enum):
    """What to do with one stream message."""

    ACCEPT = "accept"
    DUPLICATE = "duplicate"
    OUT_OF_ORDER = "out_of_order"
    TIME_BACKWARDS = "time_backwards"


@dataclass
class _StreamState:
    last_seq: int = -1
    last_stamp: float = float("-inf")
    received: int = 0
    missing: int = 0


@dataclass
class StreamTracker:
    """Tracks (robot, stream) → last seq/stamp; classifies each message.

    A message is accepted when its seq is past the last accepted one and its
    stamp does not go backwards; a jump in seq is accepted and the skipped
    messages are counted as ``missing``. Everything else is rejected with a
    reason that ends up in the service's stats. ``missing_before_join``: the
    messages a stream sent before its first one received here count as missing
    (a filter that missed a robot's start must know); an observer that joins a
    running fleet (the monitor) counts only what it lost after it joined.
    """

    streams: dict[tuple[str, str], _StreamState] = field(default_factory=dict)
    missing_before_join: bool = True
    rejected: Counter = field(default_factory=Counter)
    left: set[str] = field(default_factory=set)  # robots whose liveliness token went away
    sources: dict[tuple[str, str], str] = field(default_factory=dict)  # (robot, stream) → publishing Zenoh session

    def check(self, robot_id: str, stream: str, seq: int, stamp: float, source: str | None = None) -> Verdict:
        """The verdict on one message; ``source``: the Zenoh session that published it, when known (remembered
        from an accepted message, to tell a restarted robot process by)."""
        state = self.streams.setdefault((robot_id, stream), _StreamState())
        if seq == state.last_seq:
            verdict = Verdict.DUPLICATE
        elif seq < state.last_seq:
            verdict = Verdict.OUT_OF_ORDER
        elif stamp < state.last_stamp:
            verdict = Verdict.TIME_BACKWARDS
        else:
            if state.last_seq >= 0:
                state.missing += seq - state.last_seq - 1
            elif self.missing_before_join:
                state.missing += seq
            state.last_seq, state.last_stamp = seq, stamp
            state.received += 1
            if source is not None:
                self.sources[(robot_id, stream)] = source
            return Verdict.ACCEPT
        self.rejected[verdict.value] += 1
        return verdict

    def missing(self, robot_id: str | None = None) -> int:
        """Messages skipped in seq (gaps) so far, for one robot or all."""
        return sum(s.missing for (rid, _), s in self.streams.items() if robot_id is None or rid == robot_id)

    def received(self, robot_id: str, stream: str) -> int:
        state = self.streams.get((robot_id, stream))
        return state.received if state else 0

    def last_seq(self, robot_id: str, stream: str) -> int:
        state = self.streams.get((robot_id, stream))
        return state.last_seq if state else -1

    def leave(self, robot_id: str) -> None:
        """The robot's liveliness token went away: its streams stay (it may be back after a link cut)."""
        self.left.add(robot_id)

    def same_source(self, robot_id: str, stream: str, source: str | None) -> bool:
        """False only when both are known and ``source`` is not the session that published the stream so far."""
        known = self.sources.get((robot_id, stream))
        return source is None or known is None or source == known

    def new_run(self, robot_id: str, stream: str, seq: int, source: str | None = None) -> bool:
        """True when a stream starts again at seq 0 as a new run of its robot, not as duplicates of the old one:
        from another Zenoh session than before (a restarted robot process), or, the sessions unknown, after the
        robot's liveliness token went away. Its streams are forgotten then; the caller resets what it holds of
        the robot. A robot back after a link cut goes on with its seq numbers and is not a new run, and neither
        is its own publisher cache sending its stream again (same session)."""
        if seq != 0 or self.received(robot_id, stream) == 0:
            return False
        known = self.sources.get((robot_id, stream))
        if source is not None and known is not None:
            if source == known:
                return False
        elif robot_id not in self.left:
            return False
        self.left.discard(robot_id)
        self.forget(robot_id)
        return True

    def forget(self, robot_id: str) -> None:
        """Drop a robot's streams (it left; a restarted robot starts again at seq 0)."""
        for table in (self.streams, self.sources):
            for key in [k for k in table if k[0] == robot_id]:
                del table[key]
