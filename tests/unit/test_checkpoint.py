"""Crash-safe checkpoints (services/checkpoint.py) and the cores they hold: files written atomically, a truncated,
corrupt or foreign file refused with its reason and the previous one used, and each stateful core (FastSLAM, D-SLAM,
MCL) carrying on after a pickle round trip exactly as it would have without one (D-SLAM to its solver's tolerance:
its sparse factor is made afresh). A checkpoint never falls between a release of events and their handling."""

import asyncio
import pickle

import numpy as np
import pytest

from central.fastslam.config import FastSlamConfig
from central.fastslam.core import FastSlam
from robots.simulator import simulate
from schemas.config import FleetSettings
from schemas.contract import OdomEvent
from services.checkpoint import CheckpointError, CheckpointStore, decode_checkpoint, encode_checkpoint
from services.dslam.config import DslamConfig
from services.dslam.core import DSlam
from services.mcl.config import MclConfig
from services.mcl.fleet import MclFleet
from services.roster import Roster
from services.runtime import ServiceShell


def test_the_newest_checkpoint_comes_back_and_only_the_last_few_are_kept(tmp_path):
    store = CheckpointStore(tmp_path, "central", keep=3)
    for k in range(5):
        store.save(encode_checkpoint("central", {"k": k}, {"robots": 2}))
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["central-00000003.ckpt", "central-00000004.ckpt", "central-00000005.ckpt"]
    found = CheckpointStore(tmp_path, "central").load()
    assert found.state == {"k": 4} and found.header["summary"] == {"robots": 2} and found.age_s >= 0
    assert CheckpointStore(tmp_path, "central").save(encode_checkpoint("central", {})).name == "central-00000006.ckpt"


@pytest.mark.parametrize("damage, reason", [
    (lambda data: data[: len(data) - 10], "truncated"),
    (lambda data: data[:-5] + bytes(5), "SHA-256"),
    (lambda data: data[:30], "truncated in its header"),
    (lambda data: b"garbage" + data, "no magic"),
    (lambda data: b"", "no magic"),
])
def test_a_damaged_newest_checkpoint_is_refused_with_its_reason_and_the_previous_used(tmp_path, damage, reason):
    store = CheckpointStore(tmp_path, "dslam")
    store.save(encode_checkpoint("dslam", {"k": 1}))
    newest = store.save(encode_checkpoint("dslam", {"k": 2}))
    newest.write_bytes(damage(newest.read_bytes()))
    found = store.load()
    assert found.state == {"k": 1}
    assert len(store.refused) == 1 and store.refused[0][0] == newest.name and reason in store.refused[0][1]


def test_another_services_checkpoint_is_refused():
    with pytest.raises(CheckpointError, match="'mcl' service"):
        decode_checkpoint(encode_checkpoint("mcl", {}), "central")


def test_an_empty_or_missing_folder_has_no_checkpoint_and_no_temporary_file_is_left(tmp_path):
    assert CheckpointStore(tmp_path / "absent", "mcl").load() is None
    store = CheckpointStore(tmp_path / "new", "mcl")
    store.save(encode_checkpoint("mcl", [1, 2]))
    assert [p.name for p in (tmp_path / "new").iterdir()] == ["mcl-00000001.ckpt"]


# ------------------------------------------------------------------ the cores carry on exactly
@pytest.fixture(scope="module")
def two_robots():
    dataset = simulate("arena", seed=3, duration=24, rate=10, robot_ids=["r1", "r2"])
    events = sorted((e for r in dataset.robots.values() for e in r.events(with_truth=False)),
                    key=lambda e: (e.stamp, e.robot_id))
    return dataset, events


def _feed(core, events):
    for event in events:
        (core.on_odometry if isinstance(event, OdomEvent) else core.on_scan)(event)


def _run_with_restore(make, add, events, split):
    """(core run straight through, core pickled at ``split`` and carried on from the copy)."""
    straight, interrupted = make(), make()
    for core in (straight, interrupted):
        add(core)
    _feed(straight, events)
    _feed(interrupted, events[:split])
    restored = pickle.loads(pickle.dumps(interrupted))
    _feed(restored, events[split:])
    return straight, restored


