"""The robot streams' fast decode path (schemas/codec.py) against the pydantic models, its reference: the same message
for every payload the reference takes, the same refusal (reason and detail) for every one it refuses."""

import math

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from schemas import codec
from schemas.codec import (
    ARRAY_EXT_CODE, DecodeError, _pack_array, _unpack_array, _unpack_array_reference, decode, encode,
)
from schemas.messages import Odometry, Scan

finite = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False)
robot_ids = st.from_regex(r"[A-Za-z0-9_-]{1,12}", fullmatch=True)


def outcome(payload, model, fast):
    """("ok", message) or ("refused", reason, detail)."""
    try:
        return ("ok", decode(payload, model, fast=fast))
    except DecodeError as error:
        return ("refused", error.reason, error.detail)


def same_message(a, b) -> None:
    """Two messages alike in everything pydantic keeps: field values and their types (arrays: dtype, shape, values,
    flags), field order, the fields set."""
    assert type(a) is type(b)
    assert list(a.__dict__) == list(b.__dict__)
    assert a.model_fields_set == b.model_fields_set
    assert a.__pydantic_extra__ == b.__pydantic_extra__ and a.__pydantic_private__ == b.__pydantic_private__
    for name, x in a.__dict__.items():
        y = b.__dict__[name]
        assert type(x) is type(y), name
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and x.shape == y.shape and x.flags.writeable == y.flags.writeable, name
            np.testing.assert_array_equal(x, y)
        else:
            assert x == y, name


def same_outcome(payload, model) -> tuple:
    fast, reference = outcome(payload, model, True), outcome(payload, model, False)
    assert fast[0] == reference[0], (fast, reference)
    if fast[0] == "ok":
        same_message(fast[1], reference[1])
    else:
        assert fast == reference
    return fast


def body_payload(schema: str, body: dict) -> bytes:
    return msgpack.packb({"schema": schema, "v": 1, "body": body},
                         default=lambda a: _pack_array(np.asarray(a)) if isinstance(a, np.ndarray) else a,
                         use_bin_type=True)


def odom_body(**changes):
    body = {"robot_id": "r1", "seq": 3, "stamp": 1.5, "dt": 0.1, "control": np.array([0.5, -0.1]),
            "control_cov": np.diag([0.01, 0.002])}
    body.update(changes)
    return body


def scan_body(**changes):
    body = {"robot_id": "r1", "seq": 3, "stamp": 1.5, "ranges": np.array([1.0, 2.0, 0.0]),
            "bearings": np.array([0.0, -0.1, math.pi]), "landmark_ids": None, "noise_cov": np.diag([0.01, 0.002]),
            "robot_ids": ["r2"], "robot_ranges": np.array([3.0]), "robot_bearings": np.array([-math.pi])}
    body.update(changes)
    return body


def test_the_fast_path_builds_what_fleetslams_encoder_sends():
    """Without it the comparisons below would hold trivially."""
    envelope = msgpack.unpackb(body_payload("Scan", scan_body()), ext_hook=_unpack_array, raw=False)
    assert codec._fast_scan(envelope["body"]) is not None
    envelope = msgpack.unpackb(body_payload("Odometry", odom_body()), ext_hook=_unpack_array, raw=False)
    assert codec._fast_odometry(envelope["body"]) is not None


@st.composite
def scans(draw):
    n = draw(st.integers(0, 40))  # past codec._SMALL too: checked with numpy there
    ranges = np.array(draw(st.lists(st.floats(0, 100, allow_nan=False), min_size=n, max_size=n)), float)
    bearings = np.array(draw(st.lists(st.floats(-math.pi, math.pi, allow_nan=False), min_size=n, max_size=n)), float)
    ids = draw(st.one_of(st.none(), st.just(np.array(draw(st.lists(st.integers(-1, 10**6), min_size=n, max_size=n)),
                                                     np.int64))))
    m = draw(st.integers(0, 3))
    return Scan(robot_id=draw(robot_ids), seq=draw(st.integers(0, 2**63)), stamp=draw(finite), ranges=ranges,
                bearings=bearings, landmark_ids=ids, noise_cov=np.diag([0.01, 0.002]),
                robot_ids=[f"r{i}" for i in range(m)], robot_ranges=np.ones(m), robot_bearings=np.zeros(m))


