"""Robot membership (services/roster.py) without a router: announcement, waiting, admission, new run vs link cut,
late join, refusals; and the cross-robot reorder buffer."""

import asyncio

import numpy as np
import pytest

from schemas.codec import encode
from schemas.config import FleetSettings
from schemas.contract import OdomEvent, ScanEvent, event_nbytes, stream_event
from schemas.messages import Odometry, RobotInfo, Scan, SensorSpec
from services.roster import ReorderBuffer, Roster
from services.runtime import ServiceShell


class Clock:
    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


def info(rid="r1"):
    return RobotInfo(robot_id=rid, stamp=0.0, motion_model="unicycle", sensor=SensorSpec(max_range=5.0, fov=3.0, noise_cov=np.eye(2) * 1e-3),
                     start_pose=np.zeros(3), odom_rate_hz=10.0, scan_rate_hz=10.0)


def odom(seq, rid="r1", stamp=None):
    return Odometry(robot_id=rid, seq=seq, stamp=0.1 * seq if stamp is None else stamp, dt=0.1,
                    control=np.array([0.1, 0.0]), control_cov=np.eye(2) * 1e-3)


def scan(seq, rid="r1"):
    return Scan(robot_id=rid, seq=seq, stamp=0.1 * seq, ranges=np.array([1.0]), bearings=np.array([0.0]),
                noise_cov=np.eye(2) * 1e-3)


def test_messages_wait_for_the_announcement_and_flow_in_order_once_admitted():
    clock = Clock()
    roster = Roster(waiting_bytes=1 << 20, info_timeout_s=2.0, clock=clock)
    takeover, refused = roster.on_token("r1", "s1")
    assert takeover.ask_info is True and refused is None  # its session holds the id: ask for its RobotInfo at once
    first = roster.on_stream("r1", "odom", odom(0))
    assert first.event is None and first.refused is None and first.ask_info is False  # asked a moment ago
    clock.now = 2.5
    assert roster.on_stream("r1", "scan", scan(0)).ask_info is True  # still unannounced: ask again
    assert roster.on_info("r1", info()) == (True, None)
    assert roster.on_info("r1", info()) == (False, None)  # robots republish: announced once per run
    held, dropped = roster.admit("r1")
    assert dropped == 0 and [(type(e), e.seq) for e in held] == [(OdomEvent, 0), (ScanEvent, 0)]
    arrival = roster.on_stream("r1", "odom", odom(1))
    assert isinstance(arrival.event, OdomEvent) and arrival.event.seq == 1 and arrival.refused is None


def test_refusals_carry_their_reason_and_never_reach_the_service():
    roster = Roster()
    roster.on_info("r1", info())
    roster.admit("r1")
    assert roster.on_info("r2", info("r1"))[1][0] == "robot_id_mismatch"
    assert roster.on_stream("r2", "odom", odom(0, "r1")).refused[0] == "robot_id_mismatch"
    assert roster.on_stream("r1", "odom", odom(5)).event is not None
    assert roster.on_stream("r1", "odom", odom(5)).refused[0] == "duplicate"
    assert roster.on_stream("r1", "odom", odom(3)).refused[0] == "out_of_order"
    backwards = roster.on_stream("r1", "odom", odom(6, stamp=0.0))
    assert backwards.refused[0] == "time_backwards" and backwards.event is None
    assert roster.missing() == 5  # seq 0-4 never came


def test_waiting_is_bounded_in_bytes_and_the_overflow_counted():
    size = event_nbytes(stream_event(odom(0)))
    roster = Roster(waiting_bytes=3 * size)
    reasons = [roster.on_stream("r1", "odom", odom(k)).refused for k in range(5)]
    assert reasons[:3] == [None, None, None] and all(r[0] == "waiting_overflow" for r in reasons[3:])
    assert roster.counts["waiting_dropped"] == 2
    roster.on_info("r1", info())
    assert [e.seq for e in roster.admit("r1")[0]] == [2, 3, 4]
    assert roster.member("r1").waiting_bytes == 0


