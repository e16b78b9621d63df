"""The service shell's loop takes the intake's items in batches, with one release of the reorder buffer per batch
(services/runtime.py ``_consume_batch``): the service sees the same events and hooks, in the same order, as when
every message was handled alone with a release after it, through announcements, a late join, a gap in a robot's
odometry (the service takes it out and places it again), a robot restarted from another session, bad payloads and
keys, and the service's own items."""

import asyncio

import numpy as np
import pytest

from schemas.codec import DecodeError, encode
from schemas.config import FleetSettings
from schemas.messages import Odometry, RobotInfo, Scan, SensorSpec
from services.roster import Roster
from services.runtime import ROBOT_TAGS, ServiceShell


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


class RecordingShell(ServiceShell):
    """A shell without a router that logs every event and hook it gets; an item tagged ``place`` admits its robot
    again (as central does when MCL places a robot)."""

    def __init__(self) -> None:
        super().__init__(FleetSettings(prefix="fleet", reorder_window_s=0.5, join_wait_s=1.0))
        self.roster = Roster(clock=Clock())
        self.reorder.clock = Clock()
        self.log = []

    def ask_info(self, robot_id):
        self.log.append(("ask_info", robot_id))

    def _router_link_lost(self) -> bool:
        return False

    async def robot_announced(self, info):
        self.log.append(("announced", info.robot_id))
        await self.admit(info.robot_id)

    async def robot_event(self, event):
        self.log.append(("event", event.robot_id, type(event).__name__, event.seq, event.stamp))

    def robot_new_run(self, robot_id):
        self.log.append(("new_run", robot_id))

    def robot_joined_late(self, robot_id):
        self.log.append(("late", robot_id))

    def robot_lost_odometry(self, robot_id):
        self.log.append(("lost", robot_id))
        self.roster.hold(robot_id)  # out until placed again

    def robot_left(self, robot_id):
        self.log.append(("left", robot_id))

    async def handle(self, tag, key, payload):
        if tag == "place":
            self.log.append(("place", key))
            await self.admit(key)
        elif tag == "boom":
            raise RuntimeError("a bug met by one item")


def info(rid):
    return RobotInfo(robot_id=rid, stamp=0.0, motion_model="unicycle",
                     sensor=SensorSpec(max_range=5.0, fov=3.0, noise_cov=np.eye(2) * 1e-3), start_pose=np.zeros(3),
                     odom_rate_hz=10.0, scan_rate_hz=10.0)


def odom(rid, seq, stamp):
    return Odometry(robot_id=rid, seq=seq, stamp=stamp, dt=0.1, control=np.array([0.1, 0.0]),
                    control_cov=np.eye(2) * 1e-3)


def scan(rid, seq, stamp):
    return Scan(robot_id=rid, seq=seq, stamp=stamp, ranges=np.array([1.0]), bearings=np.array([0.0]),
                noise_cov=np.eye(2) * 1e-3)


def script() -> list[list[tuple]]:
    """Steps of (tag, key, payload, source) in the order they reach the service: each step is queued whole, then
    handled."""
    steps = []
    sessions = {"r1": "zA", "r2": "zB", "r3": "zC", "r4": "zE"}
    steps.append([("alive", f"fleet/robots/{rid}/alive/{zid}", b"", None) for rid, zid in sessions.items()])
    steps.append([("info", f"fleet/robots/{rid}/info", encode(info(rid)), zid) for rid, zid in sessions.items()])
    for k in range(30):
        if k % 3 == 0:  # three rounds of messages queued at once
            items = []
            steps.append(items)
        stamp = round(0.1 * k, 3)
        for rid, zid in sessions.items():
            if rid == "r2" and k == 13:
                continue  # lost for good: a gap in r2's odometry and scans
            if rid == "r3" and k >= 20:
                continue  # r3 restarts below
            seq = k + 5 if rid == "r4" else k  # r4 joined late: its first messages were missed
            items.append(("odom", f"fleet/robots/{rid}/odom", encode(odom(rid, seq, stamp)), zid))
            items.append(("scan", f"fleet/robots/{rid}/scan", encode(scan(rid, seq, stamp)), zid))
        if k == 17:
            items.append(("place", "r2", b"", None))
        if k == 8:
            items += [("scan", "fleet/robots/r1/scan", b"\xc1garbage", "zA"),
                      ("odom", "fleet/robots/bad id/odom", b"", "zA"),
                      ("boom", "x", b"", None), ("odom", "fleet/robots/r1/odom", encode(odom("r1", 3, 0.3)), "zA")]
        if k == 20:  # r3's process restarts: another session, seq 0 again, from the fleet's clock
            items += [("gone", "fleet/robots/r3/alive/zC", b"", None), ("alive", "fleet/robots/r3/alive/zD", b"", None)]
        if k == 23:  # its RobotInfo, asked for at its new run
            items.append(("info", "fleet/robots/r3/info", encode(info("r3")), "zD"))
        if k >= 21:
            j = k - 21
            items.append(("odom", "fleet/robots/r3/odom", encode(odom("r3", j, stamp)), "zD"))
            items.append(("scan", "fleet/robots/r3/scan", encode(scan("r3", j, stamp)), "zD"))
    return steps


