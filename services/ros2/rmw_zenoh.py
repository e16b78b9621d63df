"""ROS 2's Zenoh middleware (rmw_zenoh) spoken directly: topic keys, the sample attachment, graph tokens.

What a ROS 2 node on rmw_zenoh puts on the wire (ros2/rmw_zenoh ``docs/design.md`` and its source; DESIGN §2):

- a topic's samples on ``<domain>/<topic without its leading />/<pkg>::msg::dds_::<Type>_/<type hash>``, the
  hash ``RIHS01_<sha256>`` (Jazzy and later) or ``TypeHashNotSupported`` (Humble): a subscriber puts ``*`` there
  and so hears both;
- a CDR payload (4-byte encapsulation header, then the message);
- an attachment on every sample: int64 sequence number, int64 source time stamp (ns), the GID's length as one
  byte (16) and the 16-byte GID of the publisher; rmw_zenoh drops samples without it;
- liveliness tokens for the graph, ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<kind>/<enclave>/<namespace>/
  <node>`` for a node (kind ``NN``) with ``/<topic>/<type>/<hash>/<qos>`` added for a publisher (``MP``) or a
  subscription (``MS``); names are mangled (``/`` → ``%``, empty → ``%``). ``ros2 topic list`` and ``ros2 node
  list`` are built from these tokens.

A :class:`RosNode` declares these for fleetslam's ROS 2 side (``fleetslam ros2``), on a plain Zenoh session.
"""

from __future__ import annotations

import itertools
import logging
import os
import struct
import time
from dataclasses import dataclass
from typing import Callable

import zenoh

log = logging.getLogger(__name__)

GRAPH_PREFIX = "@ros2_lv"
GID_BYTES = 16
ATTACHMENT = struct.Struct("<qqB")  # sequence number, time stamp (ns), GID length; the GID follows
# The QoS of fleetslam's ROS 2 endpoints in rmw_zenoh's token form, defaults elided: reliable, volatile, keep last 10.
DEFAULT_QOS = "::,10:,:,:,,"


def dds_type_name(msgtype: str) -> str:
    """``pkg/msg/Type`` → ``pkg::msg::dds_::Type_`` (the type name rmw_zenoh writes into keys)."""
    package, kind, name = msgtype.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def mangle(name: str) -> str:
    """A ROS name as one key chunk: ``/`` → ``%``, the empty name and ``/`` → ``%``."""
    return "%" if name in ("", "/") else name.replace("/", "%")


def topic_key(domain_id: int, topic: str, msgtype: str, type_hash: str) -> str:
    """The key a ROS 2 topic's samples are put on."""
    return f"{domain_id}/{topic.strip('/')}/{dds_type_name(msgtype)}/{type_hash}"


def topic_subscription_key(domain_id: int, topic: str, msgtype: str) -> str:
    """The key expression a subscription declares: any type hash (Humble's ``TypeHashNotSupported`` included)."""
    return topic_key(domain_id, topic, msgtype, "*")


@dataclass(frozen=True)
class Attachment:
    """The attachment of an rmw_zenoh sample."""

    sequence: int
    stamp_ns: int
    gid: bytes

    def pack(self) -> bytes:
        return ATTACHMENT.pack(self.sequence, self.stamp_ns, len(self.gid)) + self.gid

    @classmethod
    def unpack(cls, data: bytes) -> "Attachment":
        """Parse an attachment; ValueError (``bad_attachment: …``) when it is not rmw_zenoh's layout."""
        if len(data) < ATTACHMENT.size:
            raise ValueError(f"bad_attachment: {len(data)} bytes, at least {ATTACHMENT.size + 1} expected")
        sequence, stamp_ns, gid_length = ATTACHMENT.unpack_from(data)
        if len(data) != ATTACHMENT.size + gid_length:
            raise ValueError(f"bad_attachment: GID of {gid_length} bytes announced, "
                             f"{len(data) - ATTACHMENT.size} present")
        return cls(sequence, stamp_ns, bytes(data[ATTACHMENT.size:]))


