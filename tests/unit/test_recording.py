"""Fleet recordings (MCAP): topic -> schema mapping, the file format read back by mcap's own reader, refusal of
bad files with one line, a recording as a Dataset (the same estimates as the data it came from), the replay plan."""

import json

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from robots.dataset import Dataset
from robots.loaders import load_dataset
from robots.simulator import simulate
from schemas.codec import encode, schema_name
from schemas.contract import RunOptions
from schemas.keys import Keys
from schemas.mcap_file import RecordingWriter, part_path, read_recording
from schemas.messages import (Estimate, GroundTruth, MapEstimate, MclPose, Odometry, PoseEstimate, RobotInfo, Scan,
                              ServiceStats, WorldTruth)
from schemas.recording import (MESSAGE_ENCODING, SCHEMA_ENCODING, UNKNOWN_SCHEMA, RecordingError, schema_data,
                               topic_schema_name)
from services.cli import main as cli_main
from services.offline import run_estimator
from services.replay import plan_replay

PREFIX = "fleet"
STREAM_OF = {"OdomEvent": "odom", "ScanEvent": "scan", "TruthEvent": "truth"}


@pytest.mark.parametrize("topic, model", [
    ("fleet/robots/r1/info", RobotInfo), ("fleet/robots/r-2/odom", Odometry), ("fleet/robots/r1/scan", Scan),
    ("fleet/robots/r1/truth", GroundTruth), ("fleet/world/truth", WorldTruth), ("fleet/central/estimate", Estimate),
    ("fleet/dslam/map", MapEstimate), ("fleet/dslam/pose/r1", PoseEstimate), ("fleet/mcl/r1/pose", MclPose),
    ("fleet/central/stats", ServiceStats), ("fleet/eval/stats", ServiceStats),
    ("fleet/robots/r1/alive", None), ("fleet/robots/r1/other", None), ("fleet/assoc/nn", None),
    ("other/robots/r1/odom", None), ("fleet/robots/bad id/odom", None), ("fleet", None),
])
def test_each_key_gets_the_schema_of_the_message_it_carries(topic, model):
    expected = UNKNOWN_SCHEMA if model is None else schema_name(model)
    assert topic_schema_name(PREFIX, topic) == expected
    document = json.loads(schema_data(model))
    assert document["title"] == expected
    if model is not None:
        assert set(document["properties"]["body"]["properties"]) == set(model.model_fields)


def fleet(robots=("r1", "r2"), seed=5, duration=2.0) -> Dataset:
    """What robot processes publish: each robot simulated alone (``fleetslam robot --id rid --seed seed``)."""
    logs, world = {}, None
    for rid in robots:
        alone = simulate("arena", seed=seed, duration=duration, robot_ids=[rid])
        logs[rid] = alone.robots[rid]
        world = alone
    return Dataset(name="sim", robots=logs, landmarks=world.landmarks, landmark_ids=world.landmark_ids)


def published(dataset: Dataset) -> list[tuple[str, bytes]]:
    """(key, payload) in the order a fleet publishes them: RobotInfo and the world first, then the streams."""
    keys = Keys(PREFIX)
    out = [(keys.info(rid), encode(log.info)) for rid, log in dataset.robots.items()]
    out.append((keys.world_truth, encode(WorldTruth(world="arena", stamp=0.0, landmarks=dataset.landmarks,
                                                    landmark_ids=dataset.landmark_ids))))
    out += [(keys.robot(e.robot_id, STREAM_OF[type(e).__name__]), encode(e.to_message()))
            for e in dataset.events(with_truth=True)]
    return out


def write(path, samples, t0=1_700_000_000_000_000_000, step=1_000_000) -> list[int]:
    writer = RecordingWriter(path, PREFIX, metadata={"started": "test"})
    times = [t0 + k * step for k in range(len(samples))]
    for (key, payload), t in zip(samples, times):
        writer.write(key, payload, t, t - 500)
    assert not path.exists() and part_path(path).exists()  # never a complete-looking file before the end
    writer.close()
    assert path.exists() and not part_path(path).exists()
    return times


