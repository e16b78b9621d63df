"""A TCP relay that makes one link slow and lossy, for kernels without ``tc netem`` (this machine's: "Specified
qdisc kind is unknown").

A site's router connects to the relay instead of to the depot's router; the relay connects on to the depot's
router and copies the bytes both ways, each chunk (what one ``recv`` returned) held back before it is sent on:

- by ``delay_ms`` ± ``jitter_ms`` (uniform), counted from when it arrived, but never before the chunk ahead of it
  went: a TCP stream keeps its order, so jitter delays what follows rather than overtaking it (netem on a TCP flow
  gives the same: a late segment holds the ones after it back from the application);
- on a random ``stall_probability`` of the chunks, by ``stall_ms`` more, and everything behind it with it: what a
  lost segment costs a TCP stream (nothing is lost, the stream stops until the retransmission, a timeout of about
  200 ms on Linux, then what waited behind it goes at once; stalls that overlap do not add up). A chunk stands for
  a packet: at a robot's 10 Hz a chunk is one or two messages.

Each direction of each connection draws from its own generator, seeded by (``seed``, connection number,
direction), so a run with the same seed and the same chunks is shaped the same. Connections close as TCP's do: an
end of stream is passed on once what came before it has gone (half close), a reset closes both sides.

Cutting the cable still cuts: the relay does not hide a cut, the site's packets vanish before they reach it.

    python -m tests.integration.linkrelay --listen 0.0.0.0:7448 --to 127.0.0.1:7447 --seed 1

prints ``CONNECTION {n} from {address} at {unix time}`` for each connection it relays, runs until SIGTERM or SIGINT,
then prints one line ``LINKRELAY {json}``: connections, chunks, bytes, stalls and the delays measured per direction
(``up``: from the connecting side, ``down``: towards it).
"""

from __future__ import annotations

import argparse
import json
import math
import queue
import signal
import socket
import threading
import time
from dataclasses import asdict, dataclass

import numpy as np

CHUNK_BYTES = 65536
DIRECTIONS = ("up", "down")  # up: from the side that connected to the relay to the target; down: back


@dataclass(frozen=True)
class Shape:
    """How one link is shaped, in each direction."""

    delay_ms: float = 40.0
    jitter_ms: float = 10.0
    stall_probability: float = 0.01
    stall_ms: float = 200.0

    def __post_init__(self):
        if not (0 <= self.jitter_ms <= self.delay_ms and 0 <= self.stall_probability <= 1 and self.stall_ms >= 0):
            raise ValueError(f"a shape needs 0 <= jitter <= delay, a probability and a stall >= 0: {self}")


class Shaper:
    """When each chunk of one direction goes out (pure: no sockets, no clock of its own)."""

    def __init__(self, shape: Shape, rng: np.random.Generator):
        self.shape = shape
        self.rng = rng
        self.chunks = 0
        self.stalls = 0
        self._last = -math.inf

    def release_at(self, arrived: float) -> float:
        """The time (the caller's clock, seconds) to send on a chunk that arrived at ``arrived``. Two draws per
        chunk, always: the decisions depend on the chunk's number only."""
        jitter, draw = self.rng.uniform(-1.0, 1.0), self.rng.random()
        delay_ms = self.shape.delay_ms + jitter * self.shape.jitter_ms
        if draw < self.shape.stall_probability:
            delay_ms += self.shape.stall_ms
            self.stalls += 1
        self.chunks += 1
        self._last = max(arrived + delay_ms / 1e3, self._last)
        return self._last


class _Direction:
    """One direction of one relayed connection: a reader that stamps and schedules chunks, a writer that sends
    each at its time."""

    def __init__(self, relay: "LinkRelay", source: socket.socket, sink: socket.socket, shaper: Shaper, name: str,
                 done: threading.Barrier):
        self.relay, self.source, self.sink, self.shaper, self.name, self.done = relay, source, sink, shaper, name, done
        self.chunks: queue.Queue = queue.Queue()
        self.threads = [threading.Thread(target=self._read, daemon=True, name=f"relay-{name}-read"),
                        threading.Thread(target=self._write, daemon=True, name=f"relay-{name}-write")]

    def start(self) -> None:
        for thread in self.threads:
            thread.start()

    def _read(self) -> None:
        while True:
            try:
                data = self.source.recv(CHUNK_BYTES)
            except OSError:
                data = None  # reset, or closed by the other direction
            arrived = time.monotonic()
            if not data:
                self.chunks.put((arrived, None, data is None))
                return
            with self.relay.lock:
                at = self.shaper.release_at(arrived)
            self.chunks.put((arrived, at, data))

    def _write(self) -> None:
        stop = self.relay.stopped
        while not stop.is_set():
            arrived, at, data = self.chunks.get()
            if at is None:  # end of stream: passed on after what came before it
                if data:  # an error: both sides go
                    self.relay.close_pair(self.source, self.sink)
                else:
                    try:
                        self.sink.shutdown(socket.SHUT_WR)
                    except OSError:
                        pass
                break
            if stop.wait(max(0.0, at - time.monotonic())):  # paced: the chunk is held until its time
                break
            try:
                self.sink.sendall(data)
            except OSError:
                self.relay.close_pair(self.source, self.sink)
                break
            self.relay.sent(self.name, len(data), time.monotonic() - arrived)
        try:
            self.done.wait(timeout=None if not stop.is_set() else 0)
        except threading.BrokenBarrierError:
            return
        self.relay.close_pair(self.source, self.sink)  # both directions ended: the pair closes