@settings(max_examples=150, deadline=None)
@given(scans())
def test_good_scans_decode_alike(scan):
    assert same_outcome(encode(scan), Scan)[0] == "ok"


@settings(max_examples=100, deadline=None)
@given(robot_ids, st.integers(0, 2**64 - 1), finite, st.floats(1e-6, 10), finite, finite)
def test_good_odometry_decodes_alike(rid, seq, stamp, dt, v, w):
    odom = Odometry(robot_id=rid, seq=seq, stamp=stamp, dt=dt, control=np.array([v, w]),
                    control_cov=np.array([[0.1, 0.01], [0.01, 0.2]]))
    assert same_outcome(encode(odom), Odometry)[0] == "ok"


NAN, INF = float("nan"), float("inf")
ODOMETRY_CHANGES = [
    {}, {"robot_id": "r 1"}, {"robot_id": "r1\n"}, {"robot_id": ""}, {"robot_id": "x" * 64}, {"robot_id": "x" * 65},
    {"robot_id": "rö"}, {"robot_id": 5}, {"seq": -1}, {"seq": 0}, {"seq": 2**64 - 1}, {"seq": True}, {"seq": 1.0},
    {"seq": "1"}, {"seq": None}, {"stamp": NAN}, {"stamp": INF}, {"stamp": -INF}, {"stamp": 3}, {"stamp": True},
    {"stamp": "1.5"}, {"stamp": -0.0}, {"dt": 0.0}, {"dt": -0.1}, {"dt": 10.0}, {"dt": 10.000001}, {"dt": NAN},
    {"dt": INF}, {"dt": 1}, {"dt": 5e-324}, {"control": np.array([NAN, 0.0])}, {"control": np.array([INF, 0.0])},
    {"control": np.array([1e308, 1e308])}, {"control": np.array([0.5, 0.1, 0.0])}, {"control": np.array([[0.5, 0.1]])},
    {"control": np.array([1, 2])}, {"control": np.array([1, 2], np.uint8)},
    {"control": np.array([0.5, 0.1], np.float32)},
    {"control": np.array([True, False])}, {"control": [0.5, 0.1]}, {"control": 0.5}, {"control": None},
    {"control_cov": np.eye(3)}, {"control_cov": np.eye(2)[0]}, {"control_cov": np.array([[1.0, 0.1], [0.2, 1.0]])},
    {"control_cov": np.array([[1.0, 0.1], [0.1 + 1e-12, 1.0]])}, {"control_cov": np.array([[1.0, NAN], [NAN, 1.0]])},
    {"control_cov": np.array([[1.0, 0.0], [0.0, INF]])}, {"control_cov": np.array([[1e308, 1e308], [1e308, 1e308]])},
    {"control_cov": np.eye(2, dtype=np.int64)}, {"control_cov": np.eye(2, dtype=np.float32)},
    {"control_cov": [[1.0, 0.0], [0.0, 1.0]]}, {"extra": 1},
]


@pytest.mark.parametrize("changes", ODOMETRY_CHANGES, ids=range(len(ODOMETRY_CHANGES)))
def test_odometry_payloads_get_the_references_answer(changes):
    same_outcome(body_payload("Odometry", odom_body(**changes)), Odometry)


@pytest.mark.parametrize("missing", list(odom_body()))
def test_odometry_without_a_field_gets_the_references_answer(missing):
    body = odom_body()
    del body[missing]
    assert same_outcome(body_payload("Odometry", body), Odometry)[0] == "refused"


