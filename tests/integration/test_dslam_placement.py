"""Fleet placement live in ``fleetslam dslam``, over a real router: robots without start poses.

The first robot announced anchors the D-SLAM map's frame at the origin; the others are placed by the MCL
service, which localizes them against the D-SLAM map (its default source), or place themselves from two mapped
landmarks when the scans carry landmark ids. One SE(2) transform (the anchor's true start pose) must then carry
every robot's D-SLAM pose and the map onto the truth.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
import zenoh

from robots.loaders import data_root, load_dataset
from robots.models import transform_points
from robots.simulator import simulate
from schemas.keys import Keys
from schemas.codec import encode
from schemas.messages import MapEstimate, MclPose, PoseEstimate, ServiceStats
from services.mapfeed import assemble
from tests.helpers import Collector, wait_until

pytestmark = pytest.mark.integration

ROOT = data_root()
FOLDER = None if ROOT is None else ROOT / "utias_mrclam" / "MRCLAM_Dataset6"


def latest_poses(poses: Collector) -> dict[str, PoseEstimate]:
    out = {}
    for estimate in poses.decoded(PoseEstimate):
        out[estimate.robot_id] = estimate
    return out


def test_sim_robots_without_start_poses_or_ids_wait_for_the_anchor_and_for_mcl(processes, zsession, prefix):
    """No landmark ids, no start poses: r1 anchors the frame; r2's events wait in the roster until a localized
    MclPose places it (published here, at r2's true pose in r1's frame: the service's part, not MCL's), those
    older than that pose are dropped (counted), and both robots then follow the truth through one transform."""
    keys = Keys(prefix)
    stats = Collector(zsession, keys.stats("dslam"))
    maps = Collector(zsession, keys.dslam_map)
    poses = Collector(zsession, f"{prefix}/dslam/pose/*")
    processes.start("dslam", "dslam", "--association", "unknown", "--map-period-s", "0.3", "--stats-period-s", "0.3")
    wait_until(lambda: stats.count() > 0, 60, what="the dslam service")
    duration = 30.0
    args = ("--world", "arena", "--seed", "0", "--rate", "10", "--duration", str(duration), "--speedup", "3",
            "--unknown-start", "--no-publish-ids", "--start-delay", "1.0")
    robots = [processes.start("r1", "robot", "--id", "r1", *args)]
    wait_until(lambda: "r1" in latest_poses(poses), 30, what="r1 to anchor the frame")
    r2_started = time.time()
    robots.append(processes.start("r2", "robot", "--id", "r2", *args))

    def r2_held() -> bool:  # stats from after r2 started: r1's messages, held until it anchored, are not counted
        last = stats.decoded(ServiceStats)[-1]
        return last.stamp > r2_started and last.extra.get("waiting", 0) > 20

    wait_until(lambda: "robot r2 waits for a pose from MCL" in processes.log("dslam") and r2_held(), 30,
               what="r2's messages to wait for a pose")
    assert "r2" not in latest_poses(poses) and processes.log("dslam").count("anchors the world frame") == 1
    data = simulate("arena", robots=2, seed=0, duration=duration, rate=10.0)
    frame = data.robots["r1"].info.start_pose  # the anchor's true start pose: the map's origin in the truth's frame
    stamp = 5.0
    true_r2 = data.robots["r2"].truth_at(np.array([stamp]))[0]
    c, s = np.cos(frame[2]), np.sin(frame[2])
    offset = true_r2[:2] - frame[:2]
    in_frame = np.array([c * offset[0] + s * offset[1], -s * offset[0] + c * offset[1], true_r2[2] - frame[2]])
    publisher = zsession.declare_publisher(keys.mcl_pose("r2"), congestion_control=zenoh.CongestionControl.BLOCK)
    for seq, localized in enumerate((False, True)):
        publisher.put(encode(MclPose(robot_id="r2", seq=seq, stamp=stamp, best_pose=in_frame,
                                     best_cov=np.diag([1e-4, 1e-4, 1e-5]), localized=localized)))
    wait_until(lambda: "r2" in latest_poses(poses), 30, what="r2 placed by its MclPose")
    assert min(e.stamp for e in poses.decoded(PoseEstimate) if e.robot_id == "r2") >= stamp  # none from before it
    assert "robot r2 placed by MCL" in processes.log("dslam")
    for robot in robots:
        assert robot.wait(timeout=duration / 3 + 60) == 0
    wait_until(lambda: all(latest_poses(poses)[rid].stamp > duration - 1.0 for rid in ("r1", "r2")), 30,
               what="the D-SLAM poses at the end of the run")
    last = stats.decoded(ServiceStats)[-1]
    assert last.rejected.get("before_placement", 0) > 0  # r2's held events older than its MclPose
    assert last.extra.get("robots_placed", 0) == 2
    for rid, estimate in latest_poses(poses).items():
        truth = data.robots[rid].truth_at(np.array([estimate.stamp]))[0]
        assert np.hypot(*(transform_points(frame, estimate.pose[:2]) - truth[:2])) < 0.5, rid
    final = assemble(maps.decoded(MapEstimate))
    mapped = transform_points(frame, np.asarray(final.landmarks, float).reshape(-1, 2))
    assert len(mapped) >= 5
    assert np.median(np.linalg.norm(mapped[:, None] - data.landmarks[None], axis=-1).min(1)) < 0.3
    publisher.undeclare()


@pytest.mark.skipif(FOLDER is None or not FOLDER.is_dir(),
                    reason="MR.CLAM Dataset 6 not found (set FLEETSLAM_DATA or add ../shared/data)")
def test_mrclam_robots_without_start_poses_are_anchored_and_placed(processes, zsession, prefix):
    """Barcodes: r3 anchors the frame; r2 is placed (by MCL with signatures, or from two mapped landmarks by id)."""
    keys = Keys(prefix)
    stats = Collector(zsession, keys.stats("dslam"))
    poses = Collector(zsession, f"{prefix}/dslam/pose/*")
    processes.start("dslam", "dslam", "--association", "known", "--map-period-s", "0.5", "--stats-period-s", "0.5")
    processes.start("mcl", "mcl", "--map-period-s", "0.5")
    wait_until(lambda: stats.count() > 0, 60, what="the dslam service")
    data_s, speedup = 150.0, 6.0
    robots = []
    for n in (3, 2):
        robots.append(processes.start(f"r{n}", "robot", "--replay", f"mrclam:{FOLDER}:{n}", "--unknown-start",
                                      "--duration", str(data_s), "--speedup", str(speedup)))
        wait_until(lambda: latest_poses(poses), 30, what="the anchor's pose")
    assert list(latest_poses(poses)) == ["r3"], "r3 anchors the frame"
    wait_until(lambda: set(latest_poses(poses)) == {"r2", "r3"}, data_s / speedup + 60, what="r2 placed")
    for robot in robots:
        assert robot.wait(timeout=data_s / speedup + 60) == 0
    data = load_dataset(f"mrclam:{FOLDER}")
    start = min(log.start_stamp for log in data.robots.values())
    wait_until(lambda: all(p.stamp > start + data_s - 5.0 for p in latest_poses(poses).values()), 30,
               what="the D-SLAM poses at the end of the replay")
    frame = data.robots["r3"].info.start_pose
    for rid, estimate in latest_poses(poses).items():
        truth = data.robots[rid].truth_at(np.array([estimate.stamp]))[0]
        assert np.hypot(*(transform_points(frame, estimate.pose[:2]) - truth[:2])) < 1.0, rid