@dataclass(frozen=True)
class RosSample:
    """One sample heard on a ROS 2 topic: its key, CDR payload and attachment (None when it came without one)."""

    key: str
    payload: bytes
    attachment: Attachment | None
    attachment_error: str | None = None


class RosPublisher:
    """A ROS 2 publisher: CDR payloads with rmw_zenoh's attachment, reliable with congestion control BLOCK."""

    def __init__(self, session: zenoh.Session, key: str, token: zenoh.LivelinessToken):
        self.key = key
        self.gid = os.urandom(GID_BYTES)
        self.sequence = 0
        self._publisher = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK,
                                                    reliability=zenoh.Reliability.RELIABLE)
        self._token = token

    def put(self, cdr: bytes | memoryview, stamp_ns: int | None = None) -> None:
        self.sequence += 1
        stamp_ns = time.time_ns() if stamp_ns is None else stamp_ns
        self._publisher.put(bytes(cdr), attachment=Attachment(self.sequence, stamp_ns, self.gid).pack())

    def undeclare(self) -> None:
        for entity in (self._token, self._publisher):
            try:
                entity.undeclare()
            except zenoh.ZError:
                pass


class RosNode:
    """A ROS 2 node on a Zenoh session: its ``NN`` token, and publishers and subscriptions with their tokens."""

    _node_ids = itertools.count()

    def __init__(self, session: zenoh.Session, name: str, namespace: str = "/", domain_id: int = 0,
                 enclave: str = ""):
        self.session = session
        self.name, self.namespace, self.domain_id = name, namespace, domain_id
        self.zid = str(session.info.zid())
        self.node_id = next(self._node_ids)
        self._entity_ids = itertools.count(self.node_id + 1_000)
        self._head = (f"{GRAPH_PREFIX}/{domain_id}/{self.zid}/{self.node_id}")
        self._tail = f"{mangle(enclave)}/{mangle(namespace)}/{mangle(name)}"
        self._entities: list = [session.liveliness().declare_token(f"{self._head}/{self.node_id}/NN/{self._tail}")]

    def endpoint_token_key(self, kind: str, topic: str, msgtype: str, type_hash: str, qos: str = DEFAULT_QOS) -> str:
        entity_id = next(self._entity_ids)
        return (f"{self._head}/{entity_id}/{kind}/{self._tail}/{mangle(topic)}/{dds_type_name(msgtype)}/"
                f"{type_hash}/{qos}")

    def publisher(self, topic: str, msgtype: str, type_hash: str) -> RosPublisher:
        """A publisher on ``topic`` (absolute name), announced by an ``MP`` token."""
        token = self.session.liveliness().declare_token(self.endpoint_token_key("MP", topic, msgtype, type_hash))
        publisher = RosPublisher(self.session, topic_key(self.domain_id, topic, msgtype, type_hash), token)
        self._entities.append(publisher)
        return publisher

    def subscription(self, topic: str, msgtype: str, type_hash: str, on_sample: Callable[[RosSample], None]):
        """A subscription to ``topic`` with any type hash, announced by an ``MS`` token; ``on_sample`` is called
        from Zenoh's thread with each sample (its attachment parsed, or the reason it could not be)."""

        def callback(sample: zenoh.Sample) -> None:
            attachment, error = None, None
            if sample.attachment is None:
                error = "no_attachment: rmw_zenoh samples carry one"
            else:
                try:
                    attachment = Attachment.unpack(sample.attachment.to_bytes())
                except ValueError as exc:
                    error = str(exc)
            on_sample(RosSample(str(sample.key_expr), sample.payload.to_bytes(), attachment, error))

        subscriber = self.session.declare_subscriber(topic_subscription_key(self.domain_id, topic, msgtype), callback)
        token = self.session.liveliness().declare_token(self.endpoint_token_key("MS", topic, msgtype, type_hash))
        self._entities += [subscriber, token]
        return subscriber

    def undeclare(self) -> None:
        """Undeclare every entity, tokens included (the node leaves the ROS graph)."""
        for entity in reversed(self._entities):
            try:
                entity.undeclare()
            except zenoh.ZError:
                pass
        self._entities = []