SCAN_CHANGES = [
    {}, {"ranges": np.zeros(0), "bearings": np.zeros(0), "robot_ids": [], "robot_ranges": np.zeros(0),
         "robot_bearings": np.zeros(0)},
    {"ranges": np.array([-1.0, 2.0, 3.0])}, {"ranges": np.array([-0.0, 2.0, 3.0])},
    {"ranges": np.array([NAN, 2.0, 3.0])},
    {"ranges": np.array([INF, 2.0, 3.0])}, {"ranges": np.array([1e308, 1e308, 1.0])}, {"ranges": np.array([1.0, 2.0])},
    {"ranges": np.array([1, 2, 3])}, {"ranges": np.array([1.0, 2.0, 3.0], np.float32)}, {"ranges": [1.0, 2.0, 3.0]},
    {"ranges": np.ones((3, 1))}, {"ranges": np.ones(()), "bearings": np.zeros(())},
    {"bearings": np.array([0.0, 0.0, math.pi + 1e-9])}, {"bearings": np.array([0.0, 0.0, math.pi + 2e-9])},
    {"bearings": np.array([0.0, 0.0, -math.pi - 2e-9])}, {"bearings": np.array([0.0, 0.0, 7.0])},
    {"bearings": np.array([0.0, NAN, 0.0])}, {"bearings": np.array([0.0, 0.1])},
    {"landmark_ids": np.array([1, 2, -1])}, {"landmark_ids": np.array([1, 2])},
    {"landmark_ids": np.array([1.0, 2.0, 3.0])},
    {"landmark_ids": np.array([1, 2, 3], np.int32)}, {"landmark_ids": np.array([1, 2, 3], np.uint64)},
    {"landmark_ids": [1, 2, 3]}, {"landmark_ids": np.array([True, False, True])},
    {"noise_cov": np.eye(3)}, {"noise_cov": np.array([[1.0, 0.5], [0.4, 1.0]])}, {"noise_cov": np.eye(2) * NAN},
    {"robot_ids": []}, {"robot_ids": ["r 2"]}, {"robot_ids": ["r2", "r3"]}, {"robot_ids": "r2"}, {"robot_ids": [2]},
    {"robot_ids": ["r2\n"]}, {"robot_ids": None}, {"robot_ranges": np.array([-3.0])}, {"robot_ranges": np.zeros(0)},
    {"robot_ranges": np.array([NAN])}, {"robot_bearings": np.array([4.0])}, {"robot_bearings": np.array([1, 2])},
    {"robot_bearings": np.zeros(2)}, {"seq": -2}, {"stamp": NAN}, {"robot_id": "r1/odom"}, {"another": None},
]


@pytest.mark.parametrize("changes", SCAN_CHANGES, ids=range(len(SCAN_CHANGES)))
def test_scan_payloads_get_the_references_answer(changes):
    same_outcome(body_payload("Scan", scan_body(**changes)), Scan)


@pytest.mark.parametrize("missing", list(scan_body()))
def test_scan_without_a_field_gets_the_references_answer(missing):
    body = scan_body()
    del body[missing]
    same_outcome(body_payload("Scan", body), Scan)  # the optional ones are accepted, by the reference


def test_long_scans_are_checked_alike():
    n = 3 * codec._SMALL
    for changes in ({}, {"ranges": np.r_[np.ones(n - 1), -1.0]}, {"bearings": np.r_[np.zeros(n - 1), 3.2]},
                    {"bearings": np.r_[np.zeros(n - 1), NAN]}, {"ranges": np.r_[np.ones(n - 1), INF]}):
        body = scan_body(ranges=np.ones(n), bearings=np.zeros(n))
        body.update(changes)
        same_outcome(body_payload("Scan", body), Scan)


def test_the_bad_payloads_of_the_codec_tests_are_refused_alike():
    from tests.unit.test_codec import _scan_body

    for payload in [b"", b"\xc1garbage", msgpack.packb([1, 2, 3]),
                    msgpack.packb({"schema": "Scan", "v": 99, "body": {}}),
                    msgpack.packb({"schema": "Odometry", "v": 1, "body": {}}), _scan_body(ranges=np.array([-1.0, 2.0])),
                    _scan_body(bearings=np.array([0.0])), _scan_body(extra_field=1), _scan_body(ranges=[1.0, 2.0])]:
        assert same_outcome(payload, Scan)[0] == "refused"


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_random_bytes_are_refused_alike(data):
    same_outcome(data, Scan)
    same_outcome(data, Odometry)


