"""Zenoh plumbing shared by every process: config, session, publishers, shutdown.

- :func:`zenoh_config` builds a client (or router) config: multicast scouting
  off, bounded wait for the router, optional user/password and TLS.
- :func:`open_session` opens it and turns a timeout into :class:`ConnectError`
  with the endpoint in the message.
- :class:`StreamPublisher` publishes messages reliably with congestion control
  BLOCK (the default DROP loses a flood), optionally through an advanced
  publisher whose cache lets late or cut-off subscribers recover.
- :class:`Shutdown` turns SIGINT/SIGTERM into an event so every process closes
  its session (a session with Python callbacks hangs at exit unless closed).
"""

from __future__ import annotations

import json
import logging
import math
import re
import signal
import threading
import time
from collections import deque
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterable, Iterator

import zenoh
import zenoh.ext
from pydantic import BaseModel

from schemas.codec import encode
from schemas.config import FleetSettings, RouterSettings

log = logging.getLogger(__name__)


class ConnectError(RuntimeError):
    """The router could not be reached in time."""


def _endpoints(text: str) -> list[str]:
    return [e.strip() for e in text.split(",") if e.strip()]


def zenoh_config(
    settings: FleetSettings, mode: str = "client", listen: str | None = None, base_file: str | None = None,
    routers: str | None = None,
) -> zenoh.Config:
    """A Zenoh config for ``mode`` ("client", "peer" or "router") from the shared settings.

    ``base_file`` is a JSON5 zenoh config (access control, users, TLS) that the
    settings are laid over. ``routers`` (router mode): the other routers this one connects to, comma-separated;
    it starts without them and keeps trying (every second at most), so sites come up in any order.
    A router (``settings`` a :class:`RouterSettings`) also stamps samples or not (``router_timestamps``) and
    offers compression on its links (``link_compression``).
    """
    conf = zenoh.Config.from_file(base_file) if base_file else zenoh.Config()
    entries: dict[str, object] = {
        "mode": mode,
        "scouting/multicast/enabled": False,
        "scouting/delay": 0,
    }
    if mode == "router":
        entries["listen/endpoints"] = _endpoints(listen or "tcp/0.0.0.0:7447")
        if isinstance(settings, RouterSettings):
            entries["timestamping/enabled"] = settings.router_timestamps
            entries["transport/unicast/compression/enabled"] = settings.link_compression
        if routers:
            entries["connect/endpoints"] = _endpoints(routers)
            entries["connect/timeout_ms"] = -1  # keep trying (in the background: the router serves meanwhile)
            entries["connect/exit_on_failure"] = False
            entries["connect/retry"] = {"period_init_ms": 100, "period_max_ms": 1000, "period_increase_factor": 1.5}
    else:
        entries["connect/endpoints"] = _endpoints(settings.zenoh_connect)
        entries["connect/timeout_ms"] = int(settings.connect_timeout_s * 1000)
        entries["connect/exit_on_failure"] = True
        entries["connect/retry"] = {"period_init_ms": 100, "period_max_ms": 1000, "period_increase_factor": 1.5}
    password = settings.zenoh_password
    if settings.zenoh_password_file:
        password = Path(settings.zenoh_password_file).read_text().strip()
    if settings.zenoh_user and password is not None:
        entries["transport/auth/usrpwd/user"] = settings.zenoh_user
        entries["transport/auth/usrpwd/password"] = password
    if settings.tls_root_ca:
        entries["transport/link/tls/root_ca_certificate"] = settings.tls_root_ca
    if settings.tls_cert and settings.tls_key:
        entries["transport/link/tls/enable_mtls"] = True
        entries["transport/link/tls/connect_certificate"] = settings.tls_cert
        entries["transport/link/tls/connect_private_key"] = settings.tls_key
    for key, value in entries.items():
        conf.insert_json5(key, json.dumps(value))
    return conf


def zenoh_cause(error: Exception) -> str:
    """The reason in a zenoh error, without the Rust source locations it carries (" at /…/x.rs:61.")."""
    text = re.sub(r"\s+at\s+\S+\.rs:\d+\.?", "", str(error))
    return re.sub(r"\s+", " ", text).strip().rstrip(".")


def open_session(
    settings: FleetSettings, mode: str = "client", listen: str | None = None, base_file: str | None = None,
    routers: str | None = None,
) -> zenoh.Session:
    """Open a Zenoh session (logging where it connects or listens); a router that does not answer in time, or an
    endpoint that cannot be listened on, raises :class:`ConnectError` with one line giving the real cause."""
    conf = zenoh_config(settings, mode, listen, base_file, routers)
    where = (listen or "tcp/0.0.0.0:7447") if mode == "router" else settings.zenoh_connect
    if mode == "router":
        log.info("listening on %s", where)
    else:
        log.info("connecting to the zenoh router at %s (waiting up to %g s)", where, settings.connect_timeout_s)
    try:
        return zenoh.open(conf)
    except zenoh.ZError as exc:
        cause = zenoh_cause(exc)
        if mode == "router":
            hint = ("another router or program holds that port: stop it or choose another endpoint with --listen"
                    if "Address already in use" in cause else "check the endpoint given to --listen")
            raise ConnectError(f"cannot listen on {where}: {cause}; {hint}") from None
        raise ConnectError(
            f"could not reach the zenoh router at {where} within {settings.connect_timeout_s:g} s ({cause}); "
            "start one with `fleetslam router`, or point --zenoh-connect / FLEETSLAM_ZENOH_CONNECT at yours"
        ) from None


