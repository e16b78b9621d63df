"""Record a live fleet with ``fleetslam record``, run the file offline, replay it: a real router, real processes.

- Two ``fleetslam robot`` processes are recorded; the file, read with mcap's own reader, holds every message
  each robot published, byte for byte and in order, and ``fleetslam run --dataset mcap:FILE`` gives the same
  estimates and scores as the same run on the simulated data the robots published.
- ``fleetslam replay`` publishes the recorded robots again: a subscriber receives every recorded robot message,
  byte for byte and in order, and each robot's liveliness token comes and goes; services' outputs are not replayed.
"""

import json
import signal
from collections import defaultdict

import pytest
import zenoh
from mcap.reader import make_reader

from robots.dataset import Dataset
from robots.simulator import simulate
from schemas.codec import encode
from schemas.config import RunSettings
from schemas.keys import Keys
from schemas.mcap_file import RecordingWriter, part_path
from schemas.messages import ServiceStats, WorldTruth
from services import offline
from tests.helpers import Collector, wait_until

pytestmark = pytest.mark.integration

SEED, DURATION, ROBOTS = 11, 4.0, ("r1", "r2")
STREAM_OF = {"OdomEvent": "odom", "ScanEvent": "scan", "TruthEvent": "truth"}


def simulated_fleet() -> Dataset:
    """Exactly what ``fleetslam robot --id RID --seed SEED --duration DURATION`` publishes, one robot each."""
    logs, alone = {}, None
    for rid in ROBOTS:
        alone = simulate("arena", seed=SEED, duration=DURATION, robot_ids=[rid])
        logs[rid] = alone.robots[rid]
    return Dataset(name="sim:arena", robots=logs, landmarks=alone.landmarks, landmark_ids=alone.landmark_ids)


def expected_streams(dataset: Dataset, prefix: str) -> dict[str, list[bytes]]:
    """Every robot stream message as published: key -> payloads in order."""
    keys, streams = Keys(prefix), defaultdict(list)
    for event in dataset.events(with_truth=True):
        streams[keys.robot(event.robot_id, STREAM_OF[type(event).__name__])].append(encode(event.to_message()))
    return streams


def recorded(path, prefix) -> dict[str, list[bytes]]:
    with open(path, "rb") as stream:
        reader = make_reader(stream, validate_crcs=True)
        streams = defaultdict(list)
        for _, channel, message in reader.iter_messages(log_time_order=True):
            streams[channel.topic].append(bytes(message.data))
    return streams


def test_a_recorded_fleet_runs_offline_like_the_original(router, processes, zsession, prefix, tmp_path,
                                                         monkeypatch):
    path = tmp_path / "fleet.mcap"
    stats = Collector(zsession, Keys(prefix).stats("record"))
    recorder = processes.start("record", "record", "--out", str(path), "--progress-period-s", "1")
    wait_until(lambda: stats.count(), 30, what="the recorder's stats (it is subscribed)")
    robots = [processes.start(rid, "robot", "--id", rid, "--seed", str(SEED), "--duration", str(DURATION),
                              "--speedup", "8", "--start-delay", "0.3") for rid in ROBOTS]
    for robot in robots:
        assert robot.wait(timeout=60) == 0
    original = simulated_fleet()
    expected = expected_streams(original, prefix)
    total = sum(len(v) for v in expected.values())

    def recorded_so_far() -> int:
        last = stats.decoded(ServiceStats)[-1].messages_in
        return last.get("odom", 0) + last.get("scan", 0) + last.get("truth", 0)

    wait_until(lambda: recorded_so_far() >= total, 20, what="the recorder to receive every robot message")
    assert processes.stop(recorder, signal.SIGINT, timeout=20) < 20 and recorder.returncode == 0
    assert path.is_file() and not part_path(path).exists()
    assert "recorded" in processes.log("record") and str(path) in processes.log("record")

    streams = recorded(path, prefix)
    for key, payloads in expected.items():
        assert streams[key] == payloads, key  # every message, byte for byte, in order
    keys = Keys(prefix)
    assert all(streams[keys.info(rid)] for rid in ROBOTS) and streams[keys.world_truth]

    report = tmp_path / "report"
    run = processes.start("run", "run", "--dataset", f"mcap:{path}", "--estimator", "fastslam", "--particles", "30",
                          "--seed", "4", "--no-progress", "--out", str(report), "--json", str(tmp_path / "out.json"))
    assert run.wait(timeout=120) == 0, processes.log("run")
    from_file = json.loads((tmp_path / "out.json").read_text())
    settings = RunSettings(dataset="sim:arena", estimator="fastslam", particles=30, seed=4, progress=False,
                           out=str(tmp_path / "original"))
    monkeypatch.setattr(offline, "load", lambda _settings: original)  # the same run on the data the robots published
    original_run = offline.run(settings)
    for figure in ("events", "ate_rmse_m", "ate_aligned_rmse_m", "map_rmse_m", "landmarks", "nees"):
        assert from_file[figure] == original_run[figure], figure
    assert from_file["events"]["scan"] == len(expected[keys.scan("r1")]) + len(expected[keys.scan("r2")])
    assert all(from_file["ate_rmse_m"][rid] is not None for rid in ROBOTS)


def test_replay_publishes_the_recorded_robots_message_for_message(router, processes, zsession, prefix, tmp_path):
    recorded_prefix = "elsewhere"  # a recording from another fleet comes back under this fleet's prefix
    source = simulated_fleet()
    keys, theirs = Keys(prefix), Keys(recorded_prefix)
    path = tmp_path / "fleet.mcap"
    writer = RecordingWriter(path, recorded_prefix)
    t = 1_700_000_000_000_000_000
    for rid, log in source.robots.items():
        writer.write(theirs.info(rid), encode(log.info), t)
    writer.write(theirs.world_truth, encode(WorldTruth(world="arena", stamp=0.0, landmarks=source.landmarks,
                                                       landmark_ids=source.landmark_ids)), t)
    for event in source.events(with_truth=True):
        t += 2_000_000
        writer.write(theirs.robot(event.robot_id, STREAM_OF[type(event).__name__]), encode(event.to_message()), t)
        writer.write(theirs.central_estimate, b"a service output", t)
    writer.close()

    everything = Collector(zsession, keys.everything)
    tokens: list[tuple[str, str]] = []
    liveliness = zsession.liveliness().declare_subscriber(
        keys.alive_any, lambda s: tokens.append((str(s.key_expr), "put" if s.kind == zenoh.SampleKind.PUT else "del")))
    try:
        replay = processes.start("replay", "replay", str(path), "--speedup", "4", "--start-delay", "0.3",
                                 "--robots", ",".join(ROBOTS))
        assert replay.wait(timeout=60) == 0, processes.log("replay")
        expected = expected_streams(source, prefix)
        total = sum(len(v) for v in expected.values())
        robot_keys = set(expected)
        wait_until(lambda: everything.count(lambda k: k in robot_keys) >= total, 15, what="every replayed message")
        got = defaultdict(list)
        for key, payload in everything.snapshot():
            got[key].append(payload)
        for key, payloads in expected.items():
            assert got[key] == payloads, key
        assert keys.central_estimate not in got
        for rid in ROBOTS:
            assert got[keys.info(rid)] and got[keys.info(rid)][0] == encode(source.robots[rid].info)
            wait_until(lambda r=rid: (keys.alive(r), "del") in tokens, 10, what=f"{rid}'s token to go")
            assert (keys.alive(rid), "put") in tokens
        assert "replay done" in processes.log("replay")
    finally:
        liveliness.undeclare()
        everything.undeclare()
