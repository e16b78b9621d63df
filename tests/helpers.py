"""Helpers for tests that run real processes over a real Zenoh router.

Nothing here sleeps and hopes: every wait is on a condition with a deadline.
"""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Callable

import zenoh

from schemas.codec import decode
from schemas.config import FleetSettings
from schemas.transport import open_session

REPO = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_until(predicate: Callable[[], object], timeout: float, interval: float = 0.02, what: str = "condition"):
    """Poll ``predicate`` until it returns a truthy value; fail after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(interval)


def wait_for_port(port: int, timeout: float = 10.0, host: str = "127.0.0.1") -> None:
    def listening() -> bool:
        try:
            with socket.create_connection((host, port), timeout=0.2):
                return True
        except OSError:
            return False

    wait_until(listening, timeout, 0.02, f"a listener on {host}:{port}")


class Processes:
    """Starts ``fleetslam`` commands as real OS processes and stops them all at the end."""

    def __init__(self, log_dir: Path, env: dict[str, str]):
        self.log_dir = log_dir
        self.env = env
        self.started: list[tuple[str, subprocess.Popen]] = []

    def start(self, name: str, *words: str, env: dict[str, str] | None = None) -> subprocess.Popen:
        log_path = self.log_dir / f"{name}.log"
        handle = open(log_path, "w")
        process = subprocess.Popen(
            [sys.executable, "-m", "services.cli", *words],
            env={**self.env, **(env or {})}, stdout=handle, stderr=subprocess.STDOUT, cwd=REPO,
        )
        self.started.append((name, process))
        return process

    def log(self, name: str) -> str:
        path = self.log_dir / f"{name}.log"
        return path.read_text() if path.exists() else ""

    def stop(self, process: subprocess.Popen, sig: int = signal.SIGTERM, timeout: float = 10.0) -> float:
        """Signal and wait; return the seconds it took to exit (kill after ``timeout``, once its threads' stacks are
        in its log)."""
        started = time.monotonic()
        if process.poll() is None:
            process.send_signal(sig)
        try:
            process.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self._kill(process)
        return time.monotonic() - started

    @staticmethod
    def _kill(process: subprocess.Popen) -> None:
        """SIGKILL a process that hangs, after asking it where its threads are (``fleetslam`` dumps them on SIGUSR1)."""
        process.send_signal(signal.SIGUSR1)
        try:
            process.wait(timeout=1.0)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()

    def stop_all(self) -> None:
        for _, process in reversed(self.started):
            if process.poll() is None:
                process.send_signal(signal.SIGTERM)
        for _, process in reversed(self.started):
            try:
                process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self._kill(process)


class Collector:
    """Subscribes a key expression and keeps every sample (key, payload), thread-safely."""

    def __init__(self, session: zenoh.Session, key: str):
        self._lock = threading.Lock()
        self.samples: list[tuple[str, bytes]] = []
        self._subscriber = session.declare_subscriber(key, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.samples.append((str(sample.key_expr), sample.payload.to_bytes()))

    def snapshot(self) -> list[tuple[str, bytes]]:
        with self._lock:
            return list(self.samples)

    def decoded(self, model, key_filter: Callable[[str], bool] = lambda k: True) -> list:
        return [decode(p, model) for k, p in self.snapshot() if key_filter(k)]

    def count(self, key_filter: Callable[[str], bool] = lambda k: True) -> int:
        return sum(1 for k, _ in self.snapshot() if key_filter(k))

    def undeclare(self) -> None:
        self._subscriber.undeclare()


def put_until_seen(session: zenoh.Session, key: str, payload: bytes, seen: Collector, timeout: float = 10.0) -> None:
    """Put ``payload`` on ``key`` every 0.2 s until ``seen`` holds it: a single put is lost while the router has
    not yet learnt of the subscriber, and on a loaded machine that can take seconds."""
    wait_until(lambda: (session.put(key, payload), (key, payload) in seen.snapshot())[1], timeout, 0.2,
               what=f"{payload!r} on {key}")


def client_session(endpoint: str) -> zenoh.Session:
    return open_session(FleetSettings(zenoh_connect=endpoint, connect_timeout_s=10.0))


class Asked:
    """Replies to one query sent without waiting: each (ok, payload, seconds after sending) as it comes, and when the
    query ended."""

    def __init__(self, session: zenoh.Session, key: str, payload: bytes | None, timeout: float = 20.0):
        self.replies: list[tuple[bool, bytes, float]] = []
        self.ended = threading.Event()
        self.sent = time.monotonic()
        session.get(key, zenoh.handlers.Callback(self._on_reply, self.ended.set), payload=payload, timeout=timeout)

    def _on_reply(self, reply: zenoh.Reply) -> None:
        late = time.monotonic() - self.sent
        if reply.ok is not None:
            self.replies.append((True, reply.ok.payload.to_bytes(), late))
        else:
            self.replies.append((False, reply.err.payload.to_bytes(), late))

    def one(self, within: float = 20.0) -> tuple[bool, bytes, float]:
        """The query's only reply, once the query ended."""
        assert self.ended.wait(within), "the query never ended"
        assert len(self.replies) == 1, self.replies
        return self.replies[0]
