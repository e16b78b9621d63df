"""What a fleet recording holds, independent of the file: topics, their message models and schemas.

A recording keeps every sample under a key prefix as it crossed Zenoh: the
channel topic is the key expression, the payload bytes are unchanged (the
msgpack envelope of :mod:`schemas.codec`), and each topic's schema is named
after the message model its key carries (:func:`schemas.codec.schema_name`).
A key fleetslam does not know gets the generic schema :data:`UNKNOWN_SCHEMA`.
The file itself (MCAP) is read and written by :mod:`schemas.mcap_file`.

Pure: no Zenoh, no files, no environment.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

from pydantic import BaseModel
from pydantic.json_schema import GenerateJsonSchema

from schemas.codec import ARRAY_EXT_CODE, schema_name
from schemas.keys import Keys
from schemas.messages import (Estimate, GroundTruth, MapEstimate, MclPose, Odometry, PoseEstimate, RobotInfo, Scan,
                              ServiceStats, WorldTruth)

FORMAT_VERSION = "1"
METADATA_NAME = "fleetslam"
MESSAGE_ENCODING = "msgpack"
SCHEMA_ENCODING = "jsonschema"
UNKNOWN_SCHEMA = "UnknownPayload"
ROBOT_KINDS = ("info", "odom", "scan", "truth")

KIND_MODELS: dict[str, type[BaseModel]] = {
    "info": RobotInfo,
    "odom": Odometry,
    "scan": Scan,
    "truth": GroundTruth,
    "world": WorldTruth,
    "estimate": Estimate,
    "dslam_map": MapEstimate,
    "dslam_pose": PoseEstimate,
    "mcl_pose": MclPose,
    "stats": ServiceStats,
}
"""The message model each kind of key carries (DESIGN §2)."""


class RecordingError(ValueError):
    """A recording that cannot be used; the message is one line with the reason."""


@dataclass(frozen=True, slots=True)
class RecordedMessage:
    """One sample as recorded: key, reception time and Zenoh timestamp (ns since the UNIX epoch), payload."""

    topic: str
    log_time_ns: int
    publish_time_ns: int
    data: bytes


def topic_kind(prefix: str, topic: str) -> str:
    """The kind of a key under ``prefix``: a robot stream (info, odom, scan, truth), world, estimate,
    dslam_map, dslam_pose, mcl_pose, stats, or ``unknown``."""
    keys = Keys(prefix)
    robot = keys.parse_robot_key(topic)
    if robot is not None:
        return robot[1] if robot[1] in ROBOT_KINDS else "unknown"
    head = f"{prefix}/"
    if not topic.startswith(head):
        return "unknown"
    parts = topic[len(head):].split("/")
    if topic == keys.world_truth:
        return "world"
    if topic == keys.central_estimate:
        return "estimate"
    if topic == keys.dslam_map:
        return "dslam_map"
    if len(parts) == 3 and parts[:2] == ["dslam", "pose"]:
        return "dslam_pose"
    if len(parts) == 3 and parts[0] == "mcl" and parts[2] == "pose":
        return "mcl_pose"
    if len(parts) >= 2 and parts[-1] == "stats":
        return "stats"
    return "unknown"


def topic_model(prefix: str, topic: str) -> type[BaseModel] | None:
    """The message model a key carries, None for a key fleetslam does not know."""
    return KIND_MODELS.get(topic_kind(prefix, topic))


def topic_schema_name(prefix: str, topic: str) -> str:
    """The schema name of a topic: its model's :func:`~schemas.codec.schema_name`, else :data:`UNKNOWN_SCHEMA`."""
    model = topic_model(prefix, topic)
    return UNKNOWN_SCHEMA if model is None else schema_name(model)


class _ArraysAsExtensions(GenerateJsonSchema):
    """JSON Schema of a message model whose numpy arrays travel as msgpack extensions."""

    def is_instance_schema(self, schema):
        return {"description": f"numpy array: msgpack extension type {ARRAY_EXT_CODE} holding msgpack "
                               "[dtype string, shape] then the little-endian bytes"}


def schema_data(model: type[BaseModel] | None) -> bytes:
    """The schema record's data: a JSON Schema (UTF-8) of the codec envelope ``{schema, v, body}`` around the
    model's fields; for an unknown key, a schema that says only that the payload is kept as received."""
    if model is None:
        document = {"title": UNKNOWN_SCHEMA, "description": "payload of a key fleetslam does not know, as received"}
    else:
        document = {
            "title": schema_name(model), "type": "object",
            "description": "fleetslam codec envelope (schemas/codec.py) of one message",
            "properties": {"schema": {"const": schema_name(model)},
                           "v": {"const": getattr(model, "SCHEMA_VERSION", 1)},
                           "body": model.model_json_schema(schema_generator=_ArraysAsExtensions)},
            "required": ["schema", "v", "body"],
        }
    return json.dumps(document, sort_keys=True).encode()


def robot_of(prefix: str, topic: str) -> tuple[str, str] | None:
    """(robot id, stream) of a robot stream topic (info, odom, scan, truth) under ``prefix``; None otherwise."""
    parsed = Keys(prefix).parse_robot_key(topic)
    return parsed if parsed is not None and parsed[1] in ROBOT_KINDS else None
