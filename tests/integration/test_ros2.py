"""``fleetslam ros2`` against an independent rmw_zenoh implementation (zenoh-ros2-sdk, tests/integration/ros2_side.py):
two simulated robots publish ROS 2 odometry and landmarks on rmw_zenoh keys; the bridge turns them into fleetslam
robots that central FastSLAM and D-SLAM fuse; the ROS 2 side decodes the fused poses, ``/tf`` and the maps, and
lists the topics as ``ros2 topic list`` would. Broken ROS input is counted by reason and changes nothing."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from robots.simulator import simulate
from schemas.messages import ServiceStats
from services.ros2.core import fleet_entry_for
from services.ros2.fleet import FleetFile, save_fleet
from tests.helpers import REPO, Collector, client_session, wait_until

pytestmark = pytest.mark.integration

SEED, DURATION_S, ROBOTS = 0, 20.0, ["r1", "r2"]


def test_two_ros2_robots_are_fused_and_read_their_estimates_back_in_ros2(router, processes, tmp_path):
    dataset = simulate("arena", seed=SEED, duration=DURATION_S, robot_ids=ROBOTS)
    fleet = FleetFile(robots=[fleet_entry_for(dataset.robots[rid]) for rid in ROBOTS])
    fleet_file = tmp_path / "fleet.yaml"
    save_fleet(fleet, fleet_file)
    prefix = router.env["FLEETSLAM_PREFIX"]
    session = client_session(router.endpoint)
    try:
        forwarded = Collector(session, f"{prefix}/robots/*/*")
        stats = Collector(session, f"{prefix}/ros2/stats")
        maps = Collector(session, f"{prefix}/dslam/map")
        # 10 estimates a second: the 2.5 s of the run carry many fused poses, however soon central ends its work
        processes.start("central", "central", "--association", "shared", "--seed", str(SEED),
                        "--estimate-rate-hz", "10")
        processes.start("assoc", "assoc")
        processes.start("dslam", "dslam", "--association", "auto")
        processes.start("ros2", "ros2", "--fleet", str(fleet_file), "--map-period-s", "0.5")
        wait_until(lambda: stats.count() > 0, 60, what="the bridge's stats (it has subscribed)")
        out = tmp_path / "side.json"
        side = subprocess.run([sys.executable, str(REPO / "tests" / "integration" / "ros2_side.py"), "--port",
                               str(router.port), "--fleet", str(fleet_file), "--seed", str(SEED), "--duration",
                               str(DURATION_S), "--speedup", "8", "--abuse", "--out", str(out)],
                              capture_output=True, text=True, timeout=180)
        assert side.returncode == 0, side.stdout[-2000:] + side.stderr[-3000:]
        seen = json.loads(out.read_text())
        # every ROS message reached fleetslam's keys: each control, scan and true pose once (the first odometry
        # message of a robot only starts its clock)
        for rid in ROBOTS:
            log = dataset.robots[rid]
            for stream, expected in (("odom", log.odom_stamp.size), ("scan", log.scan_stamp.size),
                                     ("truth", log.truth_stamp.size)):
                wait_until(lambda: forwarded.count(lambda k: k == f"{prefix}/robots/{rid}/{stream}") >= expected,
                           20, what=f"{rid}'s {stream} on fleetslam's keys")
                assert forwarded.count(lambda k: k == f"{prefix}/robots/{rid}/{stream}") == expected
        # broken input: counted by reason, each once
        wait_until(lambda: stats.decoded(ServiceStats)[-1].rejected == seen["abused"], 10,
                   what=f"the bridge counting {seen['abused']}")
        # the independent side decoded fused poses near the truth, the maps and the transforms
        for rid in ROBOTS:
            x, y, _ = seen["last_pose"][rid]
            truth = dataset.robots[rid].truth_pose[-1]
            assert np.hypot(x - truth[0], y - truth[1]) < 0.3, (rid, seen["last_pose"][rid], truth)
        assert seen["received"][f"/{ROBOTS[0]}/fleetslam/odom"] > 5
        assert set(seen["tf_children"]) == {entry.odom_frame for entry in fleet.robots}
        assert {"central", "dslam"} <= set(seen["last_map"]), seen["last_map"].keys()
        for source in ("central", "dslam"):
            marked = np.array(seen["last_map"][source])
            distance = np.linalg.norm(marked[:, None, :] - dataset.landmarks[None, :, :], axis=-1).min(axis=1)
            assert len(marked) >= 5 and np.median(distance) < 0.3, (source, distance)
        topics = dict((name, types) for name, types in seen["topics"])
        for rid in ROBOTS:
            assert topics[f"/{rid}/fleetslam/odom"] == ["nav_msgs/msg/Odometry"]
        assert topics["/fleetslam/map"] == ["visualization_msgs/msg/MarkerArray"]
        assert topics["/tf"] == ["tf2_msgs/msg/TFMessage"]
        assert maps.count() > 0
    finally:
        session.close()
