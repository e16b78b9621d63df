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
