"""Five MR.CLAM replay robots are a real five-robot fleet: every message through the router, in order."""

import pytest

from schemas.contract import OdomEvent, ScanEvent, TruthEvent
from robots.loaders import data_root, load_dataset
from schemas.messages import GroundTruth, Odometry, Scan
from tests.helpers import Collector, wait_until

pytestmark = pytest.mark.integration

ROOT = data_root()
FOLDER = None if ROOT is None else ROOT / "utias_mrclam" / "MRCLAM_Dataset6"
DATA_S = 20.0
STREAMS = {"odom": Odometry, "scan": Scan, "truth": GroundTruth}
EVENTS = {"odom": OdomEvent, "scan": ScanEvent, "truth": TruthEvent}


@pytest.mark.skipif(FOLDER is None or not FOLDER.is_dir(),
                    reason="MR.CLAM Dataset 6 not found (set FLEETSLAM_DATA or add ../shared/data)")
def test_five_mrclam_replay_robots_lose_nothing(router, processes, zsession, prefix):
    collector = Collector(zsession, f"{prefix}/robots/**")
    expected: dict[str, dict[str, int]] = {}
    for n in range(1, 6):
        log = next(iter(load_dataset(f"mrclam:{FOLDER}:{n}").robots.values()))
        events = list(log.events(until=log.start_stamp + DATA_S))
        expected[log.robot_id] = {stream: sum(isinstance(e, kind) for e in events) for stream, kind in EVENTS.items()}
    robots = [processes.start(f"r{n}", "robot", "--replay", f"mrclam:{FOLDER}:{n}", "--duration", str(DATA_S),
                              "--speedup", "10", "--start-delay", "0.5") for n in range(1, 6)]
    for robot in robots:
        assert robot.wait(timeout=60) == 0

    def stream_count(rid: str, stream: str) -> int:
        return collector.count(lambda k: k == f"{prefix}/robots/{rid}/{stream}")

    wait_until(lambda: all(stream_count(rid, s) >= n for rid, counts in expected.items() for s, n in counts.items()),
               15, what="every replayed message")
    assert sorted(expected) == ["r1", "r2", "r3", "r4", "r5"]
    for rid, counts in expected.items():
        assert counts["odom"] > 100 and counts["scan"] > 5 and counts["truth"] > 100
        for stream, model in STREAMS.items():
            messages = collector.decoded(model, lambda k, r=rid, s=stream: k == f"{prefix}/robots/{r}/{s}")
            assert len(messages) == counts[stream], (rid, stream)
            assert [m.seq for m in messages] == list(range(counts[stream])), (rid, stream)
            stamps = [m.stamp for m in messages]
            assert stamps == sorted(stamps) and all(m.robot_id == rid for m in messages)