def test_a_big_scan_pushes_out_as_many_small_messages_as_its_bytes_need():
    roster = Roster(waiting_bytes=4000)
    for k in range(5):
        roster.on_stream("r1", "odom", odom(k))
    big = Scan(robot_id="r1", seq=0, stamp=0.5, ranges=np.ones(150), bearings=np.zeros(150), noise_cov=np.eye(2) * 1e-3)
    assert roster.on_stream("r1", "scan", big).refused[0] == "waiting_overflow"
    held = roster.member("r1").waiting
    assert sum(event_nbytes(e) for e in held) <= 4000 and isinstance(held[-1], ScanEvent)
    assert roster.counts["waiting_dropped"] == 5 - (len(held) - 1)


def test_a_gap_is_reported_with_the_message_after_it():
    roster = Roster()
    roster.on_info("r1", info())
    roster.admit("r1")
    assert roster.on_stream("r1", "odom", odom(0)).gap == 0
    assert roster.on_stream("r1", "odom", odom(1)).gap == 0
    assert roster.on_stream("r1", "odom", odom(5)).gap == 3
    assert roster.on_stream("r1", "odom", odom(6)).gap == 0


def test_after_resuming_what_the_caches_send_again_is_already_held_not_refused():
    import pickle

    roster = Roster()
    roster.on_token("r1", "s1")
    roster.on_info("r1", info())
    roster.admit("r1")
    for k in range(6):
        roster.on_stream("r1", "odom", odom(k))
    restored = pickle.loads(pickle.dumps(roster))
    restored.resume()
    assert restored.alive_ids() == ["r1"] and restored.is_admitted("r1")
    again = [restored.on_stream("r1", "odom", odom(k)) for k in range(6)]  # the cache from seq 0
    assert all(a.event is None and a.refused is None for a in again)
    assert restored.counts["already_held"] == 6 and not restored.tracker.rejected
    after = restored.on_stream("r1", "odom", odom(6))
    assert after.event is not None and after.event.seq == 6 and after.gap == 0
    assert restored.on_stream("r1", "odom", odom(6)).refused[0] == "duplicate"  # past the checkpoint: a real duplicate


def test_a_new_run_after_leaving_is_told_and_a_return_after_a_link_cut_is_not():
    roster = Roster()
    roster.on_token("r1", "s1")
    roster.on_info("r1", info())
    roster.admit("r1")
    for k in range(3):
        roster.on_stream("r1", "odom", odom(k))
    roster.on_gone("r1")
    back = roster.on_stream("r1", "odom", odom(3))  # link cut: the seq numbers go on
    assert not back.new_run and back.event is not None
    roster.on_gone("r1")
    again = roster.on_stream("r1", "odom", odom(0))
    assert again.new_run and again.event is None and again.ask_info  # a new run: announced afresh before it flows
    assert roster.info("r1") is None and roster.counts["robot_restarts"] == 1
    assert roster.on_info("r1", info()) == (True, None)
    assert [e.seq for e in roster.admit("r1")[0]] == [0]


def test_late_join_and_admission_after_a_placement_stamp():
    roster = Roster()
    roster.on_info("r1", info())
    late = roster.on_stream("r1", "odom", odom(7))
    assert late.late and roster.counts["robots_joined_late"] == 1
    assert not roster.on_stream("r1", "odom", odom(8)).late
    kept, dropped = roster.admit("r1", after=0.75)
    assert [e.seq for e in kept] == [8] and dropped == 1
    roster.hold("r1")
    assert roster.on_stream("r1", "odom", odom(9)).event is None and roster.waiting_count() == 1


def event(rid, stamp):
    return OdomEvent(rid, 0, stamp, 0.1, np.zeros(2), np.eye(2))


def test_reorder_buffer_releases_by_watermark_window_and_flush():
    clock = Clock()
    buffer = ReorderBuffer(window_s=0.1, clock=clock)
    buffer.push(event("r1", 1.0))
    buffer.push(event("r1", 2.0))
    buffer.push(event("r2", 1.5))
    released = buffer.release(live=["r1", "r2"])  # watermark = min(2.0, 1.5)
    assert [(e.robot_id, e.stamp) for e, _ in released] == [("r1", 1.0), ("r2", 1.5)]
    assert buffer.release(live=["r1", "r2"]) == [] and len(buffer) == 1
    clock.now = 0.2  # waited longer than the window
    assert [e.stamp for e, _ in buffer.release(live=["r1", "r2"])] == [2.0]
    buffer.push(event("r2", 3.0))
    buffer.push(event("r1", 2.5))
    buffer.drop_robot("r2")
    assert [e.robot_id for e, _ in buffer.release(live=["r1", "r2"], flush=True)] == ["r1"]


