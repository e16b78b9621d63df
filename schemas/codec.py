"""The one msgpack codec for every message that crosses Zenoh.

A payload is a msgpack map ``{"schema": NAME, "v": VERSION, "body": {...}}``.
Arrays travel as msgpack extension type 1 holding a tiny header (dtype string,
shape) and the packed little-endian bytes, never as lists of Python floats.

Every failure to decode (garbage bytes, wrong schema, unknown version, wrong
types, wrong shapes, NaN where not allowed, negative ranges...) raises
:class:`DecodeError`, whose ``reason`` is a short stable label that services
use to count rejections.

The robots' streams (:class:`~schemas.messages.Odometry`, :class:`~schemas.messages.Scan`: thousands a second in a
fleet's central service) have a fast path: plain checks of the usual payload (every field there, float64 arrays,
exactly symmetric covariances) build the message without pydantic's per-field machinery. It only ever accepts: any
payload it is not sure of, and every one that is refused, goes through the pydantic models (the reference, also
``decode(..., fast=False)``), so the reasons and details of refusals are theirs; tests hold both paths to the same
messages on good and bad payloads. Array headers of the usual form are read without a msgpack unpacker, likewise
falling back to it for anything else.
"""

from __future__ import annotations

import math
import re
from typing import Any, Callable, TypeVar

import msgpack
import numpy as np
import pydantic

from schemas.messages import ROBOT_ID_PATTERN, Odometry, Scan

ARRAY_EXT_CODE = 1
ALLOWED_DTYPES = frozenset({"<f8", "<f4", "<i8", "<i4", "<i2", "|i1", "|u1", "<u2", "<u4", "<u8", "|b1"})
MAX_ARRAY_BYTES = 64 * 1024 * 1024

M = TypeVar("M", bound=pydantic.BaseModel)


class DecodeError(ValueError):
    """A payload that cannot become the expected message; ``reason`` labels why."""

    def __init__(self, reason: str, detail: str = ""):
        self.reason = reason
        self.detail = detail
        super().__init__(f"{reason}: {detail}" if detail else reason)


def _pack_array(array: np.ndarray) -> msgpack.ExtType:
    little = np.ascontiguousarray(array).astype(array.dtype.newbyteorder("<"), copy=False)
    header = msgpack.packb([little.dtype.str, list(little.shape)])
    return msgpack.ExtType(ARRAY_EXT_CODE, header + little.tobytes())


def _unpack_array_reference(code: int, data: bytes) -> np.ndarray:
    """An array extension's array, its header read by a msgpack unpacker (any valid form; every refusal)."""
    if code != ARRAY_EXT_CODE:
        raise DecodeError("malformed", f"unknown msgpack extension {code}")
    unpacker = msgpack.Unpacker(raw=False, max_buffer_size=len(data))
    unpacker.feed(data)
    try:
        dtype_str, shape = unpacker.unpack()
    except Exception as exc:  # noqa: BLE001 - any failure here is a malformed header
        raise DecodeError("malformed", f"bad array header: {exc}") from None
    if dtype_str not in ALLOWED_DTYPES:
        raise DecodeError("malformed", f"array dtype {dtype_str!r} not allowed")
    if not isinstance(shape, list) or not all(isinstance(n, int) and n >= 0 for n in shape):
        raise DecodeError("malformed", f"bad array shape {shape!r}")
    offset = unpacker.tell()
    dtype = np.dtype(dtype_str)
    count = int(np.prod(shape, dtype=np.int64)) if shape else 1
    if count * dtype.itemsize != len(data) - offset or count * dtype.itemsize > MAX_ARRAY_BYTES:
        raise DecodeError("malformed", f"array byte length does not match shape {shape} and dtype {dtype_str}")
    return np.frombuffer(data, dtype=dtype, count=count, offset=offset).reshape(shape).astype(dtype.newbyteorder("="))


# header bytes of an allowed dtype string (msgpack fixstr) → (wire dtype, native dtype)
_FIXSTR_DTYPES = {bytes([0xA0 | len(name)]) + name.encode(): (np.dtype(name), np.dtype(name).newbyteorder("="))
                  for name in ALLOWED_DTYPES}
_UINT_WIDTH = {0xCC: 1, 0xCD: 2, 0xCE: 4, 0xCF: 8}


