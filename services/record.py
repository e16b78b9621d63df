"""``fleetslam record``: every sample under the key prefix, written to an MCAP file.

It subscribes ``{prefix}/**`` and writes each sample as it arrives (topic =
key, payload unchanged, log time = reception time, publish time = the
sample's Zenoh timestamp; the layout is in :mod:`schemas.mcap_file`). The
Zenoh callback only queues the sample; the main thread writes. Progress
(samples, bytes, counts per kind) goes to the log, and its stats to
``{prefix}/record/stats`` like a service's. On SIGINT/SIGTERM or after
``--duration`` it stops subscribing, writes what is queued, finishes the file
(summary and footer) and renames ``FILE.part`` to ``FILE``. Liveliness tokens
and queries are not samples and are not recorded.
"""

from __future__ import annotations

import argparse
import logging
import os
import queue
import time
from datetime import datetime, timezone
from pathlib import Path

import zenoh

from schemas.config import RecordSettings, add_settings_arguments, settings_from_args
from schemas.keys import Keys
from schemas.mcap_file import RecordingWriter
from schemas.messages import ServiceStats
from schemas.transport import Shutdown, StreamPublisher, run_command, session_scope
from services.cli import package_version

log = logging.getLogger("fleetslam.record")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, RecordSettings)


def default_out(prefix: str, now: datetime) -> str:
    return f"recordings/{prefix}-{now:%Y%m%d-%H%M%S}.mcap"


def describe(writer: RecordingWriter) -> str:
    """``N samples, X MB (odom a, scan b, ...)``: the progress line's figures."""
    kinds = ", ".join(f"{kind} {n}" for kind, n in sorted(writer.kinds.items()))
    return f"{writer.messages} samples, {writer.bytes / 1e6:.2f} MB" + (f" ({kinds})" if kinds else "")


class Recorder:
    """Queues samples from Zenoh's callback thread; :meth:`write_queued` writes them from the main thread."""

    def __init__(self, writer: RecordingWriter):
        self.writer = writer
        self.started = time.monotonic()
        self._queue: queue.SimpleQueue = queue.SimpleQueue()

    def on_sample(self, sample: zenoh.Sample) -> None:
        stamp = sample.timestamp
        published = stamp.get_time_as_ntp64().as_nanos() if stamp is not None else None
        self._queue.put((str(sample.key_expr), sample.payload.to_bytes(), time.time_ns(), published))

    def write_queued(self, wait_s: float) -> int:
        """Write every queued sample (waiting up to ``wait_s`` for the first); the number written."""
        written = 0
        try:
            item = self._queue.get(timeout=wait_s) if wait_s > 0 else self._queue.get_nowait()
            while True:
                self.writer.write(*item)
                written += 1
                item = self._queue.get_nowait()
        except queue.Empty:
            return written

    def stats(self, instance: str) -> ServiceStats:
        return ServiceStats(service="record", instance=instance, stamp=time.time(),
                            uptime_s=time.monotonic() - self.started, messages_in=dict(self.writer.kinds),
                            extra={"bytes": float(self.writer.bytes), "samples": float(self.writer.messages)})


def run(settings: RecordSettings, shutdown: Shutdown) -> Path:
    """Record until a signal or ``settings.duration``; the finished file's path."""
    keys = Keys(settings.prefix)
    started = datetime.now(timezone.utc)
    out = Path(settings.out or default_out(settings.prefix, started.astimezone()))
    writer = RecordingWriter(out, settings.prefix, compression=settings.compression,
                             metadata={"started": started.isoformat(), "fleetslam_version": package_version()},
                             library=f"fleetslam {package_version()}")
    recorder = Recorder(writer)
    instance = f"record-{os.getpid()}"
    try:
        with session_scope(settings) as session:
            # the fleet's samples, not this process's own stats: a callback fed by our own puts is a lock cycle
            # waiting to happen (zenoh delivers local samples on the publishing thread)
            subscriber = session.declare_subscriber(keys.everything, recorder.on_sample,
                                                    allowed_origin=zenoh.Locality.REMOTE)
            stats = StreamPublisher(session, keys.stats("record"))
            log.info("recording %s to %s (Ctrl-C stops and finishes the file)", keys.everything, writer.path)
            begin = time.monotonic()
            deadline = begin + settings.duration if settings.duration else None
            next_progress = begin + settings.progress_period_s
            next_stats = begin
            try:
                while not shutdown.is_set() and (deadline is None or time.monotonic() < deadline):
                    recorder.write_queued(0.1)
                    now = time.monotonic()
                    if now >= next_stats:
                        stats.put(recorder.stats(instance))
                        next_stats = now + settings.stats_period_s
                    if now >= next_progress:
                        log.info("recording: %s", describe(writer))
                        next_progress = now + settings.progress_period_s
            finally:
                subscriber.undeclare()
                recorder.write_queued(0)
                stats.put(recorder.stats(instance))
                stats.undeclare()
    except BaseException:
        if writer.messages:
            writer.close()
            log.warning("recording stopped by an error; what was recorded is in %s", writer.path)
        else:
            writer.discard()
        raise
    path = writer.close()
    why = shutdown.signal_name or ("duration" if settings.duration else "stop")
    log.info("recorded %s in %.1f s (%s); file: %s", describe(writer), time.monotonic() - recorder.started, why, path)
    return path


def main(args: argparse.Namespace) -> int:
    return run_command(run, settings_from_args(RecordSettings, args), log, "cannot record", (OSError,))