def test_a_robot_on_another_clock_is_not_held_behind_a_robot_that_keeps_streaming():
    """A simulated robot stamps from 0, a real one in Unix time: the real robot's events do not wait for the
    simulated one to catch up (it never would), while stamps within the skew are still merged in order."""
    clock = Clock()
    buffer = ReorderBuffer(window_s=0.1, clock=clock, clock_skew_s=600.0)
    buffer.push(event("sim", 10.0))
    buffer.push(event("real", 1.8e9))
    buffer.push(event("near", 11.0))
    released = buffer.release(live=["sim", "real", "near"])
    assert [(e.robot_id, e.stamp) for e, _ in released] == [("sim", 10.0), ("real", 1.8e9)]
    buffer.push(event("sim", 10.5))  # the simulated robot streams on: the near one waits for it, as before
    assert [(e.robot_id, e.stamp) for e, _ in buffer.release(live=["sim", "real", "near"])] == [("sim", 10.5)]
    strict = ReorderBuffer(window_s=0.1, clock=Clock(), clock_skew_s=float("inf"))
    strict.push(event("sim", 10.0))
    strict.push(event("real", 1.8e9))
    strict.push(event("sim", 10.5))
    assert [e.robot_id for e, _ in strict.release(live=["sim", "real"])] == ["sim", "sim"]  # without it: held


def test_reorder_buffer_waits_for_each_stream_of_a_robot():
    """After a link cut the scans of a robot may be recovered before its odometry: a scan waits for the odometry
    stream to pass its stamp (within the window), so a robot's events are handled in time order."""
    clock = Clock()
    buffer = ReorderBuffer(window_s=0.1, clock=clock)
    buffer.push(event("r1", 1.0))
    buffer.push(ScanEvent("r1", 0, 2.0, np.ones(1), np.zeros(1), None, np.eye(2) * 1e-3))
    assert [e.stamp for e, _ in buffer.release(live=["r1"])] == [1.0]  # odometry has reached 1.0 only
    buffer.push(event("r1", 1.9))
    buffer.push(event("r1", 2.1))
    released = buffer.release(live=["r1"])
    assert [(type(e).__name__, e.stamp) for e, _ in released] == [("OdomEvent", 1.9), ("ScanEvent", 2.0)]


def test_a_robot_that_announced_itself_is_waited_for_until_it_sends_or_for_the_join_wait():
    """r2 declared its session token and has sent nothing: r1's events wait (r2 may start a moment later on the same
    clock); once r2 sends, everything goes in stamp order. A robot announced and silent holds the others back only
    ``join_wait_s``, and only while it is alive."""
    clock = Clock()
    buffer = ReorderBuffer(window_s=0.1, clock=clock, join_wait_s=1.0)

    def both(rid, stamp):
        buffer.push(event(rid, stamp))
        buffer.push(ScanEvent(rid, 0, stamp, np.ones(1), np.zeros(1), None, np.eye(2) * 1e-3))

    buffer.announce("r1")
    buffer.announce("r2")
    both("r1", 0.0)
    both("r1", 0.1)
    clock.now = 0.5  # longer than the window: without the announcement r1's events would have gone
    assert buffer.release(live=["r1"], announced=["r1", "r2"]) == []
    both("r2", 0.05)
    both("r2", 0.1)
    released = buffer.release(live=["r1", "r2"], announced=["r1", "r2"])
    assert [(e.robot_id, e.stamp) for e, _ in released] == [("r1", 0.0), ("r1", 0.0), ("r2", 0.05), ("r2", 0.05),
                                                            ("r1", 0.1), ("r2", 0.1), ("r1", 0.1), ("r2", 0.1)]
    buffer.announce("r3")
    both("r1", 0.2)
    both("r2", 0.2)
    assert buffer.release(live=["r1", "r2"], announced=["r1", "r2", "r3"]) == []
    assert len(buffer.release(live=["r1", "r2"], announced=["r1", "r2"])) == 4  # r3 went: no longer waited for
    both("r1", 0.3)
    both("r2", 0.3)
    assert buffer.release(live=["r1", "r2"], announced=["r1", "r2", "r3"]) == []  # r3 back, still silent
    clock.now = 1.6  # r3 silent for the join wait since its announcement at 0.5
    assert len(buffer.release(live=["r1", "r2"], announced=["r1", "r2", "r3"])) == 4