def test_a_recording_reads_back_with_mcap_reader_unchanged(tmp_path):
    path = tmp_path / "fleet.mcap"
    samples = published(fleet()) + [("fleet/central/estimate", b"\x93\x01\x02\x03"), ("fleet/foo", b"raw")]
    times = write(path, samples)
    with open(path, "rb") as stream:
        reader = make_reader(stream, validate_crcs=True)
        summary = reader.get_summary()
        got = [(channel.topic, message.data, message.log_time, message.publish_time, schema.name, schema.encoding,
                channel.message_encoding) for schema, channel, message in reader.iter_messages(log_time_order=True)]
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    assert summary.statistics.message_count == len(samples)
    assert [(k, bytes(d), lt, pt) for k, d, lt, pt, *_ in got] == [(k, p, t, t - 500) for (k, p), t in
                                                                    zip(samples, times)]
    assert {g[0]: g[4] for g in got} == {k: topic_schema_name(PREFIX, k) for k, _ in samples}
    assert {g[5] for g in got} == {SCHEMA_ENCODING} and {g[6] for g in got} == {MESSAGE_ENCODING}
    assert metadata["fleetslam"]["prefix"] == PREFIX
    assert metadata["fleetslam.summary"]["messages"] == str(len(samples))
    recording = read_recording(path)
    assert [(m.topic, m.data) for m in recording.messages] == samples


def foreign_mcap(path, metadata=None):
    with open(path, "wb") as stream:
        writer = Writer(stream)
        writer.start()
        if metadata is not None:
            writer.add_metadata("fleetslam", metadata)
        channel = writer.register_channel("fleet/robots/r1/odom", "msgpack", 0)
        writer.add_message(channel, log_time=1, data=b"x", publish_time=1)
        writer.finish()


