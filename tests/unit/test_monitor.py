"""The monitor's bookkeeping (services/monitor.py) without a router, fed synthetic samples: a robot's new run
(token gone, seq 0 again) is counted as a restart, while seq going back with the token still there is refused."""

import numpy as np

from schemas.codec import encode
from schemas.config import MonitorSettings
from schemas.messages import GroundTruth, Odometry
from services.monitor import Monitor

PREFIX = "fleet"


def odom(seq: int) -> bytes:
    return encode(Odometry(robot_id="r1", seq=seq, stamp=0.1 * seq, dt=0.1, control=np.array([0.1, 0.0]),
                           control_cov=np.eye(2) * 1e-3))


def truth(seq: int) -> bytes:
    return encode(GroundTruth(robot_id="r1", seq=seq, stamp=0.1 * seq, pose=np.array([0.01 * seq, 0.0, 0.0])))


async def run(monitor: Monitor, last_seq: int, skipped: int | None = None) -> None:
    """Odometry and truth of r1 from seq 0 to ``last_seq`` (odometry seq ``skipped`` lost on the way)."""
    for seq in range(last_seq + 1):
        if seq != skipped:
            await monitor.handle("sample", f"{PREFIX}/robots/r1/odom", odom(seq))
        await monitor.handle("sample", f"{PREFIX}/robots/r1/truth", truth(seq))


def monitor() -> Monitor:
    return Monitor(MonitorSettings(prefix=PREFIX, plain=True))


async def test_a_robot_that_left_and_starts_again_at_seq_0_is_a_new_run_not_out_of_order():
    watcher = monitor()
    await watcher.handle("alive", "r1", b"1")
    await run(watcher, 50, skipped=20)
    await watcher.handle("alive", "r1", b"0")
    await watcher.handle("alive", "r1", b"1")
    await run(watcher, 30)
    assert dict(watcher.rejected) == {}
    summary = watcher.summary()
    r1 = summary["robots"]["r1"]
    assert r1["restarts"] == 1 and summary["robot_restarts"] == 1
    assert (r1["odom"], r1["truth"]) == (50 + 31, 51 + 31)  # the counts add up over the runs
    assert r1["missing"] == 1  # the first run's gap is kept after the tracker forgot that run


async def test_seq_going_back_while_the_token_stays_is_out_of_order():
    watcher = monitor()
    await watcher.handle("alive", "r1", b"1")
    await run(watcher, 50)
    await run(watcher, 30)
    assert dict(watcher.rejected) == {"out_of_order": 2 * 31}
    r1 = watcher.summary()["robots"]["r1"]
    assert r1["restarts"] == 0 and (r1["odom"], r1["truth"]) == (51, 51)
