"""Per-stream order checking: every receiver detects gaps, duplicates, time
going backwards and implausible jumps from (seq, stamp), counts them, and
decides whether to use a message, so none of them can corrupt a filter's state
(DESIGN §2). A refused message never moves a stream's state: a real stream goes
on after a forged or buggy one."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from enum import Enum

from schemas.messages import Odometry, RobotInfo


class Verdict(str, Enum):
    """What to do with one stream message."""

    ACCEPT = "accept"
    DUPLICATE = "duplicate"
    OUT_OF_ORDER = "out_of_order"
    TIME_BACKWARDS = "time_backwards"
    SEQ_JUMP = "seq_jump"
    STAMP_JUMP = "stamp_jump"


@dataclass(frozen=True)
class StreamLimits:
    """How far a stream may jump forward: its stamp by at most ``max_stamp_jump_s``, its seq by at most what its
    rate could send meanwhile (``seq_slack`` × rate × stamp step + ``seq_margin``; the rate announced in RobotInfo,
    else ``max_rate_hz``). A first message may not be further from the robot's start stamp (when known) than that
    either. Past these a message is refused (``seq_jump``, ``stamp_jump``): two messages with seq 2^62 or a stamp of
    1e12 would otherwise make every later real message of the stream out of order."""

    max_stamp_jump_s: float = 3600.0
    seq_slack: float = 3.0
    seq_margin: int = 100
    max_rate_hz: float = 1000.0

    def seq_allowance(self, span_s: float, rate_hz: float | None) -> float:
        """The largest plausible seq step over ``span_s`` seconds of stamps."""
        rate = self.max_rate_hz if rate_hz is None else rate_hz
        return self.seq_slack * rate * max(span_s, 0.0) + self.seq_margin


@dataclass
class _StreamState:
    last_seq: int = -1
    last_stamp: float = float("-inf")
    received: int = 0
    missing: int = 0


@dataclass
class StreamTracker:
    """Tracks (robot, stream) → last seq/stamp; classifies each message.

    A message is accepted when its seq is past the last accepted one, its
    stamp does not go backwards, and neither jumps further than ``limits``
    allow; the skipped messages of a plausible jump in seq are counted as
    ``missing``. Everything else is rejected with a reason that ends up in the
    service's stats. ``missing_before_join``: the
    messages a stream sent before its first one received here count as missing
    (a filter that missed a robot's start must know); an observer that joins a
    running fleet (the monitor) counts only what it lost after it joined.
    """

    streams: dict[tuple[str, str], _StreamState] = field(default_factory=dict)
    missing_before_join: bool = True
    rejected: Counter = field(default_factory=Counter)
    left: set[str] = field(default_factory=set)  # robots whose liveliness token went away
    sources: dict[tuple[str, str], str] = field(default_factory=dict)  # (robot, stream) → publishing Zenoh session
    limits: StreamLimits = StreamLimits()  # a class default: checkpoints written before it existed still load

    def classify(self, robot_id: str, stream: str, seq: int, stamp: float, rate_hz: float | None = None,
                 origin: float | None = None) -> Verdict:
        """The verdict on one message, without taking it (:meth:`commit` does). ``rate_hz``: the stream's announced
        rate; ``origin``: the robot's start stamp, when known (bounds the seq of a stream's first message)."""
        state = self.streams.get((robot_id, stream))
        if state is None or state.last_seq < 0:
            if origin is not None and seq > self.limits.seq_allowance(stamp - origin, rate_hz):
                return Verdict.SEQ_JUMP
            return Verdict.ACCEPT
        if seq == state.last_seq:
            return Verdict.DUPLICATE
        if seq < state.last_seq:
            return Verdict.OUT_OF_ORDER
        if stamp < state.last_stamp:
            return Verdict.TIME_BACKWARDS
        if stamp - state.last_stamp > self.limits.max_stamp_jump_s:
            return Verdict.STAMP_JUMP
        if seq - state.last_seq - 1 > self.limits.seq_allowance(stamp - state.last_stamp, rate_hz):
            return Verdict.SEQ_JUMP
        return Verdict.ACCEPT

    def commit(self, robot_id: str, stream: str, seq: int, stamp: float, source: str | None = None) -> None:
        """Take a message :meth:`classify` accepted: it becomes the stream's last; the seqs it skipped are missing."""
        state = self.streams.setdefault((robot_id, stream), _StreamState())
        if state.last_seq >= 0:
            state.missing += seq - state.last_seq - 1
        elif self.missing_before_join:
            state.missing += seq
        state.last_seq, state.last_stamp = seq, stamp
        state.received += 1
        if source is not None:
            self.sources[(robot_id, stream)] = source

    def check(self, robot_id: str, stream: str, seq: int, stamp: float, source: str | None = None,
              rate_hz: float | None = None, origin: float | None = None) -> Verdict:
        """Classify one message and take it when accepted (a refusal is counted and changes nothing); ``source``:
        the Zenoh session that published it, when known (remembered from an accepted message, to tell a restarted
        robot process by)."""
        verdict = self.classify(robot_id, stream, seq, stamp, rate_hz, origin)
        if verdict is Verdict.ACCEPT:
            self.commit(robot_id, stream, seq, stamp, source)
        else:
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

    def last_stamp(self, robot_id: str, stream: str) -> float | None:
        """The stamp of the stream's last accepted message (None before the first)."""
        state = self.streams.get((robot_id, stream))
        return state.last_stamp if state and state.last_seq >= 0 else None

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


def odometry_doubt(message: Odometry, info: RobotInfo | None, previous_stamp: float | None, consecutive: bool,
                   dt_tolerance_s: float) -> tuple[str, str] | None:
    """Why an odometry message that is in order cannot be true, or None.

    - ``dt_mismatch``: its interval ``dt`` ends at its stamp, so it cannot reach back before the previous odometry
      message's stamp, and right after it (``consecutive`` seq) it must cover the time since (both within
      ``dt_tolerance_s`` plus 5 %): one message claiming dt = 10 s in a 10 Hz stream would move the robot 10 s worth.
    - ``control_limit``: a control beyond the motion limits the robot announced in its RobotInfo (speed; turn rate
      for a unicycle, steering angle for an ackermann robot).
    """
    if previous_stamp is not None:
        span = message.stamp - previous_stamp
        tolerance = dt_tolerance_s + 0.05 * span
        if message.dt > span + tolerance or (consecutive and message.dt < span - tolerance):
            return "dt_mismatch", f"{message.robot_id} odometry seq {message.seq}: dt {message.dt:g} s over {span:g} s of stamps"
    if info is not None:
        speed, turn = abs(float(message.control[0])), abs(float(message.control[1]))
        turn_limit = info.max_turn_rate if info.motion_model == "unicycle" else info.max_steering
        if info.max_speed is not None and speed > info.max_speed:
            return "control_limit", f"{message.robot_id} odometry seq {message.seq}: speed {speed:g} > {info.max_speed:g}"
        if turn_limit is not None and turn > turn_limit:
            return "control_limit", f"{message.robot_id} odometry seq {message.seq}: {turn:g} > {turn_limit:g}"
    return None
