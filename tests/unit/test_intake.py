"""The bounded, fair intake between Zenoh callbacks and a service's loop (services/intake.py)."""

from services.intake import Intake


def test_oversize_samples_are_refused_before_anything_else():
    intake = Intake(lane_bytes=1000, total_bytes=10_000, limits={"scan": 100})
    assert intake.put("scan", ("r1", "s"), "big", 101) == "oversize"
    assert intake.put("scan", ("r1", "s"), "ok", 100) is None
    assert intake.put("odom", ("r1", "s"), "no limit for odom", 500) is None
    assert len(intake) == 2 and intake.refused["oversize"] == 1


def test_lanes_are_served_in_turn_so_a_flood_only_delays_itself():
    intake = Intake(lane_bytes=10_000, total_bytes=100_000)
    for k in range(50):
        intake.put("scan", ("r1", "attacker"), f"flood{k}", 10)
    intake.put("odom", ("r2", "real"), "r2-0", 10)
    intake.put("odom", ("r2", "real"), "r2-1", 10)
    first = [intake.get() for _ in range(4)]
    assert first == ["flood0", "r2-0", "flood1", "r2-1"]  # r2 is not stuck behind the 50 flooded samples
    assert len(intake) == 48


def test_a_lane_and_the_whole_intake_are_bounded_in_bytes():
    woken = []
    intake = Intake(lane_bytes=100, total_bytes=250, on_first=lambda: woken.append(1))
    assert intake.put("scan", "a", 1, 60) is None and woken == [1]
    assert intake.put("scan", "a", 2, 40) is None and woken == [1]  # not empty before: no second wake-up
    assert intake.put("scan", "a", 3, 1) == "rate_limited"  # lane a is full
    assert intake.put("scan", "b", 4, 100) is None
    assert intake.put("scan", "c", 5, 60) == "queue_full"  # 260 > 250 together
    assert intake.held_bytes == 200 and intake.peak_bytes == 200
    assert [intake.get() for _ in range(4)] == [1, 4, 2, None]
    assert intake.held_bytes == 0 and intake.put("scan", "a", 6, 100) is None
    assert dict(intake.take_refused()) == {"rate_limited": 1, "queue_full": 1} and not intake.refused


def test_the_high_water_mark_is_the_most_held_since_it_was_last_taken():
    intake = Intake(lane_bytes=1000, total_bytes=1000)
    for k in range(3):
        intake.put("scan", "r1", k, 100)
    intake.get()
    assert intake.take_high_water() == 300
    assert intake.take_high_water() == 200  # what is still held
    intake.get(), intake.get()
    assert intake.take_high_water() == 200 and intake.take_high_water() == 0 and intake.peak_bytes == 300


def test_free_heap_memory_is_given_back_where_glibc_is():
    import platform

    from services.runtime import release_free_memory

    blocks = [bytearray(4096) for _ in range(20000)]  # 80 MB in small blocks, then freed: a worked-off backlog
    del blocks
    given_back = release_free_memory()
    assert isinstance(given_back, bool)
    if platform.system() == "Linux" and platform.libc_ver()[0] == "glibc":
        assert given_back