# ---------------------------------------------------------------- array headers read by hand
def array_outcome(unpack, data: bytes):
    try:
        return ("ok", unpack(ARRAY_EXT_CODE, data))
    except DecodeError as error:
        return ("refused", error.reason, error.detail)
    except Exception as error:  # noqa: BLE001 - what escapes one must escape the other (decode makes it malformed)
        return ("raised", type(error).__name__, str(error))


def same_array(data: bytes) -> tuple:
    fast, reference = array_outcome(_unpack_array, data), array_outcome(_unpack_array_reference, data)
    assert fast[0] == reference[0], (fast, reference)
    if fast[0] == "ok":
        a, b = fast[1], reference[1]
        assert a.dtype == b.dtype and a.shape == b.shape and a.flags.writeable == b.flags.writeable
        assert a.flags.c_contiguous == b.flags.c_contiguous and a.flags.owndata == b.flags.owndata
        np.testing.assert_array_equal(a, b)
    else:
        assert fast == reference
    return fast


@pytest.mark.parametrize("dtype", sorted(codec.ALLOWED_DTYPES))
@pytest.mark.parametrize("shape", [(), (0,), (1,), (5,), (2, 2), (3, 0, 2), (200,), (70_000,), (2, 3, 4, 1)])
def test_arrays_of_every_dtype_and_shape_unpack_alike(dtype, shape):
    array = (np.arange(math.prod(shape)) % 2).astype(dtype).reshape(shape)
    assert same_array(_pack_array(array).data)[0] == "ok"


def header(dtype, shape) -> bytes:
    return msgpack.packb([dtype, shape])


@pytest.mark.parametrize("data", [
    b"", b"\x92", b"\x92\xa3<f8", b"\x92\xa3<f8\x91", b"\x92\xa3<f8\x91\xcd\x00", header("<f8", [3]) + bytes(16),
    header("<f8", [3]) + bytes(32), header("<f8", [2]) + bytes(16), header(">f8", [2]) + bytes(16),
    header("<f16", [1]) + bytes(16), header("<f8", [-1]) + bytes(8), header("<f8", [2**32, 2**32]),
    header("<f8", [2**62, 4]), header("<f8", [2**64 - 1]) + bytes(8), header("<f8", 2) + bytes(16),
    header("<f8", [True]) + bytes(8), header("<f8", [1.0]) + bytes(8), header("<f8", [[1]]) + bytes(8),
    msgpack.packb(["<f8", [1], 3]) + bytes(8), msgpack.packb("<f8") + bytes(8), msgpack.packb([b"<f8", [1]]) + bytes(8),
    b"\x92\xd9\x03<f8\x91\x01" + bytes(8), b"\x92\xa3<f8\xdc\x00\x01\x01" + bytes(8),
    b"\x92\xa3<f8\x91\xcc\x01" + bytes(8), b"\x92\xa3<f8\x91\xcf" + (1).to_bytes(8, "big") + bytes(8),
    b"\x92\xa3<f8\x91\xcf" + (1).to_bytes(7, "big"), b"\x92\xa3<f8\x92\x02\x02" + bytes(24),
    header("<f8", [8 * 2**20 + 1]), b"\x92\xa3\xff\xfe\xfd\x91\x01" + bytes(8),
])
def test_odd_and_bad_array_headers_unpack_alike(data):
    same_array(data)


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # the reference's np.prod overflows on huge shapes
@settings(max_examples=300, deadline=None)
@given(st.sampled_from(sorted(codec.ALLOWED_DTYPES) + ["<f2", "xyz"]),
       st.lists(st.integers(0, 2**64 - 1) | st.integers(-5, 5), max_size=4), st.integers(0, 80))
def test_any_header_unpacks_alike(dtype, shape, extra):
    same_array(header(dtype, shape) + bytes(extra))


def test_another_extension_is_refused_alike():
    payload = msgpack.packb({"schema": "Scan", "v": 1, "body": {"ranges": msgpack.ExtType(7, b"x")}})
    assert same_outcome(payload, Scan)[:2] == ("refused", "malformed")