def test_after_the_router_link_changes_every_stream_is_waited_for_until_it_is_recovered():
    """A router restart takes every robot's token away and brings the streams back one by one: r1's recovered
    events wait for r2's stream (token not back yet) up to the recovery window, and go in stamp order once r2's
    come."""
    clock = Clock()
    buffer = ReorderBuffer(window_s=0.1, clock=clock, recovery_window_s=5.0)
    for rid in ("r1", "r2"):
        buffer.push(event(rid, 1.0))
    assert len(buffer.release(live=["r1", "r2"])) == 2
    buffer.link_changed()
    clock.now = 1.0
    buffer.push(event("r1", 1.1))
    buffer.push(event("r1", 1.2))
    assert buffer.release(live=["r1"]) == []  # r2 is not live (token gone) but its stream is being recovered
    buffer.push(event("r2", 1.15))  # its token back with it
    assert [(e.robot_id, e.stamp) for e, _ in buffer.release(live=["r1", "r2"])] == [("r1", 1.1), ("r2", 1.15)]
    buffer.link_changed()
    buffer.push(event("r1", 1.3))
    assert buffer.release(live=["r1"]) == []
    clock.now = 6.5  # r2 silent for the recovery window since the link changed
    assert [e.stamp for e, _ in buffer.release(live=["r1"])] == [1.2, 1.3]


def test_a_stall_of_the_service_itself_is_not_silence_of_the_streams():
    """The service's process was descheduled for 0.6 s (longer than the window): r2's next message still waits in
    the network buffers when r1's is pushed. r1's event waits for r2 as if the stall had not happened; a stream
    silent while the service listens is still given up after the window."""
    clock = Clock()
    buffer = ReorderBuffer(window_s=0.5, clock=clock)
    buffer.listening()
    for rid in ("r1", "r2"):
        buffer.push(event(rid, 1.0))
    assert len(buffer.release(live=["r1", "r2"])) == 2
    clock.now = 0.05
    assert buffer.listening() == 0.0  # a tick on time
    clock.now = 0.65
    assert buffer.listening() == pytest.approx(0.6)  # the stall
    buffer.push(event("r1", 1.1))
    assert buffer.release(live=["r1", "r2"]) == []  # r2 heard 0.05 s of listening ago
    buffer.push(event("r2", 1.1))
    assert [e.robot_id for e, _ in buffer.release(live=["r1", "r2"])] == ["r1", "r2"]
    buffer.push(event("r1", 1.2))
    for tick in range(1, 12):  # 0.55 s of listening: r2 silent longer than the window
        clock.now = 0.65 + 0.05 * tick
        assert buffer.listening() == 0.0
    assert [e.stamp for e, _ in buffer.release(live=["r1", "r2"])] == [1.2]


def test_a_robot_with_messages_still_queued_is_not_silent():
    """A service working off a backlog takes r2's queued messages later than they came: r2 is waited for while its
    messages wait in the intake (up to the recovery window), not only for the window since its last one was handled."""
    clock = Clock()
    buffer = ReorderBuffer(window_s=0.1, clock=clock, recovery_window_s=5.0)
    buffer.push(event("r1", 1.0))
    buffer.push(event("r2", 1.0))
    buffer.push(event("r1", 2.0))
    clock.now = 1.0
    released = buffer.release(live=["r1", "r2"], queued=["r2"])
    assert [(e.robot_id, e.stamp) for e, _ in released] == [("r1", 1.0), ("r2", 1.0)]
    assert [e.stamp for e, _ in buffer.release(live=["r1", "r2"])] == [2.0]  # r2 silent, nothing queued
    buffer.push(event("r1", 3.0))
    clock.now = 6.5  # queued for longer than the recovery window: no longer waited for
    assert [e.stamp for e, _ in buffer.release(live=["r1", "r2"], queued=["r2"])] == [3.0]


