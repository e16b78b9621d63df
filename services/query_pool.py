"""Bounded queries for the queryable services (``fleetslam assoc``, ``fleetslam mcl``'s localize).

A queryable's Zenoh callback hands each query to :meth:`QueryPool.admit`,
which answers at once, on the callback's thread, whatever need not wait for a
solve: ``busy`` when ``workers + queue`` queries are already in (nothing is
decoded then), and every refusal the service's ``prepare`` raises while it
decodes and checks the request (``too_large``, ``invalid``...). An admitted
query is solved by one of a few worker threads (numpy, scipy and the numba
kernels release the GIL) at a lower priority (``nice``), so the service's own
loop — MCL's robot tracking — keeps its path, and its processor share. A query that waited past ``deadline_s`` is dropped unsolved
(``expired``: its caller has given up); a solve gets the rest of the
deadline as its time budget. A caller may say how long it waits, with the
selector parameter ``timeout_s`` (``{key}?timeout_s=0.5``, as the association
client does): the query's deadline is then the shorter of the two, so what
its caller abandoned is not solved. Every query gets exactly one answer; a solve
that raises is answered ``solve_error``. Refusals are counted by reason in
the service's stats (in its loop, a burst of queries in one call), the queue
wait and the solve time in its ``extra`` (:meth:`put_timing`).

A pool may keep a light lane (``light_cost`` > 0): a second, smaller pool of
one worker at the service's own priority for the queries whose ``prepare``
gives a :class:`Sized` solve of at most ``light_cost`` (the association
service: a robot's scan against its neighbourhood), so that heavy queries
filling the pool never hold up the small ones a live service waits for.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable

import zenoh

from schemas.codec import DecodeError, decode

log = logging.getLogger(__name__)

Solve = Callable[[float], tuple[str, bytes]]  # the time budget (s) -> (reply key, reply payload)
Outcome = tuple[str, bytes]  # (reply key, reply payload), or a QueryRefused


@dataclass(frozen=True)
class Sized:
    """A solve with its cost (the cells of its largest array): what a pool's light lane is chosen by."""

    solve: Solve
    cost: float


class QueryRefused(Exception):
    """A query answered with ``reply_err("reason: detail")`` and counted under ``reason``."""

    def __init__(self, reason: str, detail: str = ""):
        self.reason = reason
        self.detail = detail
        super().__init__(f"{reason}: {detail}" if detail else reason)


def decode_query(query: zenoh.Query, model):
    """The query's payload decoded as ``model``; QueryRefused (``empty``, or the codec's reason) otherwise."""
    if query.payload is None:
        raise QueryRefused("empty", f"the query carries no {model.__name__} payload")
    try:
        return decode(query.payload.to_bytes(), model)
    except DecodeError as error:
        raise QueryRefused(error.reason, error.detail) from None


def caller_timeout(query: zenoh.Query) -> float | None:
    """How long the caller waits (s), from the selector parameter ``timeout_s``; None when absent or not a positive
    number."""
    parameters = getattr(query, "parameters", None)
    text = parameters.get("timeout_s") if parameters is not None else None
    try:
        value = float(text) if text is not None else math.nan
    except ValueError:
        return None
    return value if math.isfinite(value) and value > 0 else None


def is_wildcard(key_expr) -> bool:
    """Whether a query's key expression names more than one key (``*``, ``**``, ``$*``)."""
    return "*" in str(key_expr)