def _unpack_array(code: int, data: bytes) -> np.ndarray:
    """:func:`_unpack_array_reference`, with the usual header (a 2-array of a fixstr dtype and a fixarray of unsigned
    ints, as :func:`_pack_array` writes it) read by hand; anything else, and every size that does not add up, is
    left to the reference (so that its refusals are the reference's)."""
    if code == ARRAY_EXT_CODE and data[:1] == b"\x92":
        try:
            wire, native = _FIXSTR_DTYPES[data[1:5]]  # the allowed dtype strings have 3 characters: 0xa3 + 3 bytes
            head = data[5]
            offset = 6
            if 0x90 <= head <= 0x9F:
                shape = []
                for _ in range(head & 0x0F):
                    first = data[offset]
                    if first < 0x80:
                        shape.append(first)
                        offset += 1
                    else:
                        width = _UINT_WIDTH[first]
                        if offset + 1 + width > len(data):
                            raise IndexError
                        shape.append(int.from_bytes(data[offset + 1:offset + 1 + width], "big"))
                        offset += 1 + width
                nbytes = math.prod(shape) * wire.itemsize
                if nbytes == len(data) - offset and nbytes <= MAX_ARRAY_BYTES:
                    flat = np.frombuffer(data, wire, nbytes // wire.itemsize, offset)
                    return (flat if len(shape) == 1 else flat.reshape(shape)).astype(native)
        except (KeyError, IndexError):
            pass
    return _unpack_array_reference(code, data)


def _default(obj):
    if isinstance(obj, np.ndarray):
        return _pack_array(obj)
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"cannot encode {type(obj).__name__}")


_SCHEMA_NAMES: dict[type, str] = {}


def schema_name(model: type[pydantic.BaseModel]) -> str:
    name = _SCHEMA_NAMES.get(model)
    if name is None:  # (a pydantic model class answers a missing attribute slowly)
        name = _SCHEMA_NAMES[model] = getattr(model, "SCHEMA_NAME", model.__name__)
    return name


def encode(message: pydantic.BaseModel) -> bytes:
    """Encode a message model into a msgpack payload."""
    body = message.model_dump(mode="python")
    envelope = {"schema": schema_name(type(message)), "v": getattr(message, "SCHEMA_VERSION", 1), "body": body}
    return msgpack.packb(envelope, default=_default, use_bin_type=True)


def decode(payload: bytes | bytearray | memoryview, expected: type[M], fast: bool = True) -> M:
    """Decode a payload into ``expected``; raise :class:`DecodeError` on any problem. ``fast``: the robot streams'
    fast path (see the module docstring) where there is one; off, the pydantic models alone (the reference)."""
    try:
        envelope = msgpack.unpackb(bytes(payload), ext_hook=_unpack_array if fast else _unpack_array_reference,
                                   raw=False, strict_map_key=True)
    except DecodeError:
        raise
    except Exception as exc:  # noqa: BLE001 - msgpack raises many types on garbage
        raise DecodeError("malformed", f"not a msgpack payload ({type(exc).__name__})") from None
    if not isinstance(envelope, dict) or not {"schema", "v", "body"} <= envelope.keys():
        raise DecodeError("malformed", "payload is not a fleetslam envelope")
    if envelope["schema"] != schema_name(expected):
        raise DecodeError("wrong_schema", f"expected {schema_name(expected)}, got {envelope['schema']!r}")
    if envelope["v"] != getattr(expected, "SCHEMA_VERSION", 1):
        raise DecodeError("unknown_version", f"{schema_name(expected)} version {envelope['v']!r} is not supported")
    if not isinstance(envelope["body"], dict):
        raise DecodeError("malformed", "envelope body is not a map")
    if fast and (build := _FAST.get(expected)) is not None and (message := build(envelope["body"])) is not None:
        return message
    try:
        return expected.model_validate(envelope["body"], context={"wire": True})
    except pydantic.ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first.get("loc", ()))
        raise DecodeError("invalid", f"{where}: {first.get('msg', 'invalid')}") from None


# ---------------------------------------------------------------- the robot streams' fast path
# Each builder returns the message the pydantic model would validate from the body, or None when it is not sure the
# model would accept it (then the model decides, and says why it refuses). It accepts only float64 arrays (int64 for
# landmark ids), Python floats and ints of exactly those types, every field present, and covariances exactly
# symmetric: what fleetslam's own encoder sends.

_robot_id = re.compile(ROBOT_ID_PATTERN.removeprefix("^").removesuffix("$")).fullmatch  # no "$" before a newline
_SMALL = 32  # arrays up to this long are checked as Python floats (numpy's per-call cost is larger)
_BEARING_LIMIT = math.pi + 1e-9
_F8 = np.dtype(np.float64)
_I8 = np.dtype(np.int64)