@pytest.mark.parametrize("damage, reason", [
    ("missing", "no such recording"),
    ("empty", "not an MCAP file (empty)"),
    ("garbage", "not an MCAP file"),
    ("truncated", "truncated or unfinished"),
    ("cut_footer", "truncated or unfinished"),
    ("flipped_byte", "corrupt data"),
    ("foreign", "not a fleetslam recording"),
    ("future_version", "format version '99' is not supported"),
])
def test_a_bad_file_is_refused_with_one_line(tmp_path, damage, reason):
    good = tmp_path / "good.mcap"
    write(good, published(fleet(duration=1.0)))
    data = good.read_bytes()
    bad = tmp_path / "bad.mcap"
    if damage == "empty":
        bad.write_bytes(b"")
    elif damage == "garbage":
        bad.write_bytes(b"PK\x03\x04 not a recording" * 10)
    elif damage == "truncated":
        bad.write_bytes(data[: len(data) // 2])
    elif damage == "cut_footer":
        bad.write_bytes(data[:-4])
    elif damage == "flipped_byte":
        with open(good, "rb") as stream:
            chunk = make_reader(stream).get_summary().chunk_indexes[0]
        middle = chunk.chunk_start_offset + chunk.chunk_length // 2
        bad.write_bytes(data[:middle] + bytes([data[middle] ^ 0xFF]) + data[middle + 1:])
    elif damage == "foreign":
        foreign_mcap(bad)
    elif damage == "future_version":
        foreign_mcap(bad, {"format_version": "99", "prefix": PREFIX})
    with pytest.raises(RecordingError) as refused:
        read_recording(bad)
    message = str(refused.value)
    assert reason in message and "\n" not in message and str(bad) in message


def test_an_unfinished_recording_is_named_in_the_refusal(tmp_path):
    path = tmp_path / "crashed.mcap"
    writer = RecordingWriter(path, PREFIX)
    writer.write("fleet/robots/r1/odom", b"x", 1)
    with pytest.raises(RecordingError, match="crashed.mcap.part"):
        read_recording(path)
    writer.discard()
    assert not part_path(path).exists()


def same_log(a, b):
    assert encode(a.info) == encode(b.info)
    for name in ("odom_stamp", "odom_dt", "odom_control", "odom_cov", "scan_stamp", "scan_offsets", "det_range",
                 "det_bearing", "det_id", "scan_cov", "truth_stamp", "truth_pose", "robot_det_offsets",
                 "robot_det_range", "robot_det_bearing"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert a.robot_det_ids == b.robot_det_ids


def test_a_recording_is_the_data_set_it_recorded_and_gives_the_same_estimates(tmp_path):
    original = fleet(duration=3.0)
    path = tmp_path / "fleet.mcap"
    write(path, published(original) + [("fleet/central/estimate", b"not replayed")])
    loaded = load_dataset(f"mcap:{path}")
    assert sorted(loaded.robots) == sorted(original.robots)
    for rid in original.robots:
        same_log(loaded.robots[rid], original.robots[rid])
    np.testing.assert_array_equal(loaded.landmarks, original.landmarks)
    options = RunOptions(estimator="fastslam", association="known", particles=20, seed=3)
    again, first = run_estimator(loaded, options), run_estimator(original, options)
    assert first.events["scan"] > 0 and first.map_means.shape[0] > 0
    assert first.events == again.events
    np.testing.assert_array_equal(first.map_means, again.map_means)
    for rid, trajectory in first.trajectories.items():
        np.testing.assert_array_equal(trajectory.poses, again.trajectories[rid].poses)


def test_a_covariance_per_control_is_recorded_and_loaded_per_control(tmp_path):
    """A robot whose odometry covariance follows its controls keeps one per message;
    a robot with one covariance for every control keeps that one."""
    original = fleet(duration=2.0)
    log = original.robots["r1"]
    log.odom_cov = log.odom_cov[None] * (1.0 + np.arange(log.odom_stamp.size))[:, None, None]
    path = tmp_path / "fleet.mcap"
    write(path, published(original))
    loaded = load_dataset(f"mcap:{path}")
    assert loaded.robots["r1"].odom_cov.shape == (log.odom_stamp.size, 2, 2)
    assert loaded.robots["r2"].odom_cov.shape == (2, 2)
    for rid in original.robots:
        same_log(loaded.robots[rid], original.robots[rid])


def test_messages_the_services_would_refuse_are_left_out_and_counted(tmp_path):
    samples = published(fleet(robots=("r1",), duration=1.0))
    odom = [k for k, (key, _) in enumerate(samples) if key.endswith("/odom")]
    samples.insert(odom[3] + 1, samples[odom[3]])  # a duplicate
    samples.insert(odom[5], ("fleet/robots/r1/odom", b"\xc1 garbage"))
    path = tmp_path / "dirty.mcap"
    write(path, samples)
    loaded = load_dataset(f"mcap:{path}")
    assert loaded.meta["refused"] == {"duplicate": 1, "malformed": 1}
    assert loaded.robots["r1"].odom_stamp.size == len(odom)


def test_a_recording_without_robots_is_refused(tmp_path):
    path = tmp_path / "services.mcap"
    write(path, [("fleet/central/stats", b"x")])
    with pytest.raises(RecordingError, match="no robots"):
        load_dataset(f"mcap:{path}")
    with pytest.raises(RecordingError, match="no robots were recorded"):
        plan_replay(read_recording(path))


def test_the_replay_plan_takes_the_chosen_robots_from_the_start_time(tmp_path):
    path = tmp_path / "fleet.mcap"
    samples = published(fleet(robots=("r1", "r2", "r3"), duration=1.0)) + [("fleet/dslam/map", b"m")]
    step = 10_000_000  # 10 ms between samples
    write(path, samples, step=step)
    recording = read_recording(path)
    plan = plan_replay(recording, ["r1", "r3"], start_s=0.5)
    skipped = int(0.5e9 // step)
    expected = [(key, payload) for key, payload in samples[skipped:]
                if key.split("/")[2] in ("r1", "r3") and key.split("/")[1] == "robots"]
    assert [(Keys(PREFIX).robot(i.robot_id, i.stream), i.data) for i in plan.items] == expected
    assert plan.items[0].offset_s == 0.0 and np.all(np.diff([i.offset_s for i in plan.items]) > 0)
    assert sorted(plan.infos) == ["r1", "r3"] and plan.world is not None
    assert plan.last_index["r3"] == max(k for k, i in enumerate(plan.items) if i.robot_id == "r3")
    with pytest.raises(RecordingError, match="robot r9 not recorded"):
        plan_replay(recording, ["r1", "r9"])
    with pytest.raises(RecordingError, match="nothing recorded after 100 s"):
        plan_replay(recording, start_s=100.0)


def test_replay_of_a_bad_file_exits_with_one_line(tmp_path, capsys):
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"\x89MCAP0\r\n" + b"\x00" * 40)
    assert cli_main(["replay", str(bad)]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and "cannot replay" in err[0] and "truncated" in err[0] and "Traceback" not in err[0]