@contextmanager
def session_scope(settings: FleetSettings, mode: str = "client", listen: str | None = None) -> Iterator[zenoh.Session]:
    """``with session_scope(settings) as session:`` — always closed, also on errors and signals."""
    session = open_session(settings, mode, listen)
    try:
        yield session
    finally:
        try:
            session.close()
        except Exception:  # noqa: BLE001 - closing twice or after a lost link must not mask the real error
            log.debug("session close failed", exc_info=True)


def cache_samples(settings: FleetSettings, rate_hz: float) -> int:
    """How many samples a publisher of ``rate_hz`` (wall-clock messages per second) caches: the setting
    ``publisher_cache`` when given, else enough for ``outage_budget_s`` of the stream (at least 16)."""
    if settings.publisher_cache is not None:
        return settings.publisher_cache
    return max(16, math.ceil(rate_hz * settings.outage_budget_s))


def stream_caches(settings: FleetSettings, rates: dict[str, float], speedup: float = 1.0) -> dict[str, int]:
    """:func:`cache_samples` of each stream in ``rates`` (messages per second of data time), published ``speedup``
    times faster than real time."""
    return {name: cache_samples(settings, rate * speedup) for name, rate in rates.items()}


def paced(events: Iterable, data0: float, speedup: float, shutdown: "Shutdown") -> Iterator[tuple[object, float]]:
    """Each event when it is due, with how late it is (s): data time from ``data0`` divided by ``speedup``, wall time
    from the first event asked for. Stops when ``shutdown`` is set (also while waiting)."""
    wall0 = time.monotonic()
    for event in events:
        due = wall0 + (event.stamp - data0) / speedup
        now = time.monotonic()
        if (due > now and shutdown.wait(due - now)) or shutdown.is_set():
            return
        yield event, time.monotonic() - due


def linger_time(configured_s: float, stopped_by_signal: bool, heartbeat_s: float | None = None) -> float:
    """How long a robot keeps its publishers (caches, heartbeats) after its last message, for a receiver that missed
    the tail: ``configured_s``, but when a signal stopped it at most 1 s, so it exits promptly, or one heartbeat
    period (``heartbeat_s``) if that is longer, so that one heartbeat still tells of its last message."""
    return min(configured_s, max(1.0, heartbeat_s or 0.0)) if stopped_by_signal else configured_s


class StreamPublisher:
    """Reliable, congestion-control BLOCK publisher of fleetslam messages on one key.

    With ``cache`` > 0 it is an advanced publisher: it keeps the last ``cache`` samples for receivers that
    missed them (late, cut off, restarted) and sends a heartbeat every ``heartbeat_s`` (default: the setting
    ``heartbeat_period_s``'s) with its last sequence number, so a receiver learns of a lost tail even when nothing
    follows it; ``sporadic``: only when that number changed since the last heartbeat (a stream that is rarely
    published, as a robot's RobotInfo, then sends none while it is quiet).
    """

    def __init__(self, session: zenoh.Session, key: str, cache: int = 0, keep: int = 0,
                 heartbeat_s: float | None = None, sporadic: bool = False):
        self.key = key
        self.count = 0
        self.recent: deque[bytes] = deque(maxlen=keep)  # the last ``keep`` payloads, for :func:`answer_history`
        self._recent_lock = threading.Lock()
        if cache > 0:
            if heartbeat_s is None:
                heartbeat_s = FleetSettings.model_fields["heartbeat_period_s"].default
            miss = (zenoh.ext.MissDetectionConfig(sporadic_heartbeat=heartbeat_s) if sporadic
                    else zenoh.ext.MissDetectionConfig(heartbeat=heartbeat_s))
            self._publisher = zenoh.ext.declare_advanced_publisher(
                session,
                key,
                congestion_control=zenoh.CongestionControl.BLOCK,
                reliability=zenoh.Reliability.RELIABLE,
                cache=zenoh.ext.CacheConfig(max_samples=cache),
                sample_miss_detection=miss,
                publisher_detection=True,
            )
        else:
            self._publisher = session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE
            )
        self._plain = cache <= 0  # a plain publisher names its session in each sample itself (an advanced one does)

    def put(self, message: BaseModel | bytes, payload: bytes | None = None) -> None:
        """Publish ``message`` (a model, encoded here, or bytes); ``payload``: the model's encoding, made already."""
        if payload is None:
            payload = message if isinstance(message, bytes) else encode(message)
        if self._plain:
            self._publisher.put(payload, source_info=zenoh.SourceInfo(self._publisher.id, self.count))
        else:
            self._publisher.put(payload)
        self.count += 1
        if self.recent.maxlen:
            with self._recent_lock:
                self.recent.append(payload)

    def kept(self) -> list[bytes]:
        """The payloads kept (``keep``), oldest first; safe from any thread."""
        with self._recent_lock:
            return list(self.recent)

    def undeclare(self) -> None:
        try:
            self._publisher.undeclare()
        except Exception:  # noqa: BLE001 - already gone with the session
            log.debug("publisher undeclare failed", exc_info=True)