class QueryPool:
    """A bounded queue of queries in front of ``workers`` solver threads, owned by one service (``shell``)."""

    def __init__(self, shell, workers: int, queue: int, deadline_s: float, nice: int = 0,
                 clock: Callable[[], float] = time.monotonic, light_cost: float = 0.0, light_queue: int = 0,
                 name: str = "query"):
        self.shell = shell
        self.name = name
        self.workers = workers
        self.queue = queue
        self.deadline_s = deadline_s
        self.clock = clock
        self._lock = threading.Lock()
        self._pending = 0  # admitted and not yet answered: waiting or being solved
        self._tally: dict[tuple[str, str], list] = {}  # (kind, key) -> [count, first detail], for the loop to take
        self._tally_taken = True  # no call to take the tally is waiting in the loop
        self._closing = False
        self._executor = ThreadPoolExecutor(workers, thread_name_prefix=f"{shell.name}-{name}", initializer=self._lower,
                                            initargs=(nice,))
        self.wait_ms: deque[float] = deque(maxlen=2000)
        self.solve_ms: deque[float] = deque(maxlen=2000)
        self.replies = 0
        self.light_cost = light_cost
        self.light = QueryPool(shell, 1, light_queue, deadline_s, 0, clock, name="light") if light_cost > 0 else None

    def _full(self) -> bool:
        with self._lock:
            return self._pending >= self.workers + self.queue

    def _reserve(self) -> bool:
        """Take a place for one more query; False when ``workers + queue`` are already in."""
        with self._lock:
            if self._pending >= self.workers + self.queue:
                return False
            self._pending += 1
            return True

    # ------------------------------------------------------------ admission (any thread)
    def admit(self, query: zenoh.Query, tag: str, prepare: Callable[[], Solve | Sized]) -> None:
        """Take one query (counted under ``tag``): ``busy`` when full; else ``prepare()`` (decode, validate, size:
        QueryRefused is answered at once) gives the solve, which a worker of its lane runs."""
        arrived = self.clock()
        self._count("in", tag)
        if self._full() and (self.light is None or self.light._full()):  # nothing is decoded then
            lanes = [self] if self.light is None else [self, self.light]
            self.answer(query, QueryRefused("busy", f"{' and '.join(lane._load() for lane in lanes)}; ask again later"))
            return
        try:
            prepared = prepare()
        except QueryRefused as refusal:
            self.answer(query, refusal)
            return
        except Exception as exc:  # noqa: BLE001 - the client must hear back, and the service must go on
            log.debug("%s: preparing a query failed", self.shell.name, exc_info=True)
            self.answer(query, QueryRefused("solve_error", f"{type(exc).__name__}: {exc}"))
            return
        solve, cost = (prepared.solve, prepared.cost) if isinstance(prepared, Sized) else (prepared, math.inf)
        lane = self.light if self.light is not None and cost <= self.light_cost else self
        if not lane._reserve():
            self.answer(query, QueryRefused("busy", f"{lane._load()}; ask again later"))
            return
        waits = caller_timeout(query)
        deadline_s = lane.deadline_s if waits is None else min(lane.deadline_s, waits)
        try:
            lane._executor.submit(lane._run, query, solve, arrived, deadline_s)
        except RuntimeError:  # shut down: the service is stopping
            lane._release()
            self.answer(query, QueryRefused("stopping", "the service is stopping"))

    def _load(self) -> str:
        return f"{self.workers} solving and {self.queue} waiting in the {self.name} lane"

    # ------------------------------------------------------------ workers
    def _run(self, query: zenoh.Query, solve: Solve, arrived: float, deadline_s: float) -> None:
        started = self.clock()
        waited = started - arrived
        outcome: Outcome | QueryRefused
        try:
            if self._closing:
                outcome = QueryRefused("stopping", "the service is stopping")
            elif waited > deadline_s:
                outcome = QueryRefused("expired", f"waited {waited:.2f} s in the queue, past the {deadline_s:g} s "
                                       "deadline: dropped unsolved")
            else:
                outcome = solve(deadline_s - waited)
        except QueryRefused as refusal:
            outcome = refusal
        except Exception as exc:  # noqa: BLE001 - a solver error is the query's, never the service's
            log.debug("%s: a query's solve failed", self.shell.name, exc_info=True)
            outcome = QueryRefused("solve_error", f"{type(exc).__name__}: {exc}")
        solved_s = self.clock() - started
        self._release()
        self.answer(query, outcome)
        self.shell.call_in_loop(self._timed, waited * 1e3, solved_s * 1e3)

    @staticmethod
    def _lower(nice: int) -> None:
        """A worker thread's start: ``nice`` more than the process (Linux schedules threads apart), so that on a busy
        processor the service's stream handling goes first."""
        if nice > 0 and hasattr(os, "setpriority"):
            try:
                os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), os.getpriority(os.PRIO_PROCESS, 0) + nice)
            except OSError as exc:
                log.debug("cannot lower a query worker's priority: %s", exc)

    def _release(self) -> None:
        with self._lock:
            self._pending -= 1

    def answer(self, query: zenoh.Query, outcome: Outcome | QueryRefused) -> None:
        """Send the one answer of a query, from any thread, and let it go (the caller's get ends when every
        queryable has); counted in the service's loop."""
        try:
            if isinstance(outcome, QueryRefused):
                query.reply_err(str(outcome).encode())
            else:
                query.reply(*outcome)
        except Exception as exc:  # noqa: BLE001 - the session may be closing; the answer is lost either way
            log.debug("%s: cannot answer a query: %s", self.shell.name, exc)
        finally:
            query.drop()
        if isinstance(outcome, QueryRefused):
            self._count("refused", outcome.reason, outcome.detail)
        else:
            self._count("replied", "")

    # ------------------------------------------------------------ counters
    def _count(self, kind: str, key: str, detail: str = "") -> None:
        """Count one query event from any thread. The counts reach the service's counters in its loop, a burst in
        one call: 500 queries at once made 1,000 calls into the loop that handles the robots' streams."""
        with self._lock:
            entry = self._tally.setdefault((kind, key), [0, detail])
            entry[0] += 1
            schedule, self._tally_taken = self._tally_taken, False
        if schedule:
            self.shell.call_in_loop(self._take_tally)

    def _take_tally(self) -> None:
        """In the service's loop: queries in (by tag), refusals (by reason) and replies since the last call."""
        with self._lock:
            tally, self._tally, self._tally_taken = self._tally, {}, True
        for (kind, key), (count, detail) in tally.items():
            if kind == "in":
                self.shell.messages_in[key] += count
            elif kind == "refused":
                self.shell.reject(key, detail, count)
            else:
                self.replies += count

    def _timed(self, wait_ms: float, solve_ms: float) -> None:
        self.wait_ms.append(wait_ms)
        self.solve_ms.append(solve_ms)

    @property
    def total_replies(self) -> int:
        """Replies of this pool and its light lane."""
        return self.replies + (self.light.replies if self.light is not None else 0)

    def put_stats(self) -> None:
        """Replies, queries in, and the median/p99 of the queue wait and the solve time, into the service's extra
        (``query_*``; the light lane's as ``light_*``)."""
        with self._lock:
            pending = self._pending
        self.shell.extra[f"{self.name}_replies"] = float(self.replies)
        self.shell.extra[f"{self.name}_pending"] = float(pending)
        self.shell.put_timing(f"{self.name}_wait_ms", self.wait_ms)
        self.shell.put_timing(f"{self.name}_solve_ms", self.solve_ms)
        if self.light is not None:
            self.light.put_stats()

    def close(self) -> None:
        """Stop taking queries; those still waiting are answered ``stopping``, a running solve ends by its deadline."""
        self._closing = True
        self._executor.shutdown(wait=False)
        if self.light is not None:
            self.light.close()
