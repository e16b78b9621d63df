"""What a robot costs on its site's link: bytes per second on the cable between a site and the depot, split by layer.

Two network namespaces on one bridge (tests/integration/netns.py): ``site``, with its own router meshed to the
depot's (``fleetslam router --connect``) and N simulated robots (``fleetslam robot``, 10 Hz odometry and scans, one
process each, clients of the site's router); ``depot``, with its router and ``fleetslam central``, whose
subscriptions pull every robot's streams across the site's cable. Over a steady window the benchmark reads the
cable's byte counters (both directions, the switch port's veth counters, as tests/integration/sites.py does) and
captures every frame on it (an AF_PACKET socket in the switch's namespace, written as a pcap file). The capture is
parsed down to Zenoh's wire messages (batches, frames, PUSH/PUT with their key, timestamp and source info,
declarations, queries, keep-alives) to split the bytes into:

- ``payload``: the fleetslam messages themselves, per stream (odom, scan, info);
- ``zenoh_framing``: what Zenoh adds to them: batch length and frame header, message header and key, the
  timestamp a router adds, the source info (session id, sequence number) the subscribers' sample-miss
  detection and the services' per-session checks need;
- ``zenoh_control``: Zenoh messages that carry no fleetslam payload: the advanced publishers' heartbeats,
  declarations (liveliness tokens, subscribers, queryables), interests, queries and replies, keep-alives;
- ``tcp_ip_headers``: Ethernet, IPv4 and TCP headers of the frames that carry data; ``acks``: the frames that
  carry none (pure TCP acknowledgements);

and a second view by purpose (each stream's full cost, headers included, heartbeats, control, acks).

A run per robot count (``--robots 1,5,20``) and per variant (``--variants``): the variants are the settings each
change adds, applied one after the other (``before`` is the behaviour before them), so the difference between two
neighbours is one change's effect. ``--compact`` adds what a more compact message encoding would give (measured
encodings of the same simulated messages, in this benchmark only: the live codec is unchanged).

Needs root (network namespaces). About 40 s per run.

    sudo .venv/bin/python benchmarks/bandwidth.py --robots 1 --repeat 3 --compact --out reports/bandwidth.json
    sudo .venv/bin/python benchmarks/bandwidth.py --robots 5,20 --variants before,defaults

The robots' own links (client to the site's router, on the site's loopback) are captured too, to tell where an
odometry and its scan were split into two packets (``robot_links``). ``--only`` runs some steps of the ladder.
"""

from __future__ import annotations

import argparse
import bisect
import json
import os
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

PORT = 7447
PREFIX = "bw"

# Each variant adds settings to the one before it: ``env``, the environment of every process; ``router_config``, a
# zenoh config merged into both routers' (``--router-config``: for what fleetslam has no setting of its own);
# ``sysctl``, set in both namespaces. ``before``: the behaviour before issue 54's bandwidth work (RobotInfo every
# second, heartbeats every 0.5 s, routers stamping every sample, no compression on router links).
VARIANTS: dict[str, dict] = {
    "before": {"env": {"FLEETSLAM_INFO_MAX_PERIOD_S": "1", "FLEETSLAM_HEARTBEAT_PERIOD_S": "0.5",
                       "FLEETSLAM_ROUTER_TIMESTAMPS": "true", "FLEETSLAM_LINK_COMPRESSION": "false",
                       "FLEETSLAM_PUBLISH_TOGETHER": "false"}},
    "info_backoff": {"env": {"FLEETSLAM_INFO_MAX_PERIOD_S": "30"}},
    "heartbeat_1s": {"env": {"FLEETSLAM_HEARTBEAT_PERIOD_S": "1"}},
    "no_router_timestamps": {"env": {"FLEETSLAM_ROUTER_TIMESTAMPS": "false"}},
    "compression": {"env": {"FLEETSLAM_LINK_COMPRESSION": "true"}},
    "publish_together": {"env": {"FLEETSLAM_PUBLISH_TOGETHER": "true"}},
    "batch_time_limit_5ms": {"router_config": {"transport": {"link": {"tx": {"queue": {"batching": {
        "time_limit": 5}}}}}}},
    "heartbeat_2s": {"env": {"FLEETSLAM_HEARTBEAT_PERIOD_S": "2"}},
    "no_tcp_timestamps": {"sysctl": {"net.ipv4.tcp_timestamps": "0"}},
}
# Named sets of settings that are not a step of the ladder.
PRESETS: dict[str, dict] = {
    "defaults": {},  # whatever the code's defaults are
}


def _merge(into: dict, more: dict) -> dict:
    for key, value in more.items():
        into[key] = _merge(into.get(key, {}), value) if isinstance(value, dict) else value
    return into


def variant_settings(names: list[str], name: str) -> dict:
    """The settings of variant ``name``: a preset, or the ladder up to it (the steps in ``names``, from
    ``before``, in the ladder's order)."""
    steps = [name] if name in PRESETS else [n for n in VARIANTS if n in names or n == "before"]
    steps = steps[:steps.index(name) + 1]
    out: dict = {"env": {}, "router_config": {}, "sysctl": {}}
    for step in steps:
        _merge(out, (PRESETS if name in PRESETS else VARIANTS)[step])
    return out


# ----------------------------------------------------------------------------------------------------- capture
PCAP_MAGIC_NS = 0xA1B23C4D
ETH_P_ALL = 0x0003
SOL_PACKET, PACKET_STATISTICS = 263, 6


