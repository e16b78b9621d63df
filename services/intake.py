"""The bounded, fair queue between a service's Zenoh callbacks and its loop (no Zenoh here).

Every sample a service receives waits here until the service's loop takes it.
Without bounds, one robot (or one process claiming to be one) that floods its
keys fills memory and delays every other robot's messages. So:

- each sample is first held to the size limit of its kind (``limits``: a scan,
  an odometry message...), before anything decodes it: a larger one is refused
  as ``oversize``;
- samples wait in lanes, one per (robot, publishing session) for robot streams
  and one per kind otherwise, taken in turn (round robin): a flood from one lane
  only delays that lane;
- a lane holds at most ``lane_bytes`` and all lanes together ``total_bytes``:
  past them a sample is refused (``rate_limited``: its lane sends faster than the
  service handles; ``queue_full``: every lane together), so a flood costs a
  bounded amount of memory and the others' samples keep flowing.

It is filled from Zenoh's callback threads and emptied by the loop: every
method takes the lock.
"""

from __future__ import annotations

import threading
from collections import Counter, OrderedDict, deque
from typing import Any, Callable, Hashable


class Intake:
    """Byte-bounded lanes taken in turn; see the module docstring."""

    def __init__(self, lane_bytes: int, total_bytes: int, limits: dict[str, int] | None = None,
                 on_first: Callable[[], None] | None = None):
        self.lane_bytes = lane_bytes
        self.total_bytes = total_bytes
        self.limits = dict(limits or {})
        self.on_first = on_first  # called (outside the lock) when a sample arrives in an empty intake: wake the loop
        self.refused: Counter = Counter()
        self.held_bytes = 0
        self.peak_bytes = 0
        self.high_water = 0  # the most held since :meth:`take_high_water`
        self._lanes: OrderedDict[Hashable, deque[tuple[Any, int]]] = OrderedDict()
        self._lane_bytes: dict[Hashable, int] = {}
        self._count = 0
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return self._count

    def oversize(self, kind: str, nbytes: int) -> bool:
        """Whether a sample of ``kind`` and ``nbytes`` is over its size limit (then counted as ``oversize``): a
        callback asks before it copies the payload."""
        limit = self.limits.get(kind)
        if limit is None or nbytes <= limit:
            return False
        with self._lock:
            self.refused["oversize"] += 1
        return True

    def put(self, kind: str, lane: Hashable, item: Any, nbytes: int) -> str | None:
        """Queue ``item`` (of ``nbytes`` payload bytes) in ``lane``; the refusal reason instead when it is refused
        (counted in :attr:`refused`)."""
        if self.oversize(kind, nbytes):
            return "oversize"
        reason = None
        with self._lock:
            if self._lane_bytes.get(lane, 0) + nbytes > self.lane_bytes and lane in self._lanes:
                reason = "rate_limited"
            elif self.held_bytes + nbytes > self.total_bytes and self._count:
                reason = "queue_full"
            if reason is not None:
                self.refused[reason] += 1
                return reason
            was_empty = self._count == 0
            self._lanes.setdefault(lane, deque()).append((item, nbytes))
            self._lane_bytes[lane] = self._lane_bytes.get(lane, 0) + nbytes
            self.held_bytes += nbytes
            self.peak_bytes = max(self.peak_bytes, self.held_bytes)
            self.high_water = max(self.high_water, self.held_bytes)
            self._count += 1
        if was_empty and self.on_first is not None:
            self.on_first()
        return None

    def get(self) -> Any | None:
        """The next item, lanes in turn (None when empty)."""
        with self._lock:
            return self._pop()[1] if self._lanes else None

    def get_many(self, limit: int) -> list[tuple[Hashable, Any]]:
        """Up to ``limit`` items as (lane, item), in the order :meth:`get` would give them, under one lock."""
        with self._lock:
            return [self._pop() for _ in range(min(limit, self._count))]

    def _pop(self) -> tuple[Hashable, Any]:
        """(lane, item) of the first lane's oldest item, the lane moved to the back (or dropped when emptied); the lock
        held and a lane there."""
        lane, queue = next(iter(self._lanes.items()))
        item, nbytes = queue.popleft()
        self._count -= 1
        self.held_bytes -= nbytes
        self._lane_bytes[lane] -= nbytes
        if queue:
            self._lanes.move_to_end(lane)
        else:
            del self._lanes[lane]
            del self._lane_bytes[lane]
        return lane, item

    def lanes(self) -> list[Hashable]:
        """The lanes holding items now."""
        with self._lock:
            return list(self._lanes)

    def take_high_water(self) -> int:
        """The most bytes held at once since the last call (or the start)."""
        with self._lock:
            high, self.high_water = self.high_water, self.held_bytes
        return high

    def take_refused(self) -> Counter:
        """The refusals counted since the last call (moved into the service's rejection counts)."""
        with self._lock:
            refused, self.refused = self.refused, Counter()
        return refused
