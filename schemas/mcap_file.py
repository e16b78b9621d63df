"""Fleet recordings as MCAP files (the log format ROS 2 bags, Foxglove and Rerun read).

Layout (what :class:`RecordingWriter` writes and :func:`read_recording` expects):

- one channel per key expression, topic = the key, message encoding ``msgpack``,
  each message's data = the payload bytes as they crossed Zenoh;
- one schema per message model (name from :func:`schemas.codec.schema_name`,
  encoding ``jsonschema``: the codec envelope around the model's fields), and
  the generic ``UnknownPayload`` schema for keys fleetslam does not know;
- log_time = reception time, publish_time = the sample's Zenoh timestamp (the
  reception time when it has none), both ns since the UNIX epoch; sequence = the
  message's index on its channel;
- a metadata record ``fleetslam`` (format version, key prefix, start time, the
  fleetslam version) and, at the end, ``fleetslam.summary`` (counts per kind);
- zstd-compressed chunks, the summary section and the footer.

The writer writes to ``NAME.part`` and renames it to ``NAME`` once the footer
is written, so a file with the final name is always complete. The reader
refuses a missing, foreign, corrupt or unfinished file with one line
(:class:`~schemas.recording.RecordingError`).
"""

from __future__ import annotations

import os
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from mcap.reader import make_reader
from mcap.writer import MCAP0_MAGIC, CompressionType, Writer

from schemas.recording import (FORMAT_VERSION, MESSAGE_ENCODING, METADATA_NAME, SCHEMA_ENCODING, RecordedMessage,
                               RecordingError, schema_data, topic_kind, topic_model, topic_schema_name)

COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


def part_path(path: Path) -> Path:
    """Where a recording is written until it is complete."""
    return path.with_name(path.name + ".part")


class RecordingWriter:
    """Writes one recording of the keys under ``prefix``; :meth:`close` finishes it and gives it its name."""

    def __init__(self, path: str | Path, prefix: str, metadata: dict[str, str] | None = None,
                 compression: str = "zstd", library: str = "fleetslam"):
        self.path = Path(path)
        self.prefix = prefix
        self.messages = 0
        self.bytes = 0
        self.kinds: Counter = Counter()
        self.first_ns: int | None = None
        self.last_ns: int | None = None
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self._sequence: Counter = Counter()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._part = part_path(self.path)
        self._stream = open(self._part, "wb")
        self._writer = Writer(self._stream, compression=COMPRESSIONS[compression])
        self._writer.start(profile="", library=library)
        self._writer.add_metadata(METADATA_NAME, {"format_version": FORMAT_VERSION, "prefix": prefix,
                                                  **(metadata or {})})

    def _channel(self, topic: str) -> int:
        channel = self._channels.get(topic)
        if channel is None:
            name = topic_schema_name(self.prefix, topic)
            schema = self._schemas.get(name)
            if schema is None:
                schema = self._schemas[name] = self._writer.register_schema(
                    name, SCHEMA_ENCODING, schema_data(topic_model(self.prefix, topic)))
            channel = self._channels[topic] = self._writer.register_channel(topic, MESSAGE_ENCODING, schema)
        return channel

    def write(self, topic: str, data: bytes, log_time_ns: int, publish_time_ns: int | None = None) -> None:
        """Add one sample; log times never go backwards in the file (a clock step back is held at the last)."""
        log_time_ns = max(log_time_ns, self.last_ns or 0)
        channel = self._channel(topic)
        self._writer.add_message(channel, log_time=log_time_ns, data=data,
                                 publish_time=log_time_ns if publish_time_ns is None else publish_time_ns,
                                 sequence=self._sequence[topic])
        self._sequence[topic] += 1
        self.messages += 1
        self.bytes += len(data)
        self.kinds[topic_kind(self.prefix, topic)] += 1
        self.first_ns = log_time_ns if self.first_ns is None else self.first_ns
        self.last_ns = log_time_ns

    def close(self) -> Path:
        """Write the summary and footer, close, and rename the file to its final name."""
        self._writer.add_metadata(f"{METADATA_NAME}.summary", {
            "messages": str(self.messages), "bytes": str(self.bytes),
            **{f"kind.{kind}": str(n) for kind, n in sorted(self.kinds.items())}})
        self._writer.finish()
        self._stream.close()
        os.replace(self._part, self.path)
        return self.path

    def discard(self) -> None:
        """Close and remove the unfinished file (nothing was recorded)."""
        self._stream.close()
        self._part.unlink(missing_ok=True)