def capture(iface: str, out: str) -> None:
    """Write every frame on ``iface`` to the pcap file ``out`` (nanosecond stamps) until SIGTERM; then one JSON line
    on stdout with the kernel's packet and drop counts."""
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETH_P_ALL))
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 16 << 20)
    sock.bind((iface, 0))
    sock.settimeout(0.2)
    with open(out, "wb") as handle:
        handle.write(struct.pack("<IHHiIII", PCAP_MAGIC_NS, 2, 4, 0, 0, 262144, 1))
        handle.flush()
        while not stop.is_set():
            try:
                data = sock.recv(262144)
            except socket.timeout:
                continue
            except InterruptedError:
                continue
            now = time.time_ns()
            handle.write(struct.pack("<IIII", now // 1_000_000_000, now % 1_000_000_000, len(data), len(data)))
            handle.write(data)
    packets, drops = struct.unpack("II", sock.getsockopt(SOL_PACKET, PACKET_STATISTICS, 8))
    print(json.dumps({"packets": packets, "drops": drops}), flush=True)


@dataclass
class Packet:
    t: float
    length: int  # bytes on the veth (the Ethernet frame without FCS), what its counters count
    src: str = ""
    dst: str = ""
    flow: tuple = ()
    payload: bytes = b""
    tcp_flags: int = 0
    seq: int = 0


def read_pcap(path: Path) -> list[Packet]:
    data = path.read_bytes()
    magic = struct.unpack_from("<I", data, 0)[0]
    scale = 1e-9 if magic == PCAP_MAGIC_NS else 1e-6
    packets, offset = [], 24
    while offset + 16 <= len(data):
        sec, frac, caplen, length = struct.unpack_from("<IIII", data, offset)
        frame = data[offset + 16:offset + 16 + caplen]
        offset += 16 + caplen
        packet = Packet(t=sec + frac * scale, length=length)
        if len(frame) >= 34 and frame[12:14] == b"\x08\x00":
            ihl = (frame[14] & 0x0F) * 4
            total = struct.unpack_from(">H", frame, 16)[0]
            proto = frame[23]
            packet.src, packet.dst = socket.inet_ntoa(frame[26:30]), socket.inet_ntoa(frame[30:34])
            if proto == 6:
                tcp = 14 + ihl
                sport, dport, seq = struct.unpack_from(">HHI", frame, tcp)
                data_offset = (frame[tcp + 12] >> 4) * 4
                packet.tcp_flags = frame[tcp + 13]
                packet.seq = seq
                packet.flow = (packet.src, sport, packet.dst, dport)
                packet.payload = frame[tcp + data_offset:14 + total]
        packets.append(packet)
    return packets


# ------------------------------------------------------------------------------------------ zenoh wire parser
# Zenoh 1.x wire format (commons/zenoh-codec): on TCP, each batch is a 2-byte little-endian length, then (when
# compression was negotiated) one batch header byte, then transport messages; a FRAME carries network messages.
T_OAM, T_INIT, T_OPEN, T_CLOSE, T_KEEP_ALIVE, T_FRAME, T_FRAGMENT, T_JOIN = range(8)
N_OAM, N_DECLARE, N_PUSH, N_REQUEST, N_RESPONSE, N_RESPONSE_FINAL, N_INTEREST = 0x1F, 0x1E, 0x1D, 0x1C, 0x1B, 0x1A, 0x19
Z_PUT, Z_DEL, Z_QUERY, Z_REPLY, Z_ERR = 0x01, 0x02, 0x03, 0x04, 0x05
D_KEYEXPR, D_FINAL = 0x00, 0x1A
APP_STREAMS = ("odom", "scan", "info", "truth")


class ParseError(Exception):
    pass


class Cursor:
    def __init__(self, data: bytes, pos: int = 0, end: int | None = None):
        self.data, self.pos, self.end = data, pos, len(data) if end is None else end

    def u8(self) -> int:
        if self.pos >= self.end:
            raise ParseError("short")
        value = self.data[self.pos]
        self.pos += 1
        return value

    def zint(self) -> int:
        value, shift = 0, 0
        for index in range(9):
            byte = self.u8()
            if index == 8:
                return value | (byte << shift)
            value |= (byte & 0x7F) << shift
            if not byte & 0x80:
                return value
            shift += 7
        return value

    def take(self, n: int) -> bytes:
        if self.pos + n > self.end:
            raise ParseError("short")
        chunk = self.data[self.pos:self.pos + n]
        self.pos += n
        return chunk

    def zbytes(self) -> bytes:
        return self.take(self.zint())

    def left(self) -> int:
        return self.end - self.pos


def skip_exts(cur: Cursor, more: bool) -> list[tuple[int, int, int]]:
    """Skip a chain of extensions; [(extension id, start, end)]."""
    found = []
    while more:
        start = cur.pos
        header = cur.u8()
        encoding = (header >> 5) & 0x03
        if encoding == 1:
            cur.zint()
        elif encoding == 2:
            cur.take(cur.zint())
        elif encoding != 0:
            raise ParseError("extension encoding")
        found.append((header & 0x0F, start, cur.pos))
        more = bool(header & 0x80)
    return found


def wire_expr(cur: Cursor, named: bool) -> tuple[int, str]:
    scope = cur.zint()
    suffix = cur.zbytes().decode("utf-8", "replace") if named else ""
    return scope, suffix


def key_purpose(key: str) -> str:
    """What a PUSH on ``key`` is: a stream of a robot (its last chunk), a heartbeat, or something else."""
    if "/@adv/" in key:
        return "heartbeat"
    last = key.rsplit("/", 1)[-1]
    if key.startswith(f"{PREFIX}/robots/") and last in APP_STREAMS:
        return last
    return "other_put"


@dataclass
class StreamParse:
    """One TCP direction's bytes cut into labelled spans: (start, end, layer, purpose), where purpose is a name, or
    for the bytes a batch's messages share (batch length, frame header) a dict of shares; compressed batches give
    ("scaled", first byte, wire bytes, layer, purpose) entries instead."""

    spans: list = field(default_factory=list)
    keyexprs: dict = field(default_factory=dict)  # expression ids this side declared
    payload_sizes: dict = field(default_factory=lambda: defaultdict(list))  # purpose -> [size]
    compressed_batches: int = 0
    batches: int = 0
    messages_per_batch: list = field(default_factory=list)
    unparsed: int = 0
    scans_with_odom: int = 0  # batches that hold a scan and an odometry

    def reset(self) -> None:
        self.spans, self.payload_sizes = [], defaultdict(list)
        self.compressed_batches = self.batches = self.unparsed = self.scans_with_odom = 0
        self.messages_per_batch = []

    def count(self, purposes: list[str]) -> None:
        self.batches += 1
        self.messages_per_batch.append(len(purposes))
        if "odom" in purposes and "scan" in purposes:
            self.scans_with_odom += 1


def resolve(scope: int, suffix: str, mapping: dict) -> str:
    return mapping.get(scope, f"#{scope}") + suffix if scope else suffix


def parse_put_like(cur: Cursor, spans: list, purpose: str, head_start: int, result: StreamParse) -> None:
    """A PUT (or DEL) body at ``cur``; spans from ``head_start`` (the message's first byte) labelled."""
    header = cur.u8()
    mid = header & 0x1F
    if mid not in (Z_PUT, Z_DEL):
        raise ParseError(f"push body {mid:#x}")
    if header & 0x20:  # timestamp (a router adds it when timestamping is on)
        spans.append((head_start, cur.pos, "message_headers", purpose))
        start = cur.pos
        cur.zint()
        cur.take(cur.zint())
        spans.append((start, cur.pos, "router_timestamps", purpose))
        head_start = cur.pos
    if mid == Z_PUT and header & 0x40:  # encoding
        encoding = cur.zint()
        if encoding & 1:
            cur.take(cur.zint())
    for ext_id, start, end in skip_exts(cur, bool(header & 0x80)):
        if ext_id == 0x1:  # source info: the publishing session's id, the publisher's id, the sample's number
            spans.append((head_start, start, "message_headers", purpose))
            spans.append((start, end, "source_info", purpose))
            head_start = end
    if mid == Z_PUT:
        size = cur.zint()
        spans.append((head_start, cur.pos, "message_headers", purpose))
        start = cur.pos
        cur.take(size)
        spans.append((start, cur.pos, "payload", purpose))
        result.payload_sizes[purpose].append(size)
    else:
        spans.append((head_start, cur.pos, "message_headers", purpose))


def parse_network(cur: Cursor, spans: list, result: StreamParse, peer: StreamParse) -> str:
    """One network message at ``cur`` (spans appended to ``spans``); returns its purpose."""
    start = cur.pos
    header = cur.u8()
    mid = header & 0x1F
    if mid == N_PUSH:
        scope, suffix = wire_expr(cur, bool(header & 0x20))
        key = resolve(scope, suffix, result.keyexprs if header & 0x40 else peer.keyexprs)
        purpose = key_purpose(key)
        skip_exts(cur, bool(header & 0x80))
        if purpose == "heartbeat":
            parse_put_like(cur, [], purpose, start, result)
            spans.append((start, cur.pos, "control", "heartbeats"))
            return "heartbeats"
        parse_put_like(cur, spans, purpose, start, result)
        return purpose
    if mid == N_DECLARE:
        if header & 0x20:
            cur.zint()
        skip_exts(cur, bool(header & 0x80))
        body = cur.u8()
        did = body & 0x1F
        if did == D_KEYEXPR:
            expr_id = cur.zint()
            scope, suffix = wire_expr(cur, bool(body & 0x20))
            result.keyexprs[expr_id] = resolve(scope, suffix, result.keyexprs)
        elif did in (0x02, 0x04, 0x06):  # subscriber, queryable, (liveliness) token
            cur.zint()
            wire_expr(cur, bool(body & 0x20))
        elif did in (0x01, 0x03, 0x05, 0x07):  # their undeclarations
            cur.zint()
        elif did != D_FINAL:
            raise ParseError(f"declaration {did:#x}")
        skip_exts(cur, bool(body & 0x80))
        spans.append((start, cur.pos, "control", "declarations"))
        return "declarations"
    if mid == N_INTEREST:
        cur.zint()
        if (header >> 5) & 0x03:
            options = cur.u8()
            if options & 0x10:
                wire_expr(cur, bool(options & 0x20))
        skip_exts(cur, bool(header & 0x80))
        spans.append((start, cur.pos, "control", "interests"))
        return "interests"
    if mid in (N_REQUEST, N_RESPONSE):
        cur.zint()
        wire_expr(cur, bool(header & 0x20))
        skip_exts(cur, bool(header & 0x80))
        body = cur.u8()
        bid = body & 0x1F
        if bid == Z_QUERY:
            if body & 0x20:
                cur.zint()
            if body & 0x40:
                cur.zbytes()
            skip_exts(cur, bool(body & 0x80))
        elif bid == Z_REPLY:
            if body & 0x20:
                cur.zint()
            skip_exts(cur, bool(body & 0x80))
            parse_put_like(cur, [], "reply", start, result)
        elif bid == Z_ERR:
            if body & 0x40:
                encoding = cur.zint()
                if encoding & 1:
                    cur.zbytes()
            skip_exts(cur, bool(body & 0x80))
            cur.zbytes()
        else:
            raise ParseError(f"request/response body {bid:#x}")
        spans.append((start, cur.pos, "control", "queries_replies"))
        return "queries_replies"
    if mid == N_RESPONSE_FINAL:
        cur.zint()
        skip_exts(cur, bool(header & 0x80))
        spans.append((start, cur.pos, "control", "queries_replies"))
        return "queries_replies"
    if mid == N_OAM:
        skip_oam(cur, header)
        spans.append((start, cur.pos, "control", "oam"))
        return "oam"
    raise ParseError(f"network message {mid:#x}")


def skip_oam(cur: Cursor, header: int) -> None:
    """An OAM message (network or transport) after its header byte: its id, extensions and body."""
    cur.zint()
    skip_exts(cur, bool(header & 0x80))
    encoding = (header >> 5) & 0x03
    if encoding == 1:
        cur.zint()
    elif encoding == 2:
        cur.zbytes()


def parse_batch_body(cur: Cursor, result: StreamParse, peer: StreamParse) -> tuple[list, list, list]:
    """The transport messages of one batch's content: (spans, shared byte ranges, purposes), batch-local offsets."""
    spans: list = []
    shared: list = []
    purposes: list[str] = []
    try:
        while cur.left() > 0:
            start = cur.pos
            header = cur.u8()
            mid = header & 0x1F
            if mid == T_FRAME:
                cur.zint()
                skip_exts(cur, bool(header & 0x80))
                shared.append((start, cur.pos))
                while cur.left() > 0 and (cur.data[cur.pos] & 0x1F) >= N_INTEREST:
                    purposes.append(parse_network(cur, spans, result, peer))
            elif mid == T_KEEP_ALIVE:
                skip_exts(cur, bool(header & 0x80))
                spans.append((start, cur.pos, "control", "keepalives"))
                purposes.append("keepalives")
            elif mid == T_FRAGMENT:
                cur.zint()
                skip_exts(cur, bool(header & 0x80))
                spans.append((start, cur.end, "control", "fragments"))
                purposes.append("fragments")
                cur.pos = cur.end
            elif mid == T_OAM:
                skip_oam(cur, header)
                spans.append((start, cur.pos, "control", "oam"))
                purposes.append("oam")
            else:  # INIT, OPEN, CLOSE: the session's handshake and end
                spans.append((start, cur.end, "control", "handshake"))
                purposes.append("handshake")
                cur.pos = cur.end
    except ParseError:
        result.unparsed += cur.end - cur.pos
        spans.append((cur.pos, cur.end, "control", "unparsed"))
        purposes.append("unparsed")
    return spans, shared, purposes


def _shares(purposes: list[str]) -> dict[str, float]:
    if not purposes:
        return {"transport": 1.0}
    shares: dict[str, float] = defaultdict(float)
    for purpose in purposes:
        shares[purpose] += 1.0 / len(purposes)
    return dict(shares)


def parse_batch(data: bytes, base: int, result: StreamParse, peer: StreamParse, compression: bool) -> None:
    """One batch (``data``: without its 2-byte length) whose content starts at stream offset ``base``."""
    head = [(base - 2, base)]  # the length
    body = 0
    if compression:  # one batch header byte; its bit 0: the rest is lz4-compressed
        head.append((base, base + 1))
        body = 1
        if data[0] & 0x01:
            import lz4.block

            result.compressed_batches += 1
            try:
                inner = lz4.block.decompress(data[1:], uncompressed_size=65536)
            except lz4.block.LZ4BlockError:
                result.unparsed += len(data)
                result.spans.append((base + 1, base + len(data), "control", "unparsed"))
                result.spans.extend((s, e, "batch_frame", {"unparsed": 1.0}) for s, e in head)
                return
            spans, shared, purposes = parse_batch_body(Cursor(inner), result, peer)
            totals: dict = defaultdict(float)
            for s, e, layer, purpose in spans:
                totals[(layer, purpose)] += e - s
            shares = _shares(purposes)
            inner_shared = sum(e - s for s, e in shared)
            whole = sum(totals.values()) + inner_shared or 1.0
            wire = len(data) - 1
            for (layer, purpose), size in totals.items():
                result.spans.append(("scaled", base + 1, wire * size / whole, layer, purpose))
            if inner_shared:
                result.spans.append(("scaled", base + 1, wire * inner_shared / whole, "batch_frame", shares))
            result.spans.extend((s, e, "batch_frame", shares) for s, e in head)
            result.count(purposes)
            return
    spans, shared, purposes = parse_batch_body(Cursor(data, body), result, peer)
    shares = _shares(purposes)
    result.spans.extend((s + base, e + base, layer, purpose) for s, e, layer, purpose in spans)
    result.spans.extend((s + base, e + base, "batch_frame", shares) for s, e in shared)
    result.spans.extend((s, e, "batch_frame", shares) for s, e in head)
    result.count(purposes)


def reassemble(packets: list[Packet], flow: tuple) -> tuple[bytes, dict[int, int]]:
    """The bytes of one TCP direction from its SYN, and per packet index the stream offset of its payload."""
    isn = None
    stream = bytearray()
    offsets: dict[int, int] = {}
    for index, packet in enumerate(packets):
        if packet.flow != flow:
            continue
        if packet.tcp_flags & 0x02:  # SYN
            isn = packet.seq
            continue
        if isn is None or not packet.payload:
            continue
        offset = (packet.seq - isn - 1) % (1 << 32)
        offsets[index] = offset
        if offset == len(stream):
            stream += packet.payload
        elif offset + len(packet.payload) > len(stream) >= offset:  # a retransmission overlapping the end
            stream += packet.payload[len(stream) - offset:]
    return bytes(stream), offsets


def parse_stream(stream: bytes, result: StreamParse, peer: StreamParse, compression: bool) -> None:
    """Every batch of one direction; the first two (the INIT and OPEN of the handshake, where compression is
    negotiated) have no batch header."""
    offset, number = 0, 0
    while offset + 2 <= len(stream):
        length = struct.unpack_from("<H", stream, offset)[0]
        if offset + 2 + length > len(stream):
            break
        parse_batch(stream[offset + 2:offset + 2 + length], offset + 2, result, peer, compression and number >= 2)
        offset += 2 + length
        number += 1


class Tally:
    """Bytes by (layer, purpose)."""

    def __init__(self) -> None:
        self.layer: dict[str, float] = defaultdict(float)
        self.purpose: dict[str, float] = defaultdict(float)
        self.by_layer_purpose: dict[tuple[str, str], float] = defaultdict(float)

    def add(self, layer: str, purpose, nbytes: float) -> None:
        shares = purpose if isinstance(purpose, dict) else {purpose: 1.0}
        self.layer[layer] += nbytes
        for name, share in shares.items():
            self.purpose[name] += nbytes * share
            self.by_layer_purpose[(layer, name)] += nbytes * share


class SpanIndex:
    """The labelled spans of one TCP direction, looked up by stream byte range."""

    def __init__(self, parsed: StreamParse):
        self.plain = sorted((s for s in parsed.spans if s[0] != "scaled"), key=lambda s: s[0])
        self.starts = [s[0] for s in self.plain]
        self.scaled: dict[int, list] = defaultdict(list)
        for _, start, nbytes, layer, purpose in (s for s in parsed.spans if s[0] == "scaled"):
            self.scaled[start].append((nbytes, layer, purpose))
        self.scaled_starts = sorted(self.scaled)

    def labels(self, offset: int, size: int) -> dict:
        """Bytes of [offset, offset + size) per (layer, purpose), the shares of shared bytes split; a compressed
        batch's share goes to the packet that holds its first byte."""
        out: dict = defaultdict(float)
        end = offset + size
        covered = 0.0

        def add(layer, purpose, nbytes):
            if isinstance(purpose, dict):
                for name, share in purpose.items():
                    out[(layer, name)] += nbytes * share
            else:
                out[(layer, purpose)] += nbytes

        position = max(bisect.bisect_right(self.starts, offset) - 1, 0)
        while position < len(self.plain) and self.plain[position][0] < end:
            s, e, layer, purpose = self.plain[position]
            overlap = min(e, end) - max(s, offset)
            if overlap > 0:
                covered += overlap
                add(layer, purpose, overlap)
            position += 1
        first = bisect.bisect_left(self.scaled_starts, offset)
        for start in self.scaled_starts[first:bisect.bisect_left(self.scaled_starts, end)]:
            for nbytes, layer, purpose in self.scaled[start]:
                add(layer, purpose, nbytes)
        if not self.scaled and covered < size - 1e-6:
            out[("unparsed", "unparsed")] += size - covered
        return out


def breakdown(packets: list[Packet], site: str, t0: float, t1: float, compression: bool) -> dict:
    """The cable's bytes in [t0, t1), split by layer and purpose (see the module docstring)."""
    flows = {p.flow for p in packets if p.flow and p.payload}
    parses = {flow: StreamParse() for flow in flows}
    offsets: dict[tuple, dict[int, int]] = {}
    streams: dict[tuple, bytes] = {}
    for flow in flows:
        streams[flow], offsets[flow] = reassemble(packets, flow)
    for _ in range(2):  # twice: a PUSH may name an expression id the other side declared (its mapping)
        for flow in flows:
            parses[flow].reset()
            peer = parses.get((flow[2], flow[3], flow[0], flow[1])) or StreamParse()
            parse_stream(streams[flow], parses[flow], peer, compression)
    index = {flow: SpanIndex(parsed) for flow, parsed in parses.items()}
    directions = {"site_to_depot": Tally(), "depot_to_site": Tally()}
    counts = {"site_to_depot": defaultdict(int), "depot_to_site": defaultdict(int)}
    for number, packet in enumerate(packets):
        if not t0 <= packet.t < t1:
            continue
        direction = "site_to_depot" if packet.src == site else "depot_to_site"
        tally, count = directions[direction], counts[direction]
        count["frames"] += 1
        if not packet.flow:
            tally.add("other_frames", "other_frames", packet.length)
            continue
        if not packet.payload:
            kind = "acks" if packet.tcp_flags & 0x17 == 0x10 else "tcp_control"
            tally.add(kind, kind, packet.length)
            count[kind] += 1
            continue
        count["data_frames"] += 1
        header_bytes = packet.length - len(packet.payload)
        offset = offsets[packet.flow].get(number)
        labels = index[packet.flow].labels(offset, len(packet.payload)) if offset is not None else \
            {("unparsed", "unparsed"): float(len(packet.payload))}
        total = sum(labels.values()) or 1.0
        for (layer, purpose), nbytes in labels.items():
            tally.add(layer, purpose, nbytes)
            tally.add("tcp_ip_headers", purpose, header_bytes * nbytes / total)
    return {"directions": directions, "counts": counts, "parses": parses, "site": site}


# ------------------------------------------------------------------------------------------------ the fleet
def _cable_bytes(lab, host: str) -> dict[str, int]:
    """Bytes the cable of ``host`` carried so far, per direction (its switch port's counters: rx = from the host)."""
    counts = {}
    for direction, name in (("rx_bytes", "site_to_depot"), ("tx_bytes", "depot_to_site")):
        out = subprocess.run(["ip", "netns", "exec", lab.switch, "cat",
                              f"/sys/class/net/{lab.ports[host]}/statistics/{direction}"],
                             capture_output=True, text=True, check=True)
        counts[name] = int(out.stdout)
    return counts


def probe(out: str) -> None:
    """(depot) One JSON line per central stats message: wall time and messages in."""
    import zenoh

    from schemas.config import FleetSettings
    from schemas.transport import Shutdown, open_session

    settings = FleetSettings()
    shutdown = Shutdown()
    handle = open(out, "a", buffering=1)

    def on_stats(sample: zenoh.Sample) -> None:
        from schemas.codec import decode
        from schemas.messages import ServiceStats

        stats = decode(sample.payload.to_bytes(), ServiceStats)
        handle.write(json.dumps({"t": time.time(), "in": stats.messages_in, "rejected": stats.rejected}) + "\n")

    session = open_session(settings)
    try:
        subscriber = session.declare_subscriber(f"{settings.prefix}/central/stats", on_stats)
        shutdown.wait()
        subscriber.undeclare()
    finally:
        session.close()


def _stats_rows(path: Path) -> list[dict]:
    if not path.exists():
        return []
    rows = []
    for line in path.read_text().splitlines():
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            pass
    return rows


def _streamed(rows: list[dict]) -> int:
    return sum(rows[-1]["in"].get(s, 0) for s in ("odom", "scan")) if rows else 0


def run_once(robots: int, settings: dict, workdir: Path, warmup_s: float, window_s: float, rate_hz: float,
             keep_pcap: bool, robot_duration_s: float) -> dict:
    from tests.helpers import wait_until
    from tests.integration.netns import NetnsLab

    lab = NetnsLab(f"bw{os.getpid() % 1000}")
    try:
        depot, site = lab.add_host("depot"), lab.add_host("site")
        for host in ("depot", "site"):
            for key, value in settings.get("sysctl", {}).items():
                subprocess.run(lab.command(host, ["sysctl", "-q", "-w", f"{key}={value}"]), check=True)
        env = {"PATH": "/usr/bin:/bin:/usr/sbin:/sbin", "PYTHONUNBUFFERED": "1", "FLEETSLAM_PREFIX": PREFIX,
               "FLEETSLAM_ZENOH_CONNECT": f"tcp/127.0.0.1:{PORT}", "FLEETSLAM_CONNECT_TIMEOUT_S": "60",
               **settings.get("env", {})}
        if settings.get("router_config"):
            router_config = workdir / "router-config.json5"
            router_config.write_text(json.dumps(settings["router_config"]))
            env["FLEETSLAM_ROUTER_CONFIG"] = str(router_config)
        pcap = workdir / "cable.pcap"
        capturer = lab.start("switch", [sys.executable, str(Path(__file__).resolve()), "capture", "--iface",
                                        lab.ports["site"], "--out", str(pcap)], env,
                             workdir / "capture.log", REPO)
        local_pcap = workdir / "site-loopback.pcap"  # the robots' links to their router, inside the site
        local_capturer = lab.start("site", [sys.executable, str(Path(__file__).resolve()), "capture", "--iface", "lo",
                                            "--out", str(local_pcap)], env, workdir / "capture-lo.log", REPO)
        wait_until(lambda: all(f.exists() and f.stat().st_size >= 24 for f in (pcap, local_pcap)), 20, 0.05,
                   "the captures to start")
        python = [sys.executable, "-m", "services.cli"]

        def start(host: str, name: str, *argv: str):
            return lab.start(host, [*python, *argv], env, workdir / f"{name}.log", REPO)

        start("depot", "router-depot", "router", "--listen", f"tcp/0.0.0.0:{PORT}")
        start("site", "router-site", "router", "--listen", f"tcp/0.0.0.0:{PORT}", "--connect",
              f"tcp/{depot}:{PORT}")
        stats = workdir / "central-stats.jsonl"
        lab.start("depot", [sys.executable, str(Path(__file__).resolve()), "probe", "--out", str(stats)], env,
                  workdir / "probe.log", REPO)
        start("depot", "central", "central", "--association", "known")
        robot_processes = [start("site", f"r{k}", "robot", "--id", f"r{k}", "--rate", str(rate_hz), "--duration",
                                 str(robot_duration_s), "--start-delay", "1", "--no-publish-truth")
                           for k in range(1, robots + 1)]
        expected = robots * 2 * rate_hz  # messages per second central takes in

        def steady() -> bool:
            rows = _stats_rows(stats)
            if len(rows) < 3:
                return False
            (a, b) = rows[-3], rows[-1]
            return _streamed([b]) - _streamed([a]) >= 0.8 * expected * (b["t"] - a["t"])

        wait_until(steady, 120 + 5 * robots, 0.2, f"central to take in {robots} robots' streams")
        warm = time.time() + warmup_s  # past the declarations' burst
        wait_until(lambda: time.time() >= warm, warmup_s + 5, 0.2, "the warm-up")
        t0, bytes0, in0 = time.time(), _cable_bytes(lab, "site"), _streamed(_stats_rows(stats))
        wait_until(lambda: time.time() - t0 >= window_s, window_s + 5, 0.2, "the window")
        t1, bytes1, in1 = time.time(), _cable_bytes(lab, "site"), _streamed(_stats_rows(stats))
        alive = sum(p.poll() is None for p in robot_processes)
        for process in (capturer, local_capturer):
            process.send_signal(signal.SIGTERM)
            process.wait(timeout=20)
        capture_stats = json.loads((workdir / "capture.log").read_text().strip().splitlines()[-1] or "{}")
    finally:
        lab.close()
    seconds = t1 - t0
    counters = {k: (bytes1[k] - bytes0[k]) / seconds for k in bytes0}
    packets = read_pcap(pcap)
    compression = settings.get("env", {}).get("FLEETSLAM_LINK_COMPRESSION", "true").lower() == "true"
    parsed = breakdown(packets, site, t0, t1, compression)
    robot_links = robot_link_batching(read_pcap(local_pcap))
    if not keep_pcap:
        pcap.unlink()
        local_pcap.unlink()
    return {**summarise(robots, seconds, counters, parsed, capture_stats, (in1 - in0) / seconds, alive, rate_hz),
            "robot_links": robot_links}


def robot_link_batching(packets: list[Packet]) -> dict:
    """How the robots' own links (client to its router, on the site's loopback) batch: Zenoh messages per batch,
    and the share of scans sent in one batch with odometry (before the site's router forwards them)."""
    flows = {p.flow for p in packets if p.flow and p.payload and p.flow[3] == PORT}
    scans = together = 0
    per_batch: list[int] = []
    for flow in flows:
        stream, _ = reassemble(packets, flow)
        parsed = StreamParse()
        parse_stream(stream, parsed, StreamParse(), compression=False)
        if not parsed.payload_sizes.get("scan"):
            continue  # not a robot's link
        scans += len(parsed.payload_sizes["scan"])
        together += parsed.scans_with_odom
        per_batch += [n for n in parsed.messages_per_batch if n]
    return {"scans_sharing_a_batch_with_odometry": round(together / scans, 3) if scans else None,
            "zenoh_messages_per_batch": round(sum(per_batch) / len(per_batch), 2) if per_batch else None}


def summarise(robots: int, seconds: float, counters: dict, parsed: dict, capture_stats: dict, central_rate: float,
              alive: int, rate_hz: float) -> dict:
    def per_s(value: float) -> float:
        return round(value / seconds, 1)

    directions = parsed["directions"]
    total_captured = sum(sum(t.layer.values()) for t in directions.values())
    both = Tally()
    for tally in directions.values():
        for (layer, purpose), nbytes in tally.by_layer_purpose.items():
            both.add(layer, purpose, nbytes)
    payload = {p: per_s(both.by_layer_purpose.get(("payload", p), 0.0)) for p in APP_STREAMS + ("other_put",)}
    framing = {layer: per_s(both.layer.get(layer, 0.0))
               for layer in ("batch_frame", "message_headers", "router_timestamps", "source_info")}
    control = {purpose: per_s(nbytes) for (layer, purpose), nbytes in both.by_layer_purpose.items()
               if layer == "control"}
    layers = {
        "payload": round(sum(payload.values()), 1),
        "zenoh_framing": round(sum(framing.values()), 1),
        "zenoh_control": round(sum(control.values()), 1),
        "tcp_ip_headers": per_s(both.layer.get("tcp_ip_headers", 0.0)),
        "acks": per_s(both.layer.get("acks", 0.0)),
        "other": per_s(sum(both.layer.get(k, 0.0) for k in ("tcp_control", "other_frames", "unparsed"))),
    }
    purposes = {name: per_s(nbytes) for name, nbytes in sorted(both.purpose.items(), key=lambda kv: -kv[1])}
    mean_sizes, counts_in_run, together = {}, {}, None
    for flow, parse in parsed["parses"].items():
        if flow[0] == parsed["site"]:
            for purpose, sizes in parse.payload_sizes.items():
                if sizes:
                    mean_sizes[purpose] = round(sum(sizes) / len(sizes), 1)
                    counts_in_run[purpose] = len(sizes)
            scans = len(parse.payload_sizes.get("scan", []))
            together = round(parse.scans_with_odom / scans, 3) if scans else None
    frames = {d: dict(c) for d, c in parsed["counts"].items()}
    mpb = [n for p in parsed["parses"].values() for n in p.messages_per_batch if n]
    cable = round(sum(counters.values()), 1)
    return {
        "robots": robots, "rate_hz": rate_hz, "window_s": round(seconds, 1), "robots_alive_at_end": alive,
        "central_msgs_per_s": round(central_rate, 1), "expected_msgs_per_s": robots * 2 * rate_hz,
        "cable_bytes_per_s": cable, "cable_bytes_per_s_per_robot": round(cable / robots, 1),
        "cable_by_direction": {k: round(v, 1) for k, v in counters.items()},
        "captured_bytes_per_s": per_s(total_captured),
        "capture": capture_stats,
        "layers_per_robot": {k: round(v / robots, 1) for k, v in layers.items()},
        "payload_per_robot": {k: round(v / robots, 1) for k, v in payload.items() if v},
        "zenoh_framing_per_robot": {k: round(v / robots, 1) for k, v in framing.items()},
        "zenoh_control_per_robot": {k: round(v / robots, 1) for k, v in control.items()},
        "purposes_per_robot": {k: round(v / robots, 1) for k, v in purposes.items()},
        "mean_payload_bytes": mean_sizes,
        "site_messages_whole_run": counts_in_run,
        "frames_per_s": {d: {k: round(v / seconds, 1) for k, v in c.items()} for d, c in frames.items()},
        "zenoh_messages_per_batch": round(sum(mpb) / len(mpb), 2) if mpb else None,
        "scans_sharing_a_batch_with_odometry": together,
        "compressed_batches": sum(p.compressed_batches for p in parsed["parses"].values()),
        "unparsed_bytes": sum(p.unparsed for p in parsed["parses"].values()),
    }


# ----------------------------------------------------------------------------------- compact encodings (estimate)
def compact_estimate(rate_hz: float) -> dict:
    """Encoded sizes of the same simulated robot's messages: the live codec's, and two more compact ones that this
    benchmark only measures (the live codec is unchanged): msgpack without field names and array headers
    (positional, float64 kept: lossless), and packed little-endian structs with float32 (ranges, bearings,
    covariances; about 7 significant digits: below the sensors' noise by orders of magnitude)."""
    import msgpack
    import numpy as np

    from robots.process import load_robot
    from schemas.codec import encode
    from schemas.config import RobotSettings

    robot, _ = load_robot(RobotSettings(robot_id="r1", duration=60.0, rate=rate_hz))
    sizes: dict[str, dict[str, list[int]]] = {"odom": defaultdict(list), "scan": defaultdict(list)}
    for event in robot.events(with_truth=False):
        name = "odom" if type(event).__name__ == "OdomEvent" else "scan"
        message = event.to_message(with_ids=True) if name == "scan" else event.to_message()
        sizes[name]["msgpack_map (live)"].append(len(encode(message)))
        if name == "odom":
            cov = np.asarray(message.control_cov)
            positional = [message.seq, message.stamp, message.dt, np.asarray(message.control, "<f8").tobytes(),
                          cov[np.triu_indices(2)].astype("<f8").tobytes()]
            packed = struct.pack("<Idffffff", message.seq, message.stamp, message.dt,
                                 *np.asarray(message.control, float), *cov[np.triu_indices(2)])
        else:
            cov = np.asarray(message.noise_cov)
            ids = message.landmark_ids
            positional = [message.seq, message.stamp, np.asarray(message.ranges, "<f8").tobytes(),
                          np.asarray(message.bearings, "<f8").tobytes(),
                          None if ids is None else np.asarray(ids, "<i4").tobytes(),
                          cov[np.triu_indices(2)].astype("<f8").tobytes(), list(message.robot_ids),
                          np.asarray(message.robot_ranges, "<f8").tobytes(),
                          np.asarray(message.robot_bearings, "<f8").tobytes()]
            n = len(message.ranges)
            packed = (struct.pack("<IdBB", message.seq, message.stamp, n, len(message.robot_ids))
                      + np.asarray(message.ranges, "<f4").tobytes() + np.asarray(message.bearings, "<f4").tobytes()
                      + (b"" if ids is None else np.asarray(ids, "<i2").tobytes())
                      + cov[np.triu_indices(2)].astype("<f4").tobytes()
                      + b"".join(bytes([len(rid)]) + rid.encode() for rid in message.robot_ids)
                      + np.asarray(message.robot_ranges, "<f4").tobytes()
                      + np.asarray(message.robot_bearings, "<f4").tobytes())
        sizes[name]["msgpack_positional"].append(len(msgpack.packb(positional, use_bin_type=True)))
        sizes[name]["packed_f32"].append(len(packed))
    rates = robot.stream_rates()
    out = {}
    for codec in ("msgpack_map (live)", "msgpack_positional", "packed_f32"):
        mean = {name: float(np.mean(sizes[name][codec])) for name in sizes}
        out[codec] = {"odom_bytes": round(mean["odom"], 1), "scan_bytes": round(mean["scan"], 1),
                      "payload_bytes_per_s": round(mean["odom"] * rates["odom"] + mean["scan"] * rates["scan"], 1)}
    return out


def with_compact(result: dict, compact: dict) -> dict:
    """The run's per-robot cable bytes with its odometry and scan payload (as measured on the cable: compressed, if
    compression was on) replaced by each encoding's uncompressed size; everything else as measured (per-message
    costs do not depend on the payload's size). An upper bound when compression is on (the compact payload would
    shrink a little too)."""
    measured = result["payload_per_robot"].get("odom", 0.0) + result["payload_per_robot"].get("scan", 0.0)
    return {codec: round(result["cable_bytes_per_s_per_robot"] - measured + v["payload_bytes_per_s"], 1)
            for codec, v in compact.items()}


# ----------------------------------------------------------------------------------------------------- main
def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command")
    cap = sub.add_parser("capture", help="(internal) capture an interface to a pcap file until SIGTERM")
    cap.add_argument("--iface", required=True)
    cap.add_argument("--out", required=True)
    pro = sub.add_parser("probe", help="(internal) write central's stats as JSON lines until SIGTERM")
    pro.add_argument("--out", required=True)
    parser.add_argument("--robots", default="1", help="robot counts at the site, comma-separated (default: 1)")
    parser.add_argument("--variants", default="before,info_backoff,heartbeat_1s,no_router_timestamps,compression,"
                        "publish_together",
                        help=f"comma-separated, run in order; ladder steps: {', '.join(VARIANTS)}; presets: "
                        f"{', '.join(PRESETS)}")
    parser.add_argument("--window-s", type=float, default=20.0, help="steady window measured (s)")
    parser.add_argument("--warmup-s", type=float, default=5.0, help="wall seconds after the streams are steady")
    parser.add_argument("--rate", type=float, default=10.0, help="robots' scan and odometry rate (Hz)")
    parser.add_argument("--robot-duration-s", type=float, default=300.0,
                        help="seconds each robot runs (simulated before it starts: keep it short), at least its "
                        "start, central's, the warm-up and the window")
    parser.add_argument("--repeat", type=int, default=1, help="runs of each robot count and variant")
    parser.add_argument("--only", default=None, help="run only these of --variants (comma-separated; each still "
                        "with every ladder step of --variants before it)")
    parser.add_argument("--compact", action="store_true", help="also estimate compact encodings' cost")
    parser.add_argument("--keep-pcap", action="store_true", help="keep each run's capture (in --workdir)")
    parser.add_argument("--workdir", default=None, help="folder for logs (default: a temporary one)")
    parser.add_argument("--out", default=None, help="also write the JSON here")
    args = parser.parse_args()
    if args.command == "capture":
        capture(args.iface, args.out)
        return
    if args.command == "probe":
        probe(args.out)
        return
    from benchmarks.report import emit
    from tests.integration.netns import netns_unavailable

    why = netns_unavailable()
    if why:
        sys.exit(f"bandwidth: {why}")
    names = [n for n in args.variants.split(",") if n]
    unknown = [n for n in names if n not in VARIANTS and n not in PRESETS]
    if unknown:
        sys.exit(f"bandwidth: unknown variants {unknown}; known: {list(VARIANTS) + list(PRESETS)}")
    workdir = Path(args.workdir or tempfile.mkdtemp(prefix="bandwidth-"))
    compact = compact_estimate(args.rate) if args.compact else None
    runs = []

    def report() -> dict:
        return {"benchmark": "bandwidth", "target_bytes_per_s_per_robot": 5000, "workdir": str(workdir),
                "compact_encodings": compact, "runs": runs, "summary": summary_table(runs)}

    for robots in [int(n) for n in args.robots.split(",")]:
        chosen = [n for n in names if args.only is None or n in args.only.split(",")]
        for repeat, name in [(r, n) for r in range(args.repeat) for n in chosen]:  # ladders in turn: load drifts
            settings = variant_settings(names, name)
            folder = workdir / f"n{robots}-{name}-{repeat}"
            folder.mkdir(parents=True, exist_ok=True)
            try:
                result = {"variant": name, "settings": settings,
                          **run_once(robots, settings, folder, args.warmup_s, args.window_s, args.rate,
                                     args.keep_pcap, args.robot_duration_s)}
            except (AssertionError, subprocess.SubprocessError, OSError) as error:
                print(f"{name} x{robots}: failed: {error}", file=sys.stderr)
                runs.append({"variant": name, "robots": robots, "error": str(error)})
                continue
            if compact:
                result["per_robot_with_compact_payload"] = with_compact(result, compact)
            print(f"{name} x{robots}: {result['cable_bytes_per_s_per_robot']} B/s per robot "
                  f"{result['layers_per_robot']}", file=sys.stderr)
            runs.append(result)
            if args.out:  # what was measured so far, should a later run fail
                Path(args.out).parent.mkdir(parents=True, exist_ok=True)
                Path(args.out).write_text(json.dumps(report(), indent=2) + "\n")
    emit(report(), args.out)


def summary_table(runs: list[dict]) -> list[dict]:
    """Per robot count and variant: the median and range over the repeats of the per-robot cable bytes per
    second, and the median of each layer."""
    import statistics

    groups: dict[tuple[int, str], list[dict]] = defaultdict(list)
    for run in runs:
        if "error" not in run:
            groups[(run["robots"], run["variant"])].append(run)
    rows = []
    for (robots, variant), group in groups.items():
        values = [r["cable_bytes_per_s_per_robot"] for r in group]
        rows.append({"robots": robots, "variant": variant, "runs": len(group),
                     "per_robot_median": round(statistics.median(values), 1),
                     "per_robot_range": [round(min(values), 1), round(max(values), 1)],
                     "layers_median": {layer: round(statistics.median(r["layers_per_robot"][layer] for r in group), 1)
                                       for layer in group[0]["layers_per_robot"]},
                     "scans_sharing_a_batch_with_odometry": statistics.median(
                         r["scans_sharing_a_batch_with_odometry"] or 0 for r in group),
                     "central_msgs_per_s_of_expected": round(statistics.median(
                         r["central_msgs_per_s"] / r["expected_msgs_per_s"] for r in group), 3)})
    return rows


if __name__ == "__main__":
    main()
