"""The foundation over a real router: robots, liveliness, clean stops, the monitor's rejections."""

import signal
import threading

import numpy as np
import pytest
import zenoh

from robots.simulator import simulate
from schemas.codec import decode
from schemas.keys import Keys
from schemas.messages import GroundTruth, Odometry, RobotInfo, Scan, ServiceStats, WorldTruth
from tests.helpers import Collector, wait_until

pytestmark = pytest.mark.integration

STREAMS = {"odom": Odometry, "scan": Scan, "truth": GroundTruth}


def robot_args(rid, duration=2.0, seed=0, world="arena", speedup=4.0):
    return ("robot", "--id", rid, "--world", world, "--seed", str(seed), "--rate", "10", "--duration", str(duration),
            "--speedup", str(speedup), "--start-delay", "0.3")


def test_three_robots_every_message_in_order_decodable_no_gap(router, processes, zsession, prefix):
    keys = Keys(prefix)
    collector = Collector(zsession, f"{prefix}/robots/**")
    world = Collector(zsession, keys.world_truth)
    robots = [processes.start(rid, *robot_args(rid)) for rid in ("r1", "r2", "r3")]
    for process in robots:
        assert process.wait(timeout=30) == 0
    expected = {rid: simulate("arena", seed=0, duration=2.0, robot_ids=[rid]).robots[rid] for rid in ("r1", "r2", "r3")}

    def complete():
        return all(collector.count(lambda k, r=rid, s=s: k == f"{prefix}/robots/{r}/{s}") >= n
                   for rid, log in expected.items()
                   for s, n in (("odom", len(log.odom_stamp)), ("scan", len(log.scan_stamp)), ("truth", len(log.truth_stamp))))

    wait_until(complete, 10, what="every robot message")
    for rid, log in expected.items():
        for stream, model in STREAMS.items():
            messages = collector.decoded(model, lambda k, r=rid, s=stream: k == f"{prefix}/robots/{r}/{s}")
            assert [m.seq for m in messages] == list(range(len(messages)))
            stamps = [m.stamp for m in messages]
            assert stamps == sorted(stamps)
            assert all(m.robot_id == rid for m in messages)
        scans = collector.decoded(Scan, lambda k, r=rid: k == f"{prefix}/robots/{r}/scan")
        assert len(scans) == len(log.scan_stamp)
        np.testing.assert_allclose(np.concatenate([s.ranges for s in scans]), log.det_range)
        info = collector.decoded(RobotInfo, lambda k, r=rid: k == f"{prefix}/robots/{r}/info")
        assert info and info[0].start_pose is not None
    truth = world.decoded(WorldTruth)
    assert truth and truth[0].landmarks.shape == (15, 2)


def test_late_joiner_gets_robot_info_and_world_truth_by_query(router, processes, zsession, prefix):
    keys = Keys(prefix)
    alive = threading.Event()
    token_watch = zsession.liveliness().declare_subscriber(keys.alive("r7"), lambda s: alive.set(), history=True)
    processes.start("r7", *robot_args("r7", duration=30.0, speedup=1.0))
    wait_until(alive.is_set, 15, what="r7's liveliness token")
    info = [decode(r.ok.payload.to_bytes(), RobotInfo) for r in zsession.get(keys.info("r7"), timeout=5.0) if r.ok]
    world = [decode(r.ok.payload.to_bytes(), WorldTruth) for r in zsession.get(keys.world_truth, timeout=5.0) if r.ok]
    token_watch.undeclare()
    assert info[0].robot_id == "r7" and info[0].source == "sim:arena"
    assert world[0].landmarks.shape == (15, 2)


def test_sigkilled_robot_leaves_liveliness(router, processes, zsession, prefix):
    keys = Keys(prefix)
    events: list[zenoh.SampleKind] = []
    watcher = zsession.liveliness().declare_subscriber(keys.alive_any, lambda s: events.append(s.kind), history=True)
    robot = processes.start("r1", *robot_args("r1", duration=60.0, speedup=1.0))
    wait_until(lambda: zenoh.SampleKind.PUT in events, 15, what="the robot's token")
    robot.send_signal(signal.SIGKILL)
    wait_until(lambda: zenoh.SampleKind.DELETE in events, 5, what="the token to vanish after SIGKILL")
    watcher.undeclare()


def test_every_process_exits_within_two_seconds_of_sigterm(router, processes, zsession, prefix):
    keys = Keys(prefix)
    stats = Collector(zsession, keys.stats("monitor"))
    alive = threading.Event()
    watcher = zsession.liveliness().declare_subscriber(keys.alive("r1"), lambda s: alive.set(), history=True)
    robot = processes.start("r1", *robot_args("r1", duration=120.0, speedup=1.0))
    monitor = processes.start("monitor", "monitor", "--plain", "--stats-period-s", "0.2")
    wait_until(alive.is_set, 15, what="the robot")
    wait_until(lambda: stats.count() > 0, 15, what="the monitor's stats")
    watcher.undeclare()
    for name, process in (("robot", robot), ("monitor", monitor), ("router", processes.started[0][1])):
        took = processes.stop(process, signal.SIGTERM, timeout=10)
        assert process.returncode == 0, f"{name} exited with {process.returncode}: {processes.log(name)[-500:]}"
        assert took < 2.0, f"{name} took {took:.2f} s to exit after SIGTERM"


def test_monitor_counts_malformed_payloads_and_keeps_running(router, processes, zsession, prefix):
    keys = Keys(prefix)
    stats = Collector(zsession, keys.stats("monitor"))
    monitor = processes.start("monitor", "monitor", "--plain", "--stats-period-s", "0.2")
    wait_until(lambda: stats.count() > 0, 15, what="the monitor's stats")

    def latest() -> ServiceStats:
        return stats.decoded(ServiceStats)[-1]

    zsession.put(keys.scan("r1"), b"\x00not msgpack at all")
    zsession.put(keys.odom("r1"), b"\x93\x01\x02")
    zsession.put(keys.scan("r1"), b'{"robot_id": "r1", "seq": 0, "stamp": 0.0, "ranges": [1.0]}')
    wait_until(lambda: sum(latest().rejected.values()) >= 3, 10, what="three rejections")
    assert latest().rejected.get("malformed", 0) >= 3
    processes.start("r1", *robot_args("r1", duration=1.0))
    wait_until(lambda: latest().messages_in.get("sample", 0) > 20, 20, what="the monitor to keep counting")
    assert monitor.poll() is None


def test_connection_and_listening_failures_are_one_line_with_the_cause(router, processes):
    """A robot with no router names the router it tried and how to start one; a second router on a busy port says
    the port is taken. Neither prints a source path or a traceback."""
    processes.env.update(FLEETSLAM_ZENOH_CONNECT="tcp/127.0.0.1:1", FLEETSLAM_CONNECT_TIMEOUT_S="1")
    lonely = processes.start("lonely", "robot", "--world", "arena")
    busy = processes.start("busy", "router", "--listen", router.endpoint)
    for name, child in (("lonely", lonely), ("busy", busy)):
        wait_until(lambda: child.poll() is not None, timeout=60, what=f"{name} to give up")
        assert child.returncode != 0
    robot_log, router_log = processes.log("lonely"), processes.log("busy")
    assert "connecting to the zenoh router at tcp/127.0.0.1:1" in robot_log
    assert "could not reach the zenoh router at tcp/127.0.0.1:1 within 1 s" in robot_log and "fleetslam router" in robot_log
    assert f"cannot listen on {router.endpoint}" in router_log and "Address already in use" in router_log
    for text in (robot_log, router_log):
        assert ".rs:" not in text and "Traceback" not in text
