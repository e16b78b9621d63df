from schemas.streams import StreamTracker, Verdict


def test_tracker_accepts_in_order_and_counts_gaps():
    t = StreamTracker()
    assert [t.check("r1", "odom", s, s * 0.1) for s in (0, 1, 2, 5)] == [Verdict.ACCEPT] * 4
    assert t.missing("r1") == 2 and t.received("r1", "odom") == 4


def test_tracker_rejects_duplicates_reordering_and_time_going_backwards():
    t = StreamTracker()
    t.check("r1", "scan", 0, 1.0)
    t.check("r1", "scan", 1, 2.0)
    assert t.check("r1", "scan", 1, 2.0) is Verdict.DUPLICATE
    assert t.check("r1", "scan", 0, 1.0) is Verdict.OUT_OF_ORDER
    assert t.check("r1", "scan", 2, 1.5) is Verdict.TIME_BACKWARDS
    assert t.last_seq("r1", "scan") == 1
    assert dict(t.rejected) == {"duplicate": 1, "out_of_order": 1, "time_backwards": 1}
    assert t.check("r1", "scan", 2, 2.5) is Verdict.ACCEPT


def test_streams_are_independent_and_a_robot_can_be_forgotten():
    t = StreamTracker()
    t.check("r1", "scan", 3, 1.0)
    assert t.check("r2", "scan", 0, 0.0) is Verdict.ACCEPT
    assert t.missing("r1") == 3
    t.forget("r1")
    assert t.check("r1", "scan", 0, 0.0) is Verdict.ACCEPT


def test_a_robot_that_left_and_starts_again_at_seq_0_is_a_new_run():
    t = StreamTracker()
    for s in range(3):
        t.check("r1", "odom", s, s * 0.1)
    assert not t.new_run("r1", "odom", 0)  # still here: seq 0 again is a duplicate, not a new run
    t.leave("r1")
    assert not t.new_run("r1", "odom", 3)  # back after a link cut: it goes on with its seq numbers
    assert t.check("r1", "odom", 3, 0.3) is Verdict.ACCEPT
    assert not t.new_run("r2", "odom", 0)  # never seen: a first message, nothing to reset
    assert t.new_run("r1", "odom", 0)
    assert t.received("r1", "odom") == 0 and t.check("r1", "odom", 0, 0.0) is Verdict.ACCEPT
    assert not t.new_run("r1", "odom", 0)  # once per return


def test_an_observer_joining_late_counts_only_the_messages_lost_after_it_joined():
    late = StreamTracker(missing_before_join=False)
    filter_ = StreamTracker()
    for tracker in (late, filter_):
        for seq in (40, 41, 43):
            assert tracker.check("r1", "scan", seq, float(seq)) == Verdict.ACCEPT
    assert late.missing() == 1  # seq 42
    assert filter_.missing() == 41  # seq 0..39 before it joined, and 42


def test_a_new_run_is_told_by_its_publishing_session_when_known():
    tracker = StreamTracker()
    for seq in range(3):
        assert tracker.check("r1", "odom", seq, float(seq), source="old") is Verdict.ACCEPT
    assert not tracker.new_run("r1", "odom", 0, source="old")  # its own cache sending it again
    assert tracker.same_source("r1", "odom", "old") and not tracker.same_source("r1", "odom", "new")
    assert tracker.new_run("r1", "odom", 0, source="new")  # a restarted process, token or not
    assert tracker.received("r1", "odom") == 0 and not tracker.sources
    tracker.check("r1", "odom", 0, 0.0, source="new")
    tracker.leave("r1")
    assert not tracker.new_run("r1", "odom", 0, source="new")  # left, but the same session: not a new run
    assert tracker.new_run("r1", "odom", 0)  # session unknown: leaving is what tells


def test_implausible_jumps_are_refused_and_never_move_the_stream():
    t = StreamTracker()
    for seq in range(3):
        assert t.check("r1", "odom", seq, 0.1 * seq, rate_hz=10.0) is Verdict.ACCEPT
    assert t.check("r1", "odom", 2**62, 0.3, rate_hz=10.0) is Verdict.SEQ_JUMP  # two of these once killed a stream
    assert t.check("r1", "odom", 3, 1e12, rate_hz=10.0) is Verdict.STAMP_JUMP
    assert t.last_seq("r1", "odom") == 2 and t.last_stamp("r1", "odom") == 0.2 and t.missing() == 0
    assert t.check("r1", "odom", 3, 0.3, rate_hz=10.0) is Verdict.ACCEPT  # the real stream goes on
    assert t.check("r1", "odom", 3 + 300, 10.3, rate_hz=10.0) is Verdict.ACCEPT  # 10 s lost at 10 Hz: plausible
    assert t.missing() == 299 and dict(t.rejected) == {"seq_jump": 1, "stamp_jump": 1}


def test_a_first_message_far_from_the_robots_start_is_refused_when_the_start_is_known():
    t = StreamTracker()
    assert t.check("r1", "scan", 2**62, 5.0, rate_hz=10.0, origin=0.0) is Verdict.SEQ_JUMP
    assert t.missing() == 0  # never an impossible count
    assert t.check("r1", "scan", 50, 5.0, rate_hz=10.0, origin=0.0) is Verdict.ACCEPT and t.missing() == 50


def test_odometry_whose_dt_disagrees_with_its_stamps_or_beyond_the_limits_is_doubted():
    import numpy as np

    from schemas.messages import Odometry, RobotInfo, SensorSpec
    from schemas.streams import odometry_doubt

    info = RobotInfo(robot_id="r1", stamp=0.0, motion_model="unicycle",
                     sensor=SensorSpec(max_range=5.0, fov=3.0, noise_cov=np.eye(2) * 1e-3), odom_rate_hz=10.0,
                     scan_rate_hz=10.0, max_speed=1.0, max_turn_rate=0.5)

    def odom(seq, stamp, dt, v=0.5, w=0.0):
        return Odometry(robot_id="r1", seq=seq, stamp=stamp, dt=dt, control=np.array([v, w]), control_cov=np.eye(2))

    assert odometry_doubt(odom(1, 0.2, 0.1), info, 0.1, True, 0.1) is None
    assert odometry_doubt(odom(1, 0.2, 10.0), info, 0.1, True, 0.1)[0] == "dt_mismatch"  # dt = 10 s in 0.1 s
    assert odometry_doubt(odom(5, 3.0, 0.1), info, 0.1, False, 0.1) is None  # after a gap dt covers the last interval
    assert odometry_doubt(odom(1, 3.0, 0.1), info, 0.1, True, 0.1)[0] == "dt_mismatch"  # right after: it must cover
    assert odometry_doubt(odom(1, 0.2, 0.1, v=2.0), info, 0.1, True, 0.1)[0] == "control_limit"
    assert odometry_doubt(odom(1, 0.2, 0.1, w=-0.8), info, 0.1, True, 0.1)[0] == "control_limit"
    assert odometry_doubt(odom(1, 0.2, 0.1, v=2.0), info.model_copy(update={"max_speed": None}), 0.1, True, 0.1) is None
