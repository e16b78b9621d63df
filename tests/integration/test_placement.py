"""Fleet placement live, over a real router: MR.CLAM robots replayed with their start poses withheld.

The first robot announced (r3) anchors the central map's frame at the origin, and the MCL service stops
localizing it; the other is localized by the MCL service in the central map (landmark ids as signatures) and
joins it. One SE(2) transform (the anchor's true
start pose) must then carry both robots and the map onto the truth.
"""

from __future__ import annotations

import numpy as np
import pytest

from robots.loaders import data_root, load_dataset
from robots.models import transform_points
from schemas.keys import Keys
from schemas.messages import Estimate, ServiceStats
from services.mapfeed import assemble
from tests.helpers import Collector, wait_until

pytestmark = pytest.mark.integration

ROOT = data_root()
FOLDER = None if ROOT is None else ROOT / "utias_mrclam" / "MRCLAM_Dataset6"
DATA_S = 150.0
SPEEDUP = 6.0  # MR.CLAM odometry is about 67 Hz a robot: at 10x, MCL's global localization lagged on a loaded machine


@pytest.mark.skipif(FOLDER is None or not FOLDER.is_dir(),
                    reason="MR.CLAM Dataset 6 not found (set FLEETSLAM_DATA or add ../shared/data)")
def test_mrclam_robots_without_start_poses_are_anchored_placed_and_merged(processes, zsession, prefix):
    keys = Keys(prefix)
    estimates = Collector(zsession, keys.central_estimate)
    stats = Collector(zsession, keys.stats("mcl"))
    processes.start("central", "central", "--association", "known", "--particles", "30", "--estimate-rate-hz", "4")
    processes.start("mcl", "mcl", "--source", "central", "--map-period-s", "0.5")
    wait_until(lambda: stats.count() > 0, 60, what="the mcl service's stats")
    robots = []
    for n in (3, 2):  # r2 starts once r3 anchors the frame (its replay clock starts then: it joins a little later)
        robots.append(processes.start(f"r{n}", "robot", "--replay", f"mrclam:{FOLDER}:{n}", "--unknown-start",
                                      "--duration", str(DATA_S), "--speedup", str(SPEEDUP)))
        wait_until(lambda: [e for e in estimates.decoded(Estimate) if e.robots], 30, what="the anchor in the estimate")

    def both_placed() -> list[Estimate]:
        return [e for e in estimates.decoded(Estimate) if {r.robot_id for r in e.robots} == {"r3", "r2"}]

    wait_until(both_placed, DATA_S / SPEEDUP + 60, what="r2 placed by MCL into the central estimate")
    data = load_dataset(f"mrclam:{FOLDER}")
    alone = [r.robot_id for r in next(e for e in estimates.decoded(Estimate) if e.robots).robots]
    assert alone == ["r3"], f"r3 anchors the frame, not {alone}"
    released = wait_until(lambda: [m for m in stats.decoded(ServiceStats) if m.extra.get("robots_released", 0) >= 1],
                          30, what="the mcl service to stop localizing the anchor")
    assert released[-1].extra["robots_released"] == 1  # r3 only: r2 is placed by MCL itself
    frame = data.robots["r3"].info.start_pose  # the anchor's true start pose: the map's origin in the truth's frame
    first = both_placed()[0]

    for robot in robots:
        assert robot.wait(timeout=DATA_S / SPEEDUP + 60) == 0
    start = min(log.start_stamp for log in data.robots.values())
    latest = wait_until(lambda: (e := both_placed()[-1]).stamp > start + DATA_S - 5.0 and e, 30,
                        what="the estimate at the end of the replay")
    assert latest.stamp - first.stamp > 10.0, f"placed only {latest.stamp - first.stamp:.1f} s before the end"
    for robot in latest.robots:
        truth = data.robots[robot.robot_id].truth_at(np.array([robot.stamp]))[0]
        assert np.hypot(*(transform_points(frame, robot.pose[:2]) - truth[:2])) < 1.0, robot.robot_id
    whole = assemble([e for e in estimates.decoded(Estimate) if e.seq <= latest.seq])
    mapped = transform_points(frame, np.asarray(whole.landmarks, float).reshape(-1, 2))
    error = np.linalg.norm(mapped[:, None] - data.landmarks[None], axis=-1).min(1)
    assert len(mapped) >= 5 and np.median(error) < 0.5