class LinkRelay:
    """Accepts on ``listen`` and relays each connection to ``target``, shaped by ``shape`` (see the module doc)."""

    def __init__(self, listen: tuple[str, int], target: tuple[str, int], shape: Shape = Shape(), seed: int = 0):
        self.target, self.shape, self.seed = target, shape, seed
        self.on_connection = None  # called with (number, peer address) when a connection is relayed
        self.lock = threading.Lock()
        self.stopped = threading.Event()
        self.connections = 0
        self.failed_connects = 0
        self.shapers: list[tuple[str, Shaper]] = []
        self.counts = {name: {"chunks_sent": 0, "bytes": 0, "delay_ms_sum": 0.0, "delay_ms_max": 0.0,
                              "delay_ms_min": math.inf} for name in DIRECTIONS}
        self._sockets: list[socket.socket] = []
        self.server = socket.create_server(listen, reuse_port=False)
        self.server.settimeout(0.2)
        self._accepting = threading.Thread(target=self._accept, daemon=True, name="relay-accept")

    @property
    def port(self) -> int:
        return self.server.getsockname()[1]

    def start(self) -> "LinkRelay":
        self._accepting.start()
        return self

    def _accept(self) -> None:
        while not self.stopped.is_set():
            try:
                near, _ = self.server.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            try:
                far = socket.create_connection(self.target, timeout=5.0)
            except OSError:
                near.close()
                with self.lock:
                    self.failed_connects += 1
                continue
            for sock in (near, far):
                sock.settimeout(None)
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self.lock:
                number = self.connections
                self.connections += 1
                self._sockets += [near, far]
            if self.on_connection is not None:
                self.on_connection(number, near.getpeername())
            done = threading.Barrier(2)
            for index, (name, source, sink) in enumerate((("up", near, far), ("down", far, near))):
                shaper = Shaper(self.shape, np.random.default_rng([self.seed, number, index]))
                with self.lock:
                    self.shapers.append((name, shaper))
                _Direction(self, source, sink, shaper, name, done).start()

    def close_pair(self, *sockets: socket.socket) -> None:
        for sock in sockets:
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            sock.close()

    def sent(self, name: str, nbytes: int, delay_s: float) -> None:
        with self.lock:
            count = self.counts[name]
            count["chunks_sent"] += 1
            count["bytes"] += nbytes
            count["delay_ms_sum"] += delay_s * 1e3
            count["delay_ms_max"] = max(count["delay_ms_max"], delay_s * 1e3)
            count["delay_ms_min"] = min(count["delay_ms_min"], delay_s * 1e3)

    def stats(self) -> dict:
        """What was relayed so far, per direction, with the shaper's decisions."""
        with self.lock:
            out = {"shape": asdict(self.shape), "seed": self.seed, "connections": self.connections,
                   "failed_connects": self.failed_connects}
            for name in DIRECTIONS:
                count = dict(self.counts[name])
                sent = count["chunks_sent"]
                count["delay_ms_mean"] = round(count.pop("delay_ms_sum") / sent, 2) if sent else None
                count["delay_ms_min"] = round(count["delay_ms_min"], 2) if sent else None
                count["delay_ms_max"] = round(count["delay_ms_max"], 2)
                shapers = [shaper for direction, shaper in self.shapers if direction == name]
                count["chunks"] = sum(s.chunks for s in shapers)
                count["stalls"] = sum(s.stalls for s in shapers)
                out[name] = count
        return out

    def close(self) -> None:
        self.stopped.set()
        self.server.close()
        self._accepting.join(timeout=2.0)
        with self.lock:
            sockets = list(self._sockets)
        self.close_pair(*sockets)


def _address(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    return host or "0.0.0.0", int(port)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--listen", type=_address, required=True, help="HOST:PORT to accept on")
    parser.add_argument("--to", type=_address, required=True, help="HOST:PORT to relay each connection to")
    parser.add_argument("--delay-ms", type=float, default=Shape.delay_ms)
    parser.add_argument("--jitter-ms", type=float, default=Shape.jitter_ms)
    parser.add_argument("--stall-probability", type=float, default=Shape.stall_probability)
    parser.add_argument("--stall-ms", type=float, default=Shape.stall_ms)
    parser.add_argument("--seed", type=int, required=True)
    args = parser.parse_args()
    shape = Shape(args.delay_ms, args.jitter_ms, args.stall_probability, args.stall_ms)
    relay = LinkRelay(args.listen, args.to, shape, args.seed)
    relay.on_connection = lambda number, peer: print(
        f"CONNECTION {number} from {peer[0]}:{peer[1]} at {time.time():.3f}", flush=True)
    relay.start()
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    print(f"relaying {args.listen[0]}:{relay.port} -> {args.to[0]}:{args.to[1]}, {shape}, seed {args.seed}", flush=True)
    while not stop.wait(1.0):  # until a signal
        pass
    relay.close()
    print("LINKRELAY " + json.dumps(relay.stats()), flush=True)


if __name__ == "__main__":
    main()