def test_a_restarted_robot_process_is_a_new_run_even_if_its_token_never_went_away():
    roster = Roster()
    roster.on_info("r1", info())
    roster.admit("r1")
    for k in range(4):
        roster.on_stream("r1", "odom", odom(k), source="aaaa")
    assert roster.on_stream("r1", "odom", odom(0), source="aaaa").refused[0] == "out_of_order"  # same session: old
    restarted = roster.on_stream("r1", "odom", odom(0), source="bbbb")
    assert restarted.new_run and restarted.refused is None and roster.info("r1") is None


def test_after_resuming_a_robot_restarted_meanwhile_is_a_new_run_not_history():
    import pickle

    roster = Roster()
    roster.on_info("r1", info())
    roster.admit("r1")
    for k in range(6):
        roster.on_stream("r1", "odom", odom(k), source="aaaa")
    restored = pickle.loads(pickle.dumps(roster))
    restored.resume()
    assert restored.on_stream("r1", "odom", odom(0), source="aaaa").new_run is False  # the same run's cache
    assert restored.counts["already_held"] == 1
    assert restored.on_stream("r1", "odom", odom(0), source="cccc").new_run is True  # a new process of r1
    restored.on_info("r1", info())
    restored.admit("r1")
    assert restored.on_stream("r1", "odom", odom(1), source="cccc").event.seq == 1  # no longer taken as history


def test_a_robot_waiting_for_its_own_stream_does_not_hold_the_others_back():
    """r1's odometry is being recovered (silent longer than the cross-robot window, shorter than the recovery
    window): r1's scan waits for it, r2's later events go on; once r1's odometry passes, r1's events follow."""
    clock = Clock()
    buffer = ReorderBuffer(window_s=0.1, clock=clock, recovery_window_s=5.0)
    buffer.push(event("r1", 1.0))
    buffer.push(ScanEvent("r1", 0, 2.0, np.ones(1), np.zeros(1), None, np.eye(2) * 1e-3))
    clock.now = 1.0
    buffer.push(event("r2", 2.5))
    buffer.push(event("r2", 3.0))
    released = buffer.release(live=["r1", "r2"])
    assert [(e.robot_id, e.stamp) for e, _ in released] == [("r1", 1.0), ("r2", 2.5), ("r2", 3.0)]
    clock.now = 2.0
    buffer.push(event("r1", 2.0))
    assert [(type(e).__name__, e.stamp) for e, _ in buffer.release(live=["r1", "r2"])] == [("OdomEvent", 2.0),
                                                                                           ("ScanEvent", 2.0)]
    buffer.push(ScanEvent("r1", 1, 4.0, np.ones(1), np.zeros(1), None, np.eye(2) * 1e-3))
    clock.now = 7.5  # r1's odometry silent past the recovery window: the scan goes
    assert [e.stamp for e, _ in buffer.release(live=["r1", "r2"])] == [4.0]


def test_while_a_robot_is_refilled_a_gap_waits_to_be_filled_in_order():
    """After a restart the robot's kept messages are asked for: a live message past a gap is parked, the history
    fills the gap, the parked message follows in order; what both send twice is already held, not refused."""
    clock = Clock()
    roster = Roster(clock=clock)
    roster.on_info("r1", info())
    roster.admit("r1")
    for k in range(3):
        roster.on_stream("r1", "odom", odom(k))
    roster.refill("r1")
    assert roster.on_stream("r1", "odom", odom(6)).event is None  # live, past a gap: parked
    taken = []
    for k in (1, 2, 3, 4):  # the robot's history: 1, 2 already held; 3, 4 fill the gap
        arrival = roster.on_stream("r1", "odom", odom(k))
        assert arrival.refused is None and arrival.gap == 0
        taken += [arrival.event] + [a.event for a in roster.unparked("r1", "odom")]
    assert [e.seq for e in taken if e is not None] == [3, 4]
    assert roster.counts["already_held"] == 2
    arrivals = roster.refilled("r1")  # 5 never came: the parked 6 is taken, the gap counted
    assert [(a.event.seq, a.gap, stream) for a, stream in arrivals] == [(6, 1, "odom")]
    held = roster.counts["already_held"]
    assert roster.on_stream("r1", "odom", odom(6)).refused is None  # soon after: the other history's repeat
    assert roster.counts["already_held"] == held + 1
    clock.now = 11.0  # past the grace: a repeat is a duplicate again
    assert roster.on_stream("r1", "odom", odom(6)).refused[0] == "duplicate"


