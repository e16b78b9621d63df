"""The one msgpack codec for every message that crosses Zenoh.

A payload is a msgpack map ``{"schema": NAME, "v": VERSION, "body": {...}}``.
Arrays travel as msgpack extension type 1 holding a tiny header (dtype string,
shape) and the packed little-endian bytes, never as lists of Python floats.

Every failure to decode (garbage bytes, wrong schema, unknown version, wrong
types, wrong shapes, NaN where not allowed, negative ranges...) raises
:class:`DecodeError`, whose ``reason`` is a short stable label that services
use to count rejections.
"""

from __future__ import annotations

from typing import TypeVar

import msgpack
import numpy as np
import pydantic

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


def _unpack_array(code: int, data: bytes) -> np.ndarray:
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


def _default(obj):
    if isinstance(obj, np.ndarray):
        return _pack_array(obj)
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"cannot encode {type(obj).__name__}")


def schema_name(model: type[pydantic.BaseModel]) -> str:
    return getattr(model, "SCHEMA_NAME", model.__name__)


def encode(message: pydantic.BaseModel) -> bytes:
    """Encode a message model into a msgpack payload."""
    body = message.model_dump(mode="python")
    envelope = {"schema": schema_name(type(message)), "v": getattr(message, "SCHEMA_VERSION", 1), "body": body}
    return msgpack.packb(envelope, default=_default, use_bin_type=True)


def decode(payload: bytes | bytearray | memoryview, expected: type[M]) -> M:
    """Decode a payload into ``expected``; raise :class:`DecodeError` on any problem."""
    try:
        envelope = msgpack.unpackb(bytes(payload), ext_hook=_unpack_array, raw=False, strict_map_key=True)
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
    try:
        return expected.model_validate(envelope["body"], context={"wire": True})
    except pydantic.ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first.get("loc", ()))
        raise DecodeError("invalid", f"{where}: {first.get('msg', 'invalid')}") from None
