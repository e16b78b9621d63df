"""The reorder buffer's release (services/roster.py) against its first version, ``release_reference``: driven
through the same random histories (pushes of several robots' streams, some on another clock, the wall clock moving
on, stalls, announcements, link changes, robots dropped, robots live or not, queued or not), both release the same
events in the same order and keep the same ones."""

import copy
import pickle
import random

import numpy as np
import pytest

from schemas.contract import OdomEvent, ScanEvent
from services.roster import ReorderBuffer


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def make_event(rid: str, stream: str, seq: int, stamp: float):
    if stream == "odom":
        return OdomEvent(rid, seq, stamp, 0.1, np.zeros(2), np.eye(2))
    return ScanEvent(rid, seq, stamp, np.ones(1), np.zeros(1), None, np.eye(2) * 1e-3)


def key(pairs):
    return [(e.robot_id, type(e).__name__, e.seq, e.stamp, arrived) for e, arrived in pairs]


def heap_key(buffer: ReorderBuffer):
    return [entry[:4] + (entry[-1].arrived,) for entry in sorted(buffer._heap)]


def history(seed: int, steps: int = 400):
    """A random list of operations on a reorder buffer."""
    rng = random.Random(seed)
    robots = [f"r{k}" for k in range(rng.randint(1, 7))]
    base = {rid: (1.7e9 if rng.random() < 0.15 else rng.choice([0.0, 0.0, 400.0])) for rid in robots}
    stamp = {(rid, s): base[rid] for rid in robots for s in ("odom", "scan")}
    seq = {stream: 0 for stream in stamp}
    ops = []
    for _ in range(steps):
        roll = rng.random()
        if roll < 0.55:
            stream = rng.choice(list(stamp))
            stamp[stream] += rng.choice([0.0, 0.05, 0.1, 0.1, 0.1, 0.3, 2.0, 700.0 if rng.random() < 0.02 else 0.1])
            seq[stream] += 1
            ops.append(("push", stream[0], stream[1], seq[stream], stamp[stream]))
        elif roll < 0.70:
            ops.append(("tick", rng.choice([0.001, 0.01, 0.05, 0.05, 0.12, 0.3, 1.5, 6.0])))
        elif roll < 0.93:
            live = [rid for rid in robots if rng.random() < 0.85]
            announced = live + [rid for rid in robots if rid not in live and rng.random() < 0.5]
            queued = [rid for rid in robots if rng.random() < 0.2]
            ops.append(("release", live, announced, queued))
        else:
            ops.append(rng.choice([("announce", rng.choice(robots + ["late"])), ("link_changed",), ("listening",),
                                   ("drop", rng.choice(robots)), ("restart_clock",)]))
    return ops


@pytest.mark.parametrize("seed", range(60))
@pytest.mark.parametrize("window_s", [0.1, 0.5])
def test_release_matches_the_reference_on_random_histories(seed, window_s):
    clock = Clock()
    fast = ReorderBuffer(window_s, clock=clock, recovery_window_s=5.0, join_wait_s=1.0, clock_skew_s=600.0)
    reference = copy.deepcopy(fast)
    reference.clock = clock
    released = 0
    for op in history(seed):
        if op[0] == "push":
            _, rid, stream, seq, stamp = op
            event = make_event(rid, stream, seq, stamp)
            fast.push(event)
            reference.push(event)
        elif op[0] == "tick":
            clock.now += op[1]
        elif op[0] == "release":
            _, live, announced, queued = op
            a = fast.release(live, announced=announced, queued=queued)
            b = reference.release_reference(live, announced=announced, queued=queued)
            assert key(a) == key(b)
            released += len(a)
        elif op[0] == "drop":
            fast.drop_robot(op[1])
            reference.drop_robot(op[1])
        else:
            getattr(fast, op[0])(*op[1:])
            getattr(reference, op[0])(*op[1:])
        assert heap_key(fast) == heap_key(reference)
        assert fast._by_stamp == sorted((stamp, stream) for stream, stamp in fast.newest.items())
    restored = pickle.loads(pickle.dumps(fast))  # a checkpoint: the streams sorted again, not stored
    assert "_by_stamp" not in fast.__getstate__() and restored._by_stamp == fast._by_stamp
    assert key(fast.release([], flush=True)) == key(reference.release_reference([], flush=True))
    assert released > 0 or seed % 7 == 0  # the histories do release events (the check is not empty)


def test_release_takes_sets_and_lists_alike():
    clock = Clock()
    buffer = ReorderBuffer(0.1, clock=clock)
    for stamp in (1.0, 2.0):
        buffer.push(make_event("r1", "odom", int(stamp), stamp))
        buffer.push(make_event("r2", "scan", int(stamp), stamp))
    twin = copy.deepcopy(buffer)
    twin.clock = clock
    assert key(buffer.release({"r1", "r2"}, announced={"r1", "r2"}, queued=set())) == key(
        twin.release(["r1", "r2"], announced=["r1", "r2"], queued=[]))


@pytest.mark.parametrize("gap", [599.5, 600.0, 600.5])
def test_the_clock_skew_bound_is_the_references(gap):
    """Another robot's stream exactly ``clock_skew_s`` behind an event still holds it back; further behind, not."""
    for release in ("release", "release_reference"):
        clock = Clock()
        buffer = ReorderBuffer(0.1, clock=clock, clock_skew_s=600.0)
        buffer.push(make_event("r1", "odom", 0, 0.0))
        buffer.push(make_event("r1", "scan", 0, 0.0))
        buffer.push(make_event("r2", "odom", 0, gap))
        buffer.push(make_event("r2", "scan", 0, gap))
        out = getattr(buffer, release)(["r1", "r2"])
        assert [(e.robot_id, e.stamp) for e, _ in out] == [("r1", 0.0), ("r1", 0.0)] + (
            [("r2", gap), ("r2", gap)] if gap > 600.0 else []), release


@pytest.mark.parametrize("r5_stamp", [1499.5, 1500.0, 1500.5])
def test_a_stream_found_behind_an_earlier_event_still_holds_a_later_one_on_another_clock(r5_stamp):
    """Events past a held one by more than the clock skew are still looked at; a stream of another robot found
    behind one of them (r4, behind r3) holds back a later one (r5) exactly as far as the skew reaches."""
    outs = []
    for release in ("release", "release_reference"):
        clock = Clock()
        buffer = ReorderBuffer(0.1, clock=clock, clock_skew_s=600.0)
        for rid, stamp in (("r2", 10.0), ("r3", 1000.0), ("r5", r5_stamp)):
            buffer.push(make_event(rid, "odom", 0, stamp))
        clock.now += 0.2  # r2, r3 and r5 are silent now
        for rid, stamp in (("r1", 0.0), ("r4", 900.0)):
            buffer.push(make_event(rid, "odom", 0, stamp))
        live = ["r1", "r2", "r3", "r4", "r5"]
        outs.append([(e.robot_id, e.stamp) for e, _ in getattr(buffer, release)(live)])
    assert outs[0] == outs[1] == [("r1", 0.0), ("r4", 900.0)] + ([("r5", r5_stamp)] if r5_stamp > 1500.0 else [])