def _floats(value: Any, length: int | None) -> list[float] | np.ndarray | None:
    """The values of a float64 array of shape ``(length,)`` (None: any length) that are all finite (a list when
    short, else the array), or None."""
    if type(value) is not np.ndarray or value.dtype != _F8 or value.ndim != 1 or (
            length is not None and value.shape[0] != length):
        return None
    if value.shape[0] <= _SMALL:
        values = value.tolist()
        return values if math.isfinite(sum(values)) else None  # a finite sum has no NaN nor infinity in it
    return value if bool(np.isfinite(value).all()) else None


def _nonnegative(values: list[float] | np.ndarray) -> bool:
    return (min(values) >= 0.0 if values else True) if isinstance(values, list) else not bool((values < 0).any())


def _bearings_in_range(values: list[float] | np.ndarray) -> bool:
    if isinstance(values, list):
        return not values or max(map(abs, values)) <= _BEARING_LIMIT
    return not bool((np.abs(values) > _BEARING_LIMIT).any())


def _covariance2(value: Any) -> bool:
    """A finite float64 (2, 2) array, exactly symmetric."""
    if type(value) is not np.ndarray or value.dtype != _F8 or value.shape != (2, 2):
        return False
    a, b, c, d = value.ravel().tolist()
    return math.isfinite(a + b + c + d) and b == c


def _construct(model: type[M], fields: tuple[str, ...], body: dict, **replaced: Any) -> M:
    """The model holding the values of ``body`` (every one of its ``fields``, already checked; ``replaced`` instead
    of some), as ``model_validate`` would build it: the fields in the model's order, all of them set."""
    values = {name: body[name] for name in fields}
    values.update(replaced)
    message = model.__new__(model)
    object.__setattr__(message, "__dict__", values)
    object.__setattr__(message, "__pydantic_fields_set__", set(values))
    object.__setattr__(message, "__pydantic_extra__", None)
    object.__setattr__(message, "__pydantic_private__", None)
    return message


def _stream_head(body: dict, fields: frozenset) -> bool:
    """Every field there and no other, and a valid robot id, seq and stamp (StreamMessage)."""
    if body.keys() != fields:
        return False
    robot_id, seq, stamp = body["robot_id"], body["seq"], body["stamp"]
    return (type(robot_id) is str and _robot_id(robot_id) is not None and type(seq) is int and seq >= 0
            and type(stamp) is float and math.isfinite(stamp))


_ODOMETRY_FIELDS = tuple(Odometry.model_fields)  # in the model's order
_SCAN_FIELDS = tuple(Scan.model_fields)
_ODOMETRY_NAMES, _SCAN_NAMES = frozenset(_ODOMETRY_FIELDS), frozenset(_SCAN_FIELDS)


def _fast_odometry(body: dict) -> Odometry | None:
    dt = body.get("dt")
    if not _stream_head(body, _ODOMETRY_NAMES) or type(dt) is not float or not 0.0 < dt <= 10.0:
        return None
    if _floats(body["control"], 2) is None or not _covariance2(body["control_cov"]):
        return None
    return _construct(Odometry, _ODOMETRY_FIELDS, body)


def _fast_scan(body: dict) -> Scan | None:
    if not _stream_head(body, _SCAN_NAMES) or not _covariance2(body["noise_cov"]):
        return None
    ranges = _floats(body["ranges"], None)
    if ranges is None or not _nonnegative(ranges):
        return None
    n = len(ranges)
    bearings = _floats(body["bearings"], n)
    if bearings is None or not _bearings_in_range(bearings):
        return None
    ids = body["landmark_ids"]
    if ids is not None and (type(ids) is not np.ndarray or ids.dtype != _I8 or ids.shape != (n,)):
        return None
    robot_ids = body["robot_ids"]
    if type(robot_ids) is not list or not all(type(rid) is str and _robot_id(rid) is not None for rid in robot_ids):
        return None
    m = len(robot_ids)
    robot_ranges, robot_bearings = _floats(body["robot_ranges"], m), _floats(body["robot_bearings"], m)
    if robot_ranges is None or robot_bearings is None or not _nonnegative(robot_ranges) or not _bearings_in_range(
            robot_bearings):
        return None
    return _construct(Scan, _SCAN_FIELDS, body, robot_ids=list(robot_ids))  # pydantic's list is a new one


_FAST: dict[type, Callable[[dict], Any]] = {Odometry: _fast_odometry, Scan: _fast_scan}