def test_a_gap_filled_while_refilling_releases_the_parked_messages_at_once():
    roster = Roster()
    roster.on_info("r1", info())
    roster.admit("r1")
    roster.on_stream("r1", "scan", scan(0))
    roster.refill("r1")
    for k in (3, 2):
        assert roster.on_stream("r1", "scan", scan(k)).event is None
    first = roster.on_stream("r1", "scan", scan(1))
    assert first.event.seq == 1 and [a.event.seq for a in roster.unparked("r1", "scan")] == [2, 3]
    assert roster.missing() == 0 and roster.refilled("r1") == []


def test_a_robot_id_belongs_to_the_first_session_holding_its_token():
    roster = Roster()
    takeover, refused = roster.on_token("r1", "real")
    assert takeover is not None and refused is None and roster.owner("r1") == "real"
    takeover, refused = roster.on_token("r1", "forger")
    assert takeover is None and refused[0] == "second_announcer" and roster.owner("r1") == "real"
    assert roster.identify("r1", "odom", odom(0), "real", 100) == ("own", None)
    whose, refused = roster.identify("r1", "info", info(), "forger", 100)
    assert whose == "refused" and refused[0] == "not_owner"
    assert roster.identify("r1", "odom", odom(1), None, 100)[1][0] == "no_source"
    takeover, left = roster.on_token_gone("r1", "real")  # the owner went while the forger holds a token too
    assert not left and roster.owner("r1") == "forger" and takeover is not None


def test_messages_of_an_id_no_session_holds_wait_within_a_budget_then_go_counted():
    clock = Clock()
    roster = Roster(clock=clock, unannounced_bytes=1000, unannounced_s=30.0)
    for k in range(3):
        assert roster.identify("r9", "odom", odom(k, "r9"), "s9", 300) == ("held", None)
    whose, refused = roster.identify("r9", "odom", odom(3, "r9"), "s9", 300)
    assert whose == "held" and refused[0] == "unannounced_dropped" and refused[2] == 1  # the oldest went
    roster.identify("r8", "odom", odom(0, "r8"), "s8", 10)
    roster.identify("r8", "odom", odom(1, "r8"), "other", 10)
    takeover, _ = roster.on_token("r8", "s8")  # r8's session appears: what it sent is taken, the rest refused
    assert [m.seq for _, m, _ in takeover.take] == [0] and takeover.not_owner == 1
    clock.now = 31.0
    assert roster.expire_pending() == 3 and roster.pending_count() == 0 and roster.pending_bytes == 0
    assert roster.counts["unannounced_dropped"] == 4
    assert roster.identify("r7", "scan", scan(0, "r7"), "s7", 2000)[1][0] == "unannounced_dropped"  # over the budget


def test_the_tail_of_a_robot_whose_token_went_is_still_its_own_and_a_checkpoint_resumes_ownership():
    import pickle

    roster = Roster()
    roster.on_token("r1", "s1")
    roster.on_token_gone("r1", "s1")
    assert roster.identify("r1", "scan", scan(5), "s1", 100) == ("own", None)  # its last messages, recovered late
    assert roster.identify("r1", "scan", scan(5), "s2", 100)[0] == "held"  # another session: wait for its token
    roster.on_token("r1", "s1")
    restored = pickle.loads(pickle.dumps(roster))
    restored.resume()
    assert restored.owner("r1") is None and restored.identify("r1", "odom", odom(0), "s1", 10) == ("own", None)


