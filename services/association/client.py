"""Asking the association queryable (``fleetslam assoc``) from another service, e.g. D-SLAM.

:func:`query_associate` sends one :class:`AssociationRequest` to
``{prefix}/assoc/{method}`` with target ``BEST_MATCHING`` (one instance
answers) and returns the :class:`AssociationReply`. A refusal raises
:class:`AssociationRefused` (with the service's reason: ``busy``,
``too_large``, ``deadline``...); no answer within ``timeout`` (Zenoh's own
``Timeout`` error, which no replier sent) raises :class:`TimeoutError`, so
that a caller can fall back to the in-process
:func:`~services.association.core.associate`. The query tells the service
how long it waits (selector parameter ``timeout_s``): the service drops it
unsolved once the caller has given up, and cuts its solve to fit.

:class:`AssociationClient` shares the load between several service
instances: it follows their liveliness tokens and sends each request to the
next live instance's own key, round robin (a plain ``BEST_MATCHING`` query
always reaches the same instance).
"""

from __future__ import annotations

import itertools
import threading

import zenoh

from schemas.association import AssociationReply, AssociationRequest
from schemas.codec import decode, encode
from schemas.keys import Keys


class AssociationRefused(RuntimeError):
    """The service answered with an error; ``reason`` is its label (malformed, invalid, too_large...)."""

    def __init__(self, reason: str, detail: str = ""):
        self.reason = reason
        self.detail = detail
        super().__init__(f"{reason}: {detail}" if detail else reason)


def instances_key(keys: Keys) -> str:
    """Where instances announce themselves (liveliness tokens ``{prefix}/assoc/instances/{instance}``)."""
    return keys.assoc("instances")


def instance_key(keys: Keys, method: str, instance: str) -> str:
    """One instance's own queryable for ``method``."""
    return f"{keys.assoc(method)}/{instance}"


def query_associate(
    session: zenoh.Session, keys: Keys, method: str, request: AssociationRequest | bytes, timeout: float = 1.0,
    instance: str | None = None,
) -> AssociationReply:
    """Associate one scan through the queryable (one ``instance``'s key if given); raise AssociationRefused or TimeoutError."""
    key = keys.assoc(method) if instance is None else instance_key(keys, method, instance)
    payload = request if isinstance(request, bytes) else encode(request)
    selector = zenoh.Selector(key, {"timeout_s": f"{timeout:g}"})  # the service drops what we no longer wait for
    replies = session.get(selector, payload=payload, target=zenoh.QueryTarget.BEST_MATCHING, timeout=timeout)
    for reply in replies:
        if reply.ok is not None:
            return decode(reply.ok.payload.to_bytes(), AssociationReply)
        if reply.replier_id is None:  # Zenoh's own error (its timeout), not a service's answer
            break
        text = reply.err.payload.to_bytes().decode(errors="replace")
        reason, _, detail = text.partition(": ")
        raise AssociationRefused(reason, detail)
    raise TimeoutError(f"no association service answered on {key} within {timeout:g} s")


class AssociationClient:
    """Round-robin requests over the live association instances (their liveliness tokens)."""

    def __init__(self, session: zenoh.Session, keys: Keys, timeout: float = 1.0):
        self.session = session
        self.keys = keys
        self.timeout = timeout
        self._lock = threading.Lock()
        self._instances: list[str] = []
        self._turn = itertools.count()
        self._subscriber = session.liveliness().declare_subscriber(f"{instances_key(keys)}/*", self._on_token, history=True)

    def _on_token(self, sample: zenoh.Sample) -> None:
        instance = str(sample.key_expr).rsplit("/", 1)[-1]
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT and instance not in self._instances:
                self._instances.append(instance)
            elif sample.kind == zenoh.SampleKind.DELETE and instance in self._instances:
                self._instances.remove(instance)

    @property
    def instances(self) -> list[str]:
        with self._lock:
            return list(self._instances)

    def associate(self, method: str, request: AssociationRequest | bytes) -> AssociationReply:
        """Ask the next live instance; if it does not answer in time or is busy, ask the public key once."""
        with self._lock:
            instance = self._instances[next(self._turn) % len(self._instances)] if self._instances else None
        if instance is not None:
            try:
                return query_associate(self.session, self.keys, method, request, self.timeout, instance)
            except TimeoutError:
                pass
            except AssociationRefused as refusal:
                if refusal.reason != "busy":
                    raise
        return query_associate(self.session, self.keys, method, request, self.timeout)

    def close(self) -> None:
        self._subscriber.undeclare()