def declare_robot_tokens(session: zenoh.Session, keys, robot_id: str) -> list:
    """The liveliness tokens of a robot published by ``session``: DESIGN's ``{prefix}/robots/{rid}/alive`` and the
    session token naming this session (:meth:`Keys.session_token`), by which services accept the robot's messages
    from this session only."""
    zid = str(session.info.zid())
    return [session.liveliness().declare_token(keys.alive(robot_id)),
            session.liveliness().declare_token(keys.session_token(robot_id, zid))]


def answer_with(session: zenoh.Session, key: str, payload: bytes):
    """A queryable answering every query on ``key`` with ``payload``, on that concrete key (what a late joiner
    asks a robot for: its RobotInfo, the world truth)."""
    return session.declare_queryable(key, lambda query: query.reply(key, payload))


def answer_history(session: zenoh.Session, key: str, publishers: list[StreamPublisher]):
    """A queryable on ``key`` answering each query with every payload the ``publishers`` kept, oldest first, each on
    its publisher's key: what a restarted service asks a robot for (:meth:`ServiceShell.refill_from_robots`), on top
    of the advanced publishers' caches, whose history a subscriber now and then misses at declaration."""

    def answer(query: zenoh.Query) -> None:
        for publisher in publishers:
            for payload in publisher.kept():
                query.reply(publisher.key, payload)

    return session.declare_queryable(key, answer)


def replier_zid(reply: zenoh.Reply) -> str | None:
    """The Zenoh session id of the session that sent ``reply`` (None when unknown)."""
    replier = reply.replier_id
    return None if replier is None else str(replier.zid)


def sample_source(sample: zenoh.Sample) -> str | None:
    """The Zenoh session id of the session that published ``sample`` (None when it carries no source)."""
    return None if sample.source_info is None else str(sample.source_info.source_id.zid)


def history_query(session: zenoh.Session, key: str, on_payload, on_done, timeout_s: float) -> None:
    """Ask ``key`` (a robot's history queryable) for what it kept: ``on_payload(key, payload, replier)`` per reply
    (``replier``: the answering Zenoh session's id), then
    ``on_done()`` once the query is over (answered, timed out or refused)."""
    def on_reply(reply: zenoh.Reply) -> None:
        if reply.ok is not None:
            on_payload(str(reply.ok.key_expr), reply.ok.payload.to_bytes(), replier_zid(reply))

    session.get(key, zenoh.handlers.Callback(on_reply, on_done), timeout=timeout_s,
                accept_replies=zenoh.ReplyKeyExpr.ANY, consolidation=zenoh.ConsolidationMode.NONE)


def undeclare_all(entities) -> None:
    """Undeclare publishers, queryables and liveliness tokens (None skipped), ignoring those already gone."""
    for entity in entities:
        if entity is None:
            continue
        try:
            entity.undeclare()
        except zenoh.ZError:
            pass


class Shutdown:
    """A stop flag set by SIGINT/SIGTERM (or by code); install once per process from the main thread.

    ``notice`` is logged (after the signal's name) when the first signal arrives; with ``second_interrupts``
    a second signal raises KeyboardInterrupt (for work that stops at its next check: asked twice, leave now).
    :meth:`restore` puts back the handlers it replaced.
    """

    def __init__(self, install: bool = True, notice: str | None = None, second_interrupts: bool = False):
        self.event = threading.Event()
        self.signal_name: str | None = None
        self.notice = notice
        self.second_interrupts = second_interrupts
        self._previous: dict = {}
        if install and threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handle)

    def _handle(self, signum, _frame) -> None:
        if self.second_interrupts and self.event.is_set():
            raise KeyboardInterrupt
        self.signal_name = signal.Signals(signum).name
        self.event.set()
        if self.notice:
            log.warning("%s: %s", self.signal_name, self.notice)

    def restore(self) -> None:
        """Put back the signal handlers this replaced (a command run inside a longer-lived process)."""
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous = {}

    def set(self) -> None:
        self.event.set()

    def is_set(self) -> bool:
        return self.event.is_set()

    def wait(self, timeout: float | None = None) -> bool:
        return self.event.wait(timeout)


def run_command(run: Callable, settings, logger: logging.Logger, refused: str,
                errors: tuple[type[BaseException], ...]) -> int:
    """A command's exit code: ``run(settings, Shutdown())`` until a signal, 0; 2 with one logged line when the
    router cannot be reached, or on one of ``errors`` (logged after ``refused``, e.g. "cannot record")."""
    try:
        run(settings, Shutdown())
    except ConnectError as exc:
        logger.error("%s", exc)
        return 2
    except errors as exc:
        logger.error("%s: %s", refused, exc)
        return 2
    return 0