def test_plausibility_uses_the_announced_rate_start_and_limits():
    roster = Roster()
    roster.on_info("r1", info().model_copy(update={"max_speed": 0.5, "max_turn_rate": 0.5}))
    roster.admit("r1")
    assert roster.on_stream("r1", "odom", odom(0)).event is not None
    forged = Odometry(robot_id="r1", seq=1, stamp=0.1, dt=10.0, control=np.array([2.0, 0.0]),
                      control_cov=np.eye(2) * 1e-3)
    assert roster.on_stream("r1", "odom", forged).refused[0] == "dt_mismatch"
    fast = Odometry(robot_id="r1", seq=1, stamp=0.1, dt=0.1, control=np.array([2.0, 0.0]), control_cov=np.eye(2))
    assert roster.on_stream("r1", "odom", fast).refused[0] == "control_limit"
    assert roster.on_stream("r1", "odom", odom(2**62, stamp=0.1)).refused[0] == "seq_jump"
    far = scan(0).model_copy(update={"seq": 10**6, "stamp": 1.0})  # its first scan, a million seqs after the start
    assert roster.on_stream("r1", "scan", far).refused[0] == "seq_jump"
    assert roster.on_stream("r1", "odom", odom(1)).event is not None and roster.missing() == 0


class ShellWithoutRouter(ServiceShell):
    """A service shell fed by hand through ``_robot_item`` (no router): it records the seq of every event it hands
    on, and raises on the event of seq ``fail_at`` (a bug met by one message)."""

    def __init__(self, fail_at: int | None = None):
        super().__init__(FleetSettings(prefix="fleet", reorder_window_s=0.0))
        self.roster = Roster()
        self.events = []
        self.fail_at = fail_at

    def ask_info(self, robot_id):  # no router: its RobotInfo is handed in by the test
        pass

    async def robot_event(self, event):
        if event.seq == self.fail_at:
            raise RuntimeError("a bug met by one message")
        self.events.append(event.seq)

    async def odometry(self, *seqs: int) -> None:
        for seq in seqs:
            await self._robot_item("odom", "fleet/robots/r1/odom", encode(odom(seq)), "zA")

    async def join(self) -> None:
        """r1's session token and RobotInfo, from session zA."""
        await self._robot_item("alive", "fleet/robots/r1/alive/zA", b"")
        await self._robot_item("info", "fleet/robots/r1/info", encode(info()), "zA")

    async def refilled(self, *seqs: int) -> None:
        """The end of r1's history query, with its kept odometry of ``seqs``."""
        replies = [("odom", "fleet/robots/r1/odom", encode(odom(seq)), "zA") for seq in seqs]
        await self._robot_item("refilled", "fleet/robots/r1/history", (replies, 0))


def test_a_restarted_service_takes_the_robots_kept_messages_before_it_counts_a_gap():
    """After a restart the service asks the robot for what it kept (``refill_from_robots``); a live message past the
    gap waits. The answer comes as one ``refilled`` item, replies first: the gap is filled in order and nothing is
    counted lost, whatever lane the live messages were queued in (shell ``ServiceShell._robot_item``, no router)."""
    async def scenario(shell: ShellWithoutRouter):
        await shell.join()
        await shell.odometry(0, 1, 2)
        shell.roster.refill("r1")  # restarted from a checkpoint that held seq 2: the robot is asked for the rest
        await shell.odometry(5)  # live, past the gap: waits
        assert shell.events == [0, 1, 2]
        await shell.refilled(3, 4)

    shell = ShellWithoutRouter()
    asyncio.run(scenario(shell))
    assert shell.events == [0, 1, 2, 3, 4, 5]
    assert shell.roster.tracker.missing("r1") == 0 and not shell.rejected
    assert shell.messages_in["odom"] == 2  # the replies count as the odometry they are


def test_a_reply_that_fails_in_the_handler_does_not_keep_the_robot_parked():
    """One kept message that breaks the service's handler is counted (``handler_error``) and the rest of the answer,
    then the parked live messages, are still taken."""
    async def scenario(shell: ShellWithoutRouter):
        await shell.join()
        await shell.odometry(0)
        shell.roster.refill("r1")
        await shell.odometry(3)  # past the gap: parked
        await shell.refilled(1, 2, 3, 4)
        await shell.odometry(5)

    shell = ShellWithoutRouter(fail_at=3)
    asyncio.run(scenario(shell))
    assert shell.events == [0, 1, 2, 4, 5] and shell.rejected["handler_error"] == 1
    assert not shell.roster.refilling and not shell.roster.parked
