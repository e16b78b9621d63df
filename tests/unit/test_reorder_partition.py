"""The reorder buffer across a site's link cut (issue 54's multi-site run): with ``partition_wait_s`` the other
robots' events wait for a robot that went silent and then lost its token, and a robot heard again after a silence
has its other stream waited for, so that its recovered streams go out in stamp order."""

from __future__ import annotations

import numpy as np

from schemas.contract import OdomEvent, ScanEvent
from services.roster import ReorderBuffer


def odom(rid: str, seq: int, stamp: float) -> OdomEvent:
    return OdomEvent(rid, seq, stamp, 0.1, np.zeros(2), np.eye(2))


def scan(rid: str, seq: int, stamp: float) -> ScanEvent:
    return ScanEvent(rid, seq, stamp, np.zeros(0), np.zeros(0), None, np.eye(2))


class Fleet:
    """Two robots at 10 Hz on a simulated wall clock; r1 is cut off from ``cut`` to ``back`` (its token gone after
    ``lease``), then sends what it missed: all its odometry first, then its scans ``scans_after`` later."""

    def __init__(self, buffer: ReorderBuffer, now: list[float]):
        self.buffer, self.now, self.out = buffer, now, []

    def run(self, until: float, cut: float, back: float, lease: float = 10.0, scans_after: float = 2.0,
            queued_at_gone: bool = False) -> list[tuple[str, float]]:
        backlog_sent = scans_sent = False
        for k in range(int(until * 10)):
            t = self.now[0] = round(k * 0.1, 1)
            self.buffer.listening()
            self.buffer.push(odom("r2", k, t))
            self.buffer.push(scan("r2", k, t))
            if not cut < t < back:
                if t >= back and not backlog_sent:  # the cut's odometry, recovered at once
                    for j in range(int(cut * 10) + 1, k):
                        self.buffer.push(odom("r1", j, round(j * 0.1, 1)))
                    backlog_sent = True
                if t >= back + scans_after and not scans_sent:  # the scans' part comes later
                    for j in range(int(cut * 10) + 1, k):
                        self.buffer.push(scan("r1", j, round(j * 0.1, 1)))
                    scans_sent = True
                if t < back or scans_sent:
                    self.buffer.push(odom("r1", k, t))
                    self.buffer.push(scan("r1", k, t))
                elif backlog_sent:
                    self.buffer.push(odom("r1", k, t))
            gone = cut + lease <= t < back
            live = ["r2"] if gone else ["r1", "r2"]
            queued = {"r1"} if queued_at_gone and abs(t - (cut + lease)) < 0.05 else set()
            self.out += [(ev.robot_id, ev.stamp) for ev, _ in self.buffer.release(live, announced=live, queued=queued)]
        return self.out


def in_stamp_order(out: list[tuple[str, float]]) -> bool:
    return all(a[1] <= b[1] for a, b in zip(out, out[1:]))


def test_a_cut_robot_is_waited_for_through_its_lease_and_its_absence_with_partition_wait():
    now = [0.0]
    out = Fleet(ReorderBuffer(2.0, clock=lambda: now[0], partition_wait_s=60.0), now).run(60.0, cut=6.6, back=36.6,
                                                                                            queued_at_gone=True)
    assert in_stamp_order(out)
    assert sum(rid == "r1" for rid, _ in out) > 500


def test_without_partition_wait_the_others_go_on_after_the_window():
    now = [0.0]
    out = Fleet(ReorderBuffer(2.0, clock=lambda: now[0]), now).run(60.0, cut=6.6, back=36.6)
    assert not in_stamp_order(out)  # r2 went on during the cut: what r1 recovered comes after


def test_partition_wait_is_bounded():
    now = [0.0]
    buffer = ReorderBuffer(2.0, clock=lambda: now[0], partition_wait_s=20.0)
    out = Fleet(buffer, now).run(60.0, cut=6.6, back=1e9)  # r1 never comes back
    assert max(stamp for rid, stamp in out if rid == "r2") > 30.0  # held 20 s of r1's silence, then on


def test_a_robot_heard_again_after_a_silence_waits_for_its_other_stream():
    """Without partition wait (the others went on): its odometry recovered first does not run ahead of its scans,
    recovered 4 s later (within the 5 s recovery window)."""
    now = [0.0]
    out = Fleet(ReorderBuffer(0.1, clock=lambda: now[0]), now).run(60.0, cut=6.6, back=36.6, scans_after=4.0)
    r1 = [(rid, stamp) for rid, stamp in out if rid == "r1"]
    assert in_stamp_order(r1)