def fill(shell: ServiceShell, items) -> None:
    for tag, key, payload, source in items:
        shell.enqueue(tag, key, payload, source)


async def one_by_one(shell: ServiceShell) -> None:
    """The loop as it was: one item at a time, the reorder buffer released after each stream message."""
    while (item := shell.intake.get()) is not None:
        tag, key, payload, _arrived, source = item
        shell.messages_in[tag] += 1
        try:
            if tag in ROBOT_TAGS:
                await shell._robot_item(tag, key, payload, source)
            else:
                await shell.handle(tag, key, payload)
        except DecodeError as error:
            shell.reject_decode(error)
        except Exception:  # noqa: BLE001
            shell.reject("handler_error")


async def in_batches(shell: ServiceShell, size: int) -> None:
    while batch := shell.intake.get_many(size):
        await shell._consume_batch(batch)


def run(drive) -> RecordingShell:
    shell = RecordingShell()

    async def steps():
        for items in script():
            fill(shell, items)
            await drive(shell)
        await shell.release_events(flush=True)

    asyncio.run(steps())
    return shell


@pytest.mark.parametrize("size", [1, 3, 7, 64, 1000])
def test_batches_give_the_service_what_one_message_at_a_time_gave(size):
    reference = run(one_by_one)
    batched = run(lambda shell: in_batches(shell, size))
    events = [entry for entry in reference.log if entry[0] == "event"]
    kinds = {entry[0] for entry in reference.log}
    assert {"announced", "late", "lost", "place", "left", "new_run"} <= kinds and len(events) > 200  # all exercised
    assert kinds == {entry[0] for entry in reference.log}
    assert batched.log == reference.log
    assert batched.rejected == reference.rejected and batched.messages_in == reference.messages_in
    assert reference.rejected["malformed"] == 1 and reference.rejected["bad_key"] == 1
    assert reference.rejected["handler_error"] == 1 and reference.rejected["out_of_order"] == 1
    assert reference.log.count(("announced", "r3")) == 2
    assert len(batched._latencies_ms) == sum(map(len, script())) and not batched._in_hand and not batched._in_batch


def test_a_batch_holds_its_events_until_its_end_and_counts_its_items_as_queued():
    """In a batch the stream messages' events wait in the reorder buffer until the batch's end (or until the
    service acts on something else); the robots of the items not handled yet count as queued meanwhile."""
    shell = RecordingShell()
    fill(shell, script()[0] + script()[1])  # tokens and RobotInfo
    asyncio.run(in_batches(shell, 64))
    seen = []
    original = shell.reorder.release

    def spy(live, flush=False, announced=(), queued=()):
        seen.append(set(queued))
        return original(live, flush, announced, queued)

    shell.reorder.release = spy
    fill(shell, [("odom", "fleet/robots/r1/odom", encode(odom("r1", 0, 0.0)), "zA"),
                 ("info", "fleet/robots/r1/info", encode(info("r1")), "zA"),
                 ("odom", "fleet/robots/r2/odom", encode(odom("r2", 0, 0.0)), "zB")])
    asyncio.run(in_batches(shell, 64))
    # the lanes in turn: r1's odometry, r2's, r1's RobotInfo. r2's seq 0 may start a new run: what r1 pushed is
    # released first, with r1's RobotInfo still in hand; then before the RobotInfo, what r2 pushed
    assert seen == [{"r1"}, set()]


@pytest.mark.parametrize("limit", [1, 2, 5, 100])
def test_the_intake_gives_a_batch_in_the_order_of_one_item_at_a_time(limit):
    from services.intake import Intake

    def filled() -> Intake:
        intake = Intake(lane_bytes=10_000, total_bytes=100_000)
        for k in range(12):
            intake.put("scan", ("r1", "a"), f"r1-{k}", 10)
            if k % 3 == 0:
                intake.put("odom", ("r2", "b"), f"r2-{k}", 20)
            if k == 5:
                intake.put("state", "state", "q", 0)
        return intake

    one, many = filled(), filled()
    singles = [one.get() for _ in range(len(one))]
    batches = []
    while batch := many.get_many(limit):
        assert len(batch) <= limit
        batches += batch
    assert [item for _lane, item in batches] == singles
    assert [lane for lane, _ in batches][:4] == [("r1", "a"), ("r2", "b"), "state", ("r1", "a")]  # in turn
    assert len(many) == 0 and many.held_bytes == 0 and not many.lanes() and many.get() is None
