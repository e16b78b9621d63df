"""``fleetslam assoc``: data association as a Zenoh queryable on ``{prefix}/assoc/{method}``.

One queryable per method (nn, greedy, ihgr, exact, jcbb, auto). A query carries
an :class:`~schemas.association.AssociationRequest`; the service decodes it,
calls :func:`~services.association.core.associate` and replies with an
:class:`~schemas.association.AssociationReply` on the method's concrete key.
A bad request (undecodable, invalid, too large, not solvable) gets
``reply_err`` with ``"reason: detail"`` and is counted; the service keeps
serving. Stats go to ``{prefix}/assoc/stats``.

Several instances run side by side. Each declares its queryables *complete*
on the public keys ``{prefix}/assoc/{method}`` (a ``BEST_MATCHING`` query is
answered by exactly one instance; the router keeps choosing the same one while
it lives, so the others are standbys), and on its own keys
``{prefix}/assoc/{method}/{instance}``, announced by a liveliness token
``{prefix}/assoc/instances/{instance}``: the
:class:`~services.association.client.AssociationClient` spreads its requests
over the live instances round robin, which is how the load is shared.
"""

from __future__ import annotations

import argparse
import logging
import os
import time
import uuid

import zenoh

from schemas.association import AssociationRequest
from schemas.codec import encode
from schemas.config import AssocSettings, add_settings_arguments, settings_from_args
from services.association.client import instance_key, instances_key
from services.association.core import AssociationError, associate
from services.runtime import ServiceShell

log = logging.getLogger(__name__)


class AssocService(ServiceShell):
    """The association queryable: decode, validate, :func:`associate`, encode, reply."""

    name = "assoc"
    uses_kernels = ("association",)

    def __init__(self, settings: AssocSettings, instance: str | None = None):
        super().__init__(settings, instance or f"assoc-{os.getpid()}-{uuid.uuid4().hex[:6]}")
        self.methods = settings.methods.split(",")
        self._solve_ms_total = 0.0

    def setup(self, session: zenoh.Session) -> None:
        for method in self.methods:
            for key in (self.keys.assoc(method), instance_key(self.keys, method, self.instance)):
                queryable = session.declare_queryable(key, self._on_query(method, key), complete=self.settings.complete)
                self._declared.append(queryable)
        self._declared.append(session.liveliness().declare_token(f"{instances_key(self.keys)}/{self.instance}"))

    def _on_query(self, method: str, key: str):
        def callback(query: zenoh.Query) -> None:
            self.enqueue(method, key, query)  # the query object rides the queue; it is answered in handle()

        return callback

    async def handle(self, tag: str, key: str, query: zenoh.Query) -> None:
        try:
            self._answer(tag, key, query)
        except Exception as exc:  # noqa: BLE001 - the client must hear back, and the service must go on
            log.exception("assoc: %s failed", tag)
            self.refuse(query, "internal_error", f"{type(exc).__name__}: {exc}")
        finally:
            query.drop()

    def _answer(self, method: str, key: str, query: zenoh.Query) -> None:
        request = self.decode_request(query, AssociationRequest)
        if request is None:
            return
        m, n = request.size
        if m > self.settings.max_measurements or n > self.settings.max_landmarks:
            self.refuse(query, "too_large", f"{m} measurements × {n} landmarks exceeds "
                         f"{self.settings.max_measurements} × {self.settings.max_landmarks}")
            return
        if request.jcbb_max_nodes > self.settings.max_jcbb_nodes:
            request = request.model_copy(update={"jcbb_max_nodes": self.settings.max_jcbb_nodes})
        started = time.perf_counter()
        try:
            reply = associate(request, method)
        except AssociationError as error:
            self.refuse(query, error.reason, error.detail)
            return
        self._solve_ms_total += (time.perf_counter() - started) * 1e3
        query.reply(key, encode(reply))
        self.published += 1
        self.extra["replies"] = float(self.published)
        self.extra["solve_ms_mean"] = self._solve_ms_total / self.published


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, AssocSettings)


def main(args: argparse.Namespace) -> int:
    return AssocService(settings_from_args(AssocSettings, args)).serve()