@pytest.mark.parametrize("association, compiled", [("known", True), ("known", False), ("shared", True), ("nn", False)])
def test_fastslam_carries_on_bitwise_after_a_checkpoint(two_robots, association, compiled):
    dataset, events = two_robots
    make = lambda: FastSlam(FastSlamConfig(particles=30, association=association, compiled=compiled, seed=5))  # noqa: E731
    add = lambda core: [core.add_robot(r.info) for r in dataset.robots.values()]  # noqa: E731
    straight, restored = _run_with_restore(make, add, events, len(events) // 3)
    assert restored.landmark_map().means.shape[0] > 3
    for rid, (pose, cov) in straight.poses().items():
        other_pose, other_cov = restored.poses()[rid]
        np.testing.assert_array_equal(pose, other_pose)
        np.testing.assert_array_equal(cov, other_cov)
    np.testing.assert_array_equal(straight.landmark_map().means, restored.landmark_map().means)
    np.testing.assert_array_equal(straight.weights(), restored.weights())


def test_a_fastslam_checkpoint_from_before_the_weight_cache_carries_on_bitwise(two_robots):
    """A checkpoint pickled before the filter cached its weights and its known-landmark arrays (``logw`` in the
    state, ``known_slots`` a plain dict), before the turn gains (none in the state: every gain 1, as with
    them off) and before the robots kept their detections of robots is restored as one of today's and carries on
    exactly."""
    dataset, events = two_robots
    make = lambda: FastSlam(FastSlamConfig(particles=30, association="shared", seed=5,  # noqa: E731
                                           turn_gain_std=0.0, turn_gain_walk=0.0))
    straight, interrupted = make(), make()
    for core in (straight, interrupted):
        [core.add_robot(r.info) for r in dataset.robots.values()]
    split = len(events) // 3
    _feed(straight, events)
    _feed(interrupted, events[:split])
    old = dict(interrupted.__dict__)
    old["logw"] = old.pop("_logw")
    old.pop("_weights")
    old["known_slots"] = dict(old["known_slots"])
    old.pop("turn_gain")
    state = pickle.loads(pickle.dumps(old))
    for robot in state["robots"].values():
        del robot.__dict__["robot_checks"]
    restored = FastSlam.__new__(FastSlam)
    restored.__setstate__(state)
    assert restored.known_slots.arrays()[0].size > 3
    assert all(robot.robot_checks == [] for robot in restored.robots.values())
    _feed(restored, events[split:])
    np.testing.assert_array_equal(straight.weights(), restored.weights())
    np.testing.assert_array_equal(straight.landmark_map().means, restored.landmark_map().means)


def test_dslam_carries_on_after_a_checkpoint_to_its_solver_tolerance(two_robots):
    dataset, events = two_robots
    add = lambda core: [core.add_robot(r.info) for r in dataset.robots.values()]  # noqa: E731
    straight, restored = _run_with_restore(DSlam, add, events, len(events) // 2)
    assert len(restored.ids) > 3 and restored.ids == straight.ids
    np.testing.assert_allclose(restored.landmark_map().means, straight.landmark_map().means, atol=1e-6)
    for rid, (pose, _) in straight.poses().items():
        np.testing.assert_allclose(restored.poses()[rid][0], pose, atol=1e-6)


def test_a_dslam_checkpoint_from_before_the_turn_slip_carries_on(two_robots):
    """A checkpoint whose robots have no summed turn slip (written before it existed) reads the field's default,
    none, and the filter carries on."""
    dataset, events = two_robots
    half = len(events) // 2
    old = DSlam(DslamConfig(association="jcbb"))
    for log in dataset.robots.values():
        old.add_robot(log.info.model_copy(update={"turn_slip_var": 0.02}))
    _feed(old, events[:half])
    for robot in old.robots.values():
        del robot.__dict__["turn_slip"]
    restored = pickle.loads(pickle.dumps(old))
    assert {robot.turn_slip for robot in restored.robots.values()} == {0.0}
    _feed(restored, events[half:])
    assert len(restored.ids) > 3 and all(robot.pose is not None for robot in restored.robots.values())


def test_mcl_carries_on_bitwise_after_a_checkpoint(two_robots):
    dataset, events = two_robots
    infos = [r.info.model_copy(update={"start_pose": None, "start_pose_cov": None}) for r in dataset.robots.values()]
    make = lambda: MclFleet(MclConfig(particles=300, seed=2), dataset.landmarks, landmark_ids=dataset.landmark_ids)  # noqa: E731
    add = lambda fleet: [fleet.add_robot(info) for info in infos]  # noqa: E731
    straight, restored = _run_with_restore(make, add, events, len(events) // 2)
    for rid in ("r1", "r2"):
        np.testing.assert_array_equal(straight.robots[rid].mcl.particles, restored.robots[rid].mcl.particles)
        np.testing.assert_array_equal(straight.poses()[rid][0], restored.poses()[rid][0])



class AwaitingShell(ServiceShell):
    """A service shell without a router whose ``robot_event`` awaits, as D-SLAM's does (its scans go to a worker
    thread): the loop may run a checkpoint, or a stop may come, between the events of one release. It holds 20
    odometry events of r1, released together."""

    name = "awaiting"

    def __init__(self, state_dir):
        super().__init__(FleetSettings(prefix="fleet", reorder_window_s=0.5))
        self.roster = Roster()
        self.checkpoints = CheckpointStore(state_dir, self.name)
        self.handled: list[int] = []
        self.handled_at_snapshot: list[int] | None = None
        for seq in range(20):
            self.reorder.push(OdomEvent("r1", seq, 0.1 * seq, 0.1, np.zeros(2), np.eye(2)))

    async def robot_event(self, event):
        self.handled.append(event.seq)  # handled, then the await: as D-SLAM's shielded scan
        await asyncio.sleep(0)

    def checkpoint_state(self):
        return {"handled": list(self.handled)}

    async def snapshot(self):
        self.handled_at_snapshot = list(self.handled)
        return await super().snapshot()


def test_a_checkpoint_taken_while_a_release_is_handled_holds_every_event_handled_or_held(tmp_path):
    """Events the reorder buffer gave out are no longer held by it: a checkpoint taken between two of them would
    hold neither the rest nor their effect, and a service resumed from it would never see them (their seqs count as
    received). The checkpoint waits for the release to end."""

    async def scenario():
        shell = AwaitingShell(tmp_path)
        release = asyncio.create_task(shell.release_events(flush=True))
        for _ in range(3):
            await asyncio.sleep(0)
        assert 0 < len(shell.handled) < 20  # the release is under way
        await shell._write_checkpoint()
        await release
        return shell

    shell = asyncio.run(scenario())
    state = CheckpointStore(tmp_path, "awaiting").load().state
    held = sorted(entry[-1].event.seq for entry in state["reorder"]._heap)
    assert state["service"]["handled"] == shell.handled_at_snapshot
    assert sorted(shell.handled_at_snapshot + held) == list(range(20)), (shell.handled_at_snapshot, held)


def test_a_stop_between_the_events_of_a_release_holds_the_rest_again_for_the_last_flush(tmp_path):
    """A stop cancels the loop between two events of one release: the events after the one under way are held
    again, and the stop's last flush hands every one over, once and in order."""

    async def scenario():
        shell = AwaitingShell(tmp_path)
        release = asyncio.create_task(shell.release_events(flush=True))
        for _ in range(3):
            await asyncio.sleep(0)
        release.cancel()
        with pytest.raises(asyncio.CancelledError):
            await release
        assert len(shell.handled) < 20
        await shell.release_events(flush=True)
        return shell

    assert asyncio.run(scenario()).handled == list(range(20))
