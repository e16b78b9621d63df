"""Codec and schemas: round trips (property tests) and one clear rejection type for bad payloads."""

import math

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from schemas.codec import DecodeError, decode, encode
from schemas.messages import (
    Estimate, GroundTruth, MapEstimate, MclPose, Odometry, RobotEstimate, RobotInfo, Scan, SensorSpec, ServiceStats,
    WorldTruth,
)

finite = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False)
robot_ids = st.from_regex(r"[A-Za-z0-9_-]{1,12}", fullmatch=True)


@st.composite
def scans(draw):
    n = draw(st.integers(0, 40))
    ranges = np.array(draw(st.lists(st.floats(0, 100, allow_nan=False), min_size=n, max_size=n)))
    bearings = np.array(draw(st.lists(st.floats(-math.pi, math.pi, allow_nan=False), min_size=n, max_size=n)))
    ids = draw(st.one_of(st.none(), st.just(np.array(draw(st.lists(st.integers(-1, 10**6), min_size=n, max_size=n)), np.int64))))
    m = draw(st.integers(0, 3))
    return Scan(robot_id=draw(robot_ids), seq=draw(st.integers(0, 2**40)), stamp=draw(finite),
                ranges=ranges.reshape(n), bearings=bearings.reshape(n), landmark_ids=ids, noise_cov=np.diag([0.01, 0.002]),
                robot_ids=[f"r{i}" for i in range(m)], robot_ranges=np.ones(m), robot_bearings=np.zeros(m))


@settings(max_examples=80, deadline=None)
@given(scans())
def test_scan_round_trip(scan):
    back = decode(encode(scan), Scan)
    assert back.robot_id == scan.robot_id and back.seq == scan.seq and back.stamp == scan.stamp
    np.testing.assert_array_equal(back.ranges, scan.ranges)
    np.testing.assert_array_equal(back.bearings, scan.bearings)
    if scan.landmark_ids is None:
        assert back.landmark_ids is None
    else:
        np.testing.assert_array_equal(back.landmark_ids, scan.landmark_ids)
    assert back.robot_ids == scan.robot_ids


@settings(max_examples=60, deadline=None)
@given(robot_ids, st.integers(0, 2**31), finite, st.floats(1e-4, 10), finite, finite)
def test_odometry_round_trip(rid, seq, stamp, dt, v, w):
    odom = Odometry(robot_id=rid, seq=seq, stamp=stamp, dt=dt, control=np.array([v, w]), control_cov=np.eye(2) * 0.1)
    back = decode(encode(odom), Odometry)
    assert back.model_dump(exclude={"control", "control_cov"}) == odom.model_dump(exclude={"control", "control_cov"})
    np.testing.assert_array_equal(back.control, odom.control)


def test_arrays_travel_as_packed_little_endian_binary():
    payload = encode(GroundTruth(robot_id="r1", seq=0, stamp=0.0, pose=np.array([1.0, 2.0, 0.5])))
    envelope = msgpack.unpackb(payload, raw=False)
    pose = envelope["body"]["pose"]
    assert isinstance(pose, msgpack.ExtType) and pose.data.endswith(np.array([1.0, 2.0, 0.5], "<f8").tobytes())


def test_every_message_round_trips():
    sensor = SensorSpec(max_range=5.0, fov=math.pi, noise_cov=np.eye(2) * 0.01)
    messages = [
        RobotInfo(robot_id="r1", stamp=0.0, motion_model="ackermann", wheelbase=2.83, encoder_offset=0.76, sensor=sensor,
                  start_pose=np.zeros(3), odom_rate_hz=40.0, scan_rate_hz=5.0),
        WorldTruth(world="arena", stamp=0.0, landmarks=np.ones((3, 2)), landmark_ids=np.arange(3)),
        Estimate(seq=1, stamp=2.0, robots=[RobotEstimate(robot_id="r1", stamp=2.0, pose=np.zeros(3), cov=np.eye(3))],
                 landmarks=np.ones((2, 2)), landmark_covs=np.tile(np.eye(2), (2, 1, 1)), particles=10, effective_particles=5.5),
        MapEstimate(seq=0, stamp=0.0, landmarks=np.zeros((0, 2)), landmark_ids=np.zeros(0, np.int64)),
        ServiceStats(service="x", instance="x-1", stamp=1.0, uptime_s=1.0, rejected={"malformed": 2}),
        MclPose(robot_id="r4", seq=0, stamp=0.0, best_pose=np.zeros(3), best_cov=np.eye(3), localized=True),
    ]
    for message in messages:
        assert encode(decode(encode(message), type(message))) == encode(message)


def _scan_body(**changes):
    body = {"robot_id": "r1", "seq": 0, "stamp": 0.0, "ranges": np.array([1.0, 2.0]), "bearings": np.array([0.0, 0.1]),
            "noise_cov": np.eye(2)}
    body.update(changes)
    return msgpack.packb({"schema": "Scan", "v": 1, "body": body}, default=lambda a: encode_array(a), use_bin_type=True)


def encode_array(array):
    from schemas.codec import _pack_array
    return _pack_array(np.asarray(array))


@pytest.mark.parametrize(
    "payload, reason",
    [
        (b"", "malformed"),
        (b"\xc1garbage", "malformed"),
        (msgpack.packb([1, 2, 3]), "malformed"),
        (msgpack.packb({"schema": "Scan", "v": 99, "body": {}}), "unknown_version"),
        (msgpack.packb({"schema": "Odometry", "v": 1, "body": {}}), "wrong_schema"),
        (_scan_body(ranges=np.array([-1.0, 2.0])), "invalid"),
        (_scan_body(ranges=np.array([np.nan, 2.0])), "invalid"),
        (_scan_body(bearings=np.array([0.0, np.inf])), "invalid"),
        (_scan_body(bearings=np.array([0.0])), "invalid"),
        (_scan_body(noise_cov=np.eye(3)), "invalid"),
        (_scan_body(seq=-1), "invalid"),
        (_scan_body(seq="zero"), "invalid"),
        (_scan_body(robot_id="r 1/x"), "invalid"),
        (_scan_body(extra_field=1), "invalid"),
        (_scan_body(ranges=[1.0, 2.0]), "invalid"),
        (_scan_body(bearings=np.array([0.0, 7.0])), "invalid"),
    ],
)
def test_bad_payloads_raise_one_exception_type_with_a_reason(payload, reason):
    with pytest.raises(DecodeError) as info:
        decode(payload, Scan)
    assert info.value.reason == reason


def test_array_with_lying_shape_is_malformed():
    from schemas.codec import ARRAY_EXT_CODE
    header = msgpack.packb(["<f8", [5]])
    fake = msgpack.ExtType(ARRAY_EXT_CODE, header + np.zeros(2).tobytes())
    payload = msgpack.packb({"schema": "GroundTruth", "v": 1, "body": {"robot_id": "r1", "seq": 0, "stamp": 0.0, "pose": fake}})
    with pytest.raises(DecodeError) as info:
        decode(payload, GroundTruth)
    assert info.value.reason == "malformed"


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=200))
def test_random_bytes_never_escape_as_another_exception(data):
    try:
        decode(data, Scan)
    except DecodeError as error:
        assert error.reason in {"malformed", "wrong_schema", "unknown_version", "invalid"}