@dataclass
class Recording:
    """A recording read back: its metadata and every message in log-time order."""

    path: Path
    prefix: str
    metadata: dict[str, dict[str, str]]
    messages: list[RecordedMessage]
    schemas: dict[str, str] = field(default_factory=dict)  # topic -> schema name

    def kinds(self) -> Counter:
        return Counter(topic_kind(self.prefix, m.topic) for m in self.messages)


def _problem(exc: Exception) -> str:
    text = str(exc).splitlines()[0] if str(exc) else ""
    return f"{type(exc).__name__}{': ' + text if text else ''}"


def read_recording(path: str | Path) -> Recording:
    """Read a whole recording; :class:`RecordingError` (one line) if it is missing, foreign, corrupt or unfinished."""
    path = Path(path).expanduser()
    if not path.is_file():
        hint = f" (an unfinished recording is {part_path(path).name})" if part_path(path).is_file() else ""
        raise RecordingError(f"{path}: no such recording{hint}")
    with open(path, "rb") as stream:
        head = stream.read(len(MCAP0_MAGIC))
        if head != MCAP0_MAGIC:
            what = "empty" if not head else "does not start with the MCAP magic bytes"
            raise RecordingError(f"{path}: not an MCAP file ({what})")
        stream.seek(-len(MCAP0_MAGIC), os.SEEK_END)
        if stream.tell() < len(MCAP0_MAGIC) or stream.read() != MCAP0_MAGIC:
            raise RecordingError(f"{path}: truncated or unfinished: it does not end with the MCAP magic bytes "
                                 "(the recording did not finish)")
        stream.seek(0)
        try:
            reader = make_reader(stream, validate_crcs=True)
            reader.get_header()
        except Exception as exc:  # noqa: BLE001 - the mcap reader raises many types on foreign bytes
            raise RecordingError(f"{path}: not an MCAP file ({_problem(exc)})") from None
        try:
            summary = reader.get_summary()
        except Exception as exc:  # noqa: BLE001
            raise RecordingError(f"{path}: truncated or unfinished: no valid MCAP footer ({_problem(exc)})") from None
        if summary is None:
            raise RecordingError(f"{path}: the MCAP file has no summary section (not written by fleetslam record)")
        try:
            metadata = {record.name: dict(record.metadata) for record in reader.iter_metadata()}
        except Exception as exc:  # noqa: BLE001
            raise RecordingError(f"{path}: corrupt metadata ({_problem(exc)})") from None
        info = metadata.get(METADATA_NAME)
        if info is None:
            raise RecordingError(f"{path}: not a fleetslam recording (no '{METADATA_NAME}' metadata record)")
        if info.get("format_version") != FORMAT_VERSION:
            raise RecordingError(f"{path}: recording format version {info.get('format_version')!r} is not supported "
                                 f"(this fleetslam reads version {FORMAT_VERSION})")
        prefix = info.get("prefix", "")
        if not re.fullmatch(r"[A-Za-z0-9_-]+", prefix):
            raise RecordingError(f"{path}: the recording's key prefix {prefix!r} is not a valid prefix")
        foreign = sorted({c.message_encoding for c in summary.channels.values()} - {MESSAGE_ENCODING})
        if foreign:
            raise RecordingError(f"{path}: message encoding {', '.join(foreign)} is not {MESSAGE_ENCODING}")
        messages: list[RecordedMessage] = []
        try:
            for _, channel, message in reader.iter_messages(log_time_order=True):
                messages.append(RecordedMessage(channel.topic, message.log_time, message.publish_time,
                                                bytes(message.data)))
        except Exception as exc:  # noqa: BLE001 - a bad CRC, a broken chunk, bad compression
            raise RecordingError(f"{path}: corrupt data after {len(messages)} messages ({_problem(exc)})") from None
    expected = summary.statistics.message_count if summary.statistics is not None else len(messages)
    if len(messages) != expected:
        raise RecordingError(f"{path}: corrupt: {len(messages)} messages readable, the summary counts {expected}")
    schemas = {c.topic: summary.schemas[c.schema_id].name if c.schema_id in summary.schemas else ""
               for c in summary.channels.values()}
    return Recording(path=path, prefix=prefix, metadata=metadata, messages=messages, schemas=schemas)
