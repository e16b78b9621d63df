"""Crash-safe checkpoints of a service's whole state, written atomically (no Zenoh, no numerics here).

A checkpoint file is one line of magic, one line of JSON header (format, service, creation time, payload size and
SHA-256, a short summary) and the payload: the state pickled. It is written to a temporary file in the same folder,
fsynced, renamed into place and the folder fsynced, so a crash at any moment leaves either the previous checkpoint
or the new one, never half of one. Files are numbered (``central-00000042.ckpt``); the newest ``keep`` stay.

:meth:`CheckpointStore.load` returns the newest checkpoint that reads back whole: a truncated, corrupt or foreign
file is refused with its reason (logged and kept in :attr:`CheckpointStore.refused`) and the one before it is used.
The state is pickled: a checkpoint folder must be as trusted as the service's own code (it is the service's own).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import pickle
import re
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

MAGIC = b"fleetslam-checkpoint\n"
FORMAT = 2  # 2: the reorder buffer breaks stamp ties by robot id and waits for announced robots


class CheckpointError(ValueError):
    """A checkpoint file that cannot be used; the message says why."""


@dataclass
class Checkpoint:
    """A checkpoint read back: its file, header and state."""

    path: Path
    header: dict
    state: Any

    @property
    def age_s(self) -> float:
        return time.time() - float(self.header.get("created", 0.0))


def encode_checkpoint(service: str, state: Any, summary: dict | None = None) -> bytes:
    """The bytes of a checkpoint of ``state`` (pickled) for ``service``."""
    payload = pickle.dumps(state, protocol=pickle.HIGHEST_PROTOCOL)
    header = {"format": FORMAT, "service": service, "created": time.time(), "bytes": len(payload),
              "sha256": hashlib.sha256(payload).hexdigest(), "summary": summary or {}}
    return MAGIC + json.dumps(header).encode() + b"\n" + payload


def decode_checkpoint(data: bytes, service: str) -> tuple[dict, Any]:
    """(header, state) of a checkpoint's bytes; :class:`CheckpointError` says why they cannot be used."""
    if not data.startswith(MAGIC):
        raise CheckpointError("not a fleetslam checkpoint (no magic line)")
    end = data.find(b"\n", len(MAGIC))
    if end < 0:
        raise CheckpointError("truncated in its header")
    try:
        header = json.loads(data[len(MAGIC):end])
    except ValueError as exc:
        raise CheckpointError(f"unreadable header ({exc})") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise CheckpointError(f"format {header.get('format') if isinstance(header, dict) else '?'}; this "
                              f"fleetslam reads format {FORMAT}")
    if header.get("service") != service:
        raise CheckpointError(f"written by the {header.get('service')!r} service, not {service!r}")
    payload = data[end + 1:]
    if len(payload) != header.get("bytes"):
        raise CheckpointError(f"truncated: {len(payload)} of {header.get('bytes')} payload bytes")
    if hashlib.sha256(payload).hexdigest() != header.get("sha256"):
        raise CheckpointError("corrupt: its payload does not match its SHA-256")
    try:
        state = pickle.loads(payload)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure is a refusal with its reason
        raise CheckpointError(f"its state does not load ({type(exc).__name__}: {exc})") from None
    return header, state


def write_atomically(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path``: temporary file, fsync, rename, fsync of the folder."""
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as handle:
        handle.write(data)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(tmp, path)
    folder = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(folder)
    finally:
        os.close(folder)


@dataclass
class CheckpointStore:
    """The numbered checkpoints of one service in one folder."""

    directory: Path
    service: str
    keep: int = 3
    refused: list[tuple[str, str]] = field(default_factory=list)  # (file name, reason) of files load() passed over

    def __post_init__(self) -> None:
        self.directory = Path(self.directory)
        self._pattern = re.compile(rf"^{re.escape(self.service)}-(\d+)\.ckpt$")
        self._number = max((n for n, _ in self._files()), default=0)
        self._lock = threading.Lock()  # a periodic save still running in its thread and the final one

    def _files(self) -> list[tuple[int, Path]]:
        """(number, path) of this service's checkpoint files, newest first."""
        if not self.directory.is_dir():
            return []
        found = [(int(m.group(1)), p) for p in self.directory.iterdir() if (m := self._pattern.match(p.name))]
        return sorted(found, reverse=True)

    def save(self, data: bytes) -> Path:
        """Write an encoded checkpoint (:func:`encode_checkpoint`) as the newest; older ones past ``keep`` go."""
        with self._lock:
            self.directory.mkdir(parents=True, exist_ok=True)
            self._number += 1
            path = self.directory / f"{self.service}-{self._number:08d}.ckpt"
            write_atomically(path, data)
            for _, old in self._files()[self.keep:]:
                old.unlink(missing_ok=True)
            return path

    def load(self) -> Checkpoint | None:
        """The newest checkpoint that reads back whole, or None; each file refused on the way is logged."""
        self.refused = []
        for _, path in self._files():
            try:
                header, state = decode_checkpoint(path.read_bytes(), self.service)
            except (OSError, CheckpointError) as exc:
                self.refused.append((path.name, str(exc)))
                log.warning("checkpoint %s refused: %s; trying the one before it", path, exc)
                continue
            return Checkpoint(path, header, state)
        return None
