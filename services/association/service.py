"""``fleetslam assoc``: data association as a Zenoh queryable on ``{prefix}/assoc/{method}``.

One queryable per method (nn, greedy, ihgr, exact, jcbb, auto). A query carries
an :class:`~schemas.association.AssociationRequest`; the service decodes it,
calls :func:`~services.association.core.associate` and replies with an
:class:`~schemas.association.AssociationReply` on the method's concrete key.
A bad request (undecodable, invalid, too large, not solvable) gets
``reply_err`` with ``"reason: detail"`` and is counted; the service keeps
serving. Stats go to ``{prefix}/assoc/stats``.

Queries are bounded (:class:`~services.query_pool.QueryPool`): a request is
decoded and sized (:func:`~services.association.core.query_cells` against
``max_query_cells``) on Zenoh's callback thread and refused at once when too
large or when ``query_queue`` requests already wait (``busy``); the others
are solved by ``query_workers`` threads within ``query_deadline_s``; those of at most ``light_query_cells`` cells
(what a live D-SLAM asks) by a worker of their own, so that heavy queries never hold them up.

A query on a wildcard (``{prefix}/assoc/**``, ``{prefix}/assoc/*``) reaches
every queryable of an instance, but is solved and answered once per
instance: by the default method ``auto`` (the first served method when
``auto`` is not served) on the first key the wildcard names, public before
instance keys; the reply's ``method`` and key say which. The other
queryables let it go unanswered. A concrete key is answered by its method,
as always.

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
import uuid

import zenoh

from schemas.association import AssociationRequest
from schemas.codec import encode
from schemas.config import AssocSettings, add_settings_arguments, settings_from_args
from services.association.client import instance_key, instances_key
from services.association.core import AssociationError, associate, query_cells
from services.query_pool import QueryPool, QueryRefused, Sized, decode_query, is_wildcard
from services.runtime import ServiceShell

log = logging.getLogger(__name__)

DEFAULT_METHOD = "auto"


class AssocService(ServiceShell):
    """The association queryable: decode, validate, size, then :func:`associate` in a worker, encode, reply."""

    name = "assoc"
    uses_kernels = ("association",)

    def __init__(self, settings: AssocSettings, instance: str | None = None):
        super().__init__(settings, instance or f"assoc-{os.getpid()}-{uuid.uuid4().hex[:6]}")
        self.settings: AssocSettings = settings
        self.methods = settings.methods.split(",")
        self.pool = QueryPool(self, settings.query_workers, settings.query_queue, settings.query_deadline_s,
                              settings.query_nice, light_cost=settings.light_query_cells,
                              light_queue=settings.light_query_queue)
        self._wildcard_order: list[zenoh.KeyExpr] = []

    def setup(self, session: zenoh.Session) -> None:
        first = sorted(self.methods, key=lambda method: method != DEFAULT_METHOD)
        self._wildcard_order = [zenoh.KeyExpr(self.keys.assoc(method)) for method in first] + [
            zenoh.KeyExpr(instance_key(self.keys, method, self.instance)) for method in first]
        for method in self.methods:
            for key in (self.keys.assoc(method), instance_key(self.keys, method, self.instance)):
                queryable = session.declare_queryable(key, self._on_query(method, key), complete=self.settings.complete)
                self._declared.append(queryable)
        self._declared.append(session.liveliness().declare_token(f"{instances_key(self.keys)}/{self.instance}"))

    def _on_query(self, method: str, key: str):
        def callback(query: zenoh.Query) -> None:
            if is_wildcard(query.key_expr) and not self.answers_wildcard(key, query.key_expr):
                query.drop()  # another queryable of this instance answers it
                return
            self.pool.admit(query, method, lambda: self._prepare(method, key, query))

        return callback

    def answers_wildcard(self, key: str, asked: zenoh.KeyExpr) -> bool:
        """Whether the queryable on ``key`` is the one of this instance that answers the wildcard ``asked``: the
        first of the default method's keys, then the other methods', public keys before the instance's."""
        for candidate in self._wildcard_order:
            if candidate.intersects(asked):
                return str(candidate) == key
        return False

    def _prepare(self, method: str, key: str, query: zenoh.Query) -> Sized:
        """Decode and size the request on the callback's thread (QueryRefused at once); the solve for a worker, with
        its cells (the light lane takes the small ones)."""
        request = decode_query(query, AssociationRequest)
        s = self.settings
        m, n = request.size
        if m > s.max_measurements or n > s.max_landmarks:
            raise QueryRefused("too_large", f"{m} measurements × {n} landmarks exceeds "
                               f"{s.max_measurements} × {s.max_landmarks}")
        cells = query_cells(request, method)
        if cells > s.max_query_cells:
            raise QueryRefused("too_large", f"{m} measurements × {n} landmarks make {cells} cells for {method}, "
                               f"above max_query_cells {s.max_query_cells}")
        if request.jcbb_max_nodes > s.max_jcbb_nodes:
            request = request.model_copy(update={"jcbb_max_nodes": s.max_jcbb_nodes})

        def solve(budget_s: float) -> tuple[str, bytes]:
            try:
                reply = associate(request, method, time_budget_s=budget_s)
            except AssociationError as error:
                raise QueryRefused(error.reason, error.detail) from None
            return key, encode(reply)

        return Sized(solve, cells)

    def stats(self):
        self.pool.put_stats()
        self.published = self.pool.total_replies
        return super().stats()

    def on_stop(self) -> None:
        self.pool.close()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, AssocSettings)


def main(args: argparse.Namespace) -> int:
    return AssocService(settings_from_args(AssocSettings, args)).serve()
