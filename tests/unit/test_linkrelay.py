"""The relay that shapes the multi-site test's links where the kernel has no ``tc netem``
(tests/integration/linkrelay.py): every chunk is held 40 ± 10 ms, the stream keeps its order, and a seeded share of
the chunks stalls the stream for a retransmission timeout."""

from __future__ import annotations

import socket
import struct
import threading
import time

import numpy as np
import pytest

from tests.integration.linkrelay import LinkRelay, Shape, Shaper

SHAPE = Shape(delay_ms=40.0, jitter_ms=10.0, stall_probability=0.01, stall_ms=200.0)


def test_shaper_delays_by_40_plus_minus_10_ms_keeps_order_and_stalls_1_percent_of_chunks():
    shaper = Shaper(SHAPE, np.random.default_rng([7, 0, 0]))
    arrivals = np.arange(20_000) * 1.0  # a second apart: no chunk waits for the one ahead
    release = np.array([shaper.release_at(t) for t in arrivals])
    delays_ms = (release - arrivals) * 1e3
    stalled = delays_ms > 100.0
    assert np.all(np.diff(release) >= 0)
    assert 30.0 <= delays_ms[~stalled].min() < 31.0 and 49.0 < delays_ms[~stalled].max() <= 50.0
    assert abs(np.median(delays_ms[~stalled]) - 40.0) < 0.5
    assert np.all((delays_ms[stalled] >= 230.0) & (delays_ms[stalled] <= 250.0))
    assert shaper.stalls == stalled.sum() and shaper.chunks == arrivals.size
    assert 140 <= shaper.stalls <= 260  # binomial(20000, 1 %): 200 ± 14
    again = Shaper(SHAPE, np.random.default_rng([7, 0, 0]))
    assert [again.release_at(t) for t in arrivals[:500]] == release[:500].tolist()  # seeded: the same decisions


def test_shaper_holds_what_follows_a_late_or_stalled_chunk_back_in_order():
    shaper = Shaper(Shape(delay_ms=40.0, jitter_ms=10.0, stall_probability=0.5, stall_ms=200.0),
                    np.random.default_rng(3))
    arrivals = np.arange(400) * 0.001  # a millisecond apart: jitter and stalls would reorder them
    release = np.array([shaper.release_at(t) for t in arrivals])
    assert np.all(np.diff(release) >= 0)
    assert np.all(release - arrivals >= 0.030)
    assert 150 <= shaper.stalls <= 250


def test_shape_is_checked():
    with pytest.raises(ValueError):
        Shape(delay_ms=5.0, jitter_ms=10.0)
    with pytest.raises(ValueError):
        Shape(stall_probability=1.5)


class Sink:
    """A TCP server that records, for each 8-byte sequence number it receives, when it came."""

    def __init__(self):
        self.server = socket.create_server(("127.0.0.1", 0))
        self.received: list[tuple[int, float]] = []
        self.closed = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        conn, _ = self.server.accept()
        buffer = b""
        with conn:
            while data := conn.recv(65536):
                now = time.monotonic()
                buffer += data
                while len(buffer) >= 16:
                    seq, _pad = struct.unpack("<qq", buffer[:16])
                    buffer = buffer[16:]
                    self.received.append((seq, now))
        self.closed.set()


def test_relay_delays_every_chunk_keeps_the_stream_in_order_and_stalls_at_the_seeded_rate():
    sink = Sink()
    shape = Shape(delay_ms=40.0, jitter_ms=10.0, stall_probability=0.05, stall_ms=200.0)
    relay = LinkRelay(("127.0.0.1", 0), sink.server.getsockname(), shape, seed=11).start()
    pace = threading.Event()  # never set: waits on it pace the sender
    sent_at: list[float] = []
    try:
        with socket.create_connection(("127.0.0.1", relay.port)) as client:
            client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            for seq in range(200):
                sent_at.append(time.monotonic())
                client.sendall(struct.pack("<qq", seq, 0))
                pace.wait(0.01)  # pacing: one message every 10 ms, a robot stream's rate
        assert sink.closed.wait(30.0), "the end of stream did not come through the relay"
    finally:
        relay.close()
    seqs = [seq for seq, _ in sink.received]
    assert seqs == list(range(200)), "not every message once and in order"
    delays_ms = np.array([(at - sent_at[seq]) * 1e3 for seq, at in sink.received])
    assert delays_ms.min() >= 29.0, delays_ms.min()  # no chunk goes before its 40 - 10 ms
    assert np.percentile(delays_ms, 10) < 80.0  # most go soon after (a loaded machine adds to it)
    stats = relay.stats()
    up = stats["up"]
    assert up["chunks"] >= 100 and up["chunks_sent"] == up["chunks"] and up["bytes"] == 200 * 16
    # 5 % of the chunks stalled the stream by 200 ms; a stall holds its chunk and those behind it
    assert 0.01 * up["chunks"] <= up["stalls"] <= 0.12 * up["chunks"], up
    assert (delays_ms >= 230.0).sum() >= up["stalls"], (up, np.sort(delays_ms)[-20:])
    replayed = Shaper(shape, np.random.default_rng([11, 0, 0]))  # the relay's first connection, upwards
    for _ in range(up["chunks"]):
        replayed.release_at(0.0)
    assert up["stalls"] == replayed.stalls  # the stalls are the seed's: the same chunks stall in every run
