"""Robot membership (services/roster.py) without a router: announcement, waiting, admission, new run vs link cut,
late join, refusals; and the cross-robot reorder buffer."""

import numpy as np

from schemas.contract import OdomEvent, ScanEvent
from schemas.messages import Odometry, RobotInfo, Scan, SensorSpec
from services.roster import ReorderBuffer, Roster


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
    roster = Roster(waiting_limit=10, info_timeout_s=2.0, clock=clock)
    assert roster.on_alive("r1") is True  # ask for its RobotInfo at once
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


def test_waiting_is_bounded_and_the_overflow_counted():
    roster = Roster(waiting_limit=3)
    reasons = [roster.on_stream("r1", "odom", odom(k)).refused for k in range(5)]
    assert reasons[:3] == [None, None, None] and all(r[0] == "waiting_overflow" for r in reasons[3:])
    roster.on_info("r1", info())
    assert [e.seq for e in roster.admit("r1")[0]] == [2, 3, 4]


def test_a_new_run_after_leaving_is_told_and_a_return_after_a_link_cut_is_not():
    roster = Roster()
    roster.on_alive("r1")
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
