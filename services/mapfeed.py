"""Both ends of a map output sent by tiles (:mod:`schemas.maptiles`), for the services' shells.

- :class:`StateQueries` (the producers, central and D-SLAM): the state queryable. Queries that arrive between two
  turns of the loop wait together and all get the one full map built at the next turn (at most ``limit`` wait;
  more are answered ``busy`` at once), so a flood of them costs the service one map.
- :class:`MapFeed` (the receivers: evaluator, viz, MCL, the ROS 2 bridge): decodes each published map message,
  assembles the whole map, and when it joined late or missed a message asks the producer's state queryable for a full
  one; the messages it gives back are whole maps, as if the producer had sent the whole map every time.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Generic, TypeVar

import zenoh

from schemas.maptiles import TileBlock, TiledMap
from schemas.messages import TiledMapMessage

log = logging.getLogger("fleetslam.mapfeed")

M = TypeVar("M", bound=TiledMapMessage)


class StateQueries:
    """A producer's state queryable on ``key``; the shell answers the waiting queries at its loop's next turn."""

    def __init__(self, shell, key: str, limit: int):
        self.shell, self.key, self.limit = shell, key, limit
        self._lock = threading.Lock()
        self._waiting: list[zenoh.Query] = []  # Zenoh's threads append
        self.answered = 0

    def declare(self, session: zenoh.Session) -> None:
        self.shell._declared.append(session.declare_queryable(self.key, self._on_query))

    def _on_query(self, query: zenoh.Query) -> None:
        """Zenoh's callback: the query waits with the others for the next turn; ``busy`` when too many wait."""
        with self._lock:
            admitted = len(self._waiting) < self.limit
            if admitted:
                self._waiting.append(query)
                first = len(self._waiting) == 1
        if not admitted:
            try:
                query.reply_err(f"busy: {self.limit} state queries wait already; ask again later".encode())
            finally:
                query.drop()
            self.shell.call_in_loop(self.shell.reject, "busy", "a state query")
        elif first:  # the loop answers every query waiting by then
            self.shell.enqueue("state", self.key, b"")

    def answer(self, payload: bytes | None, error: bytes = b"not_available") -> None:
        """Answer every waiting query with ``payload`` (None: with ``error``)."""
        with self._lock:
            queries, self._waiting = self._waiting, []
        for query in queries:
            try:
                if payload is None:
                    query.reply_err(error)
                else:
                    query.reply(self.key, payload)
            except Exception as exc:  # noqa: BLE001 - the caller may be gone; the others still get theirs
                log.debug("cannot answer a state query on %s: %s", self.key, exc)
            finally:
                query.drop()
        self.answered += len(queries)


def tile_block(message: TiledMapMessage) -> TileBlock:
    """A map message's tiles and landmarks (its covariances and ids too, when it has them)."""
    covs = getattr(message, "landmark_covs", None)
    return TileBlock(message.full, message.tile_size, message.tiles, message.tile_counts, message.landmarks, covs,
                     getattr(message, "landmark_ids", None))


def whole(message: M, tiles: TiledMap) -> M:
    """``message`` with the whole assembled map in place of its tiles: a full, untiled message."""
    block = tiles.block()
    update = {"landmarks": block.means, "full": True, "tiles": block.tiles, "tile_counts": block.counts}
    if "landmark_covs" in type(message).model_fields:
        update["landmark_covs"] = block.covs
    if "landmark_ids" in type(message).model_fields:
        update["landmark_ids"] = block.ids
    return message.model_copy(update=update)


class MapFeed(Generic[M]):
    """A receiver of one map output (``kind`` on ``stream_key``, full maps from ``state_key``).

    The shell subscribes ``stream_key`` under a tag of its choice and passes each message it decoded to
    :meth:`take`; the replies of the state queries the feed sends come back to the shell under :attr:`reply_tag`,
    for :meth:`take` as well (``reply=True``).
    """

    def __init__(self, shell, kind: type[M], state_key: str, reply_tag: str, ask_every_s: float = 2.0):
        self.shell, self.kind, self.state_key, self.reply_tag = shell, kind, state_key, reply_tag
        self.tiles = TiledMap()
        self.ask_every_s = ask_every_s
        self._asked_at = -float("inf")
        self.asked = 0

    def take(self, message: M, reply: bool = False) -> M | None:
        """``message`` with the whole map in place of its tiles (``reply``: it answers the state query
        :attr:`reply_tag` stands for). After a missed message the map is the one before the gap until a full map
        mends it (asked for here); None until the feed has a whole map at all."""
        if not self.tiles.take(message.seq, tile_block(message), reply=reply):
            self.ask()
        return whole(message, self.tiles) if self.tiles.ready else None

    def ask(self) -> None:
        """Ask the producer for a full map, at most once every ``ask_every_s``."""
        now = time.monotonic()
        session = self.shell.session
        if session is None or now - self._asked_at < self.ask_every_s:
            return
        self._asked_at = now
        self.asked += 1

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is not None:
                self.shell.enqueue(self.reply_tag, self.state_key, reply.ok.payload.to_bytes())

        try:
            session.get(self.state_key, on_reply, timeout=self.ask_every_s)
        except Exception as exc:  # noqa: BLE001 - the session is closing; the next message asks again
            log.debug("cannot ask %s for a full map: %s", self.state_key, exc)


def assemble(messages: list[M]) -> M | None:
    """The whole map after a run of published map messages in the order received (a recording, a test's
    collector): the last message, whole; None when a missed message left it incomplete."""
    tiles, last = TiledMap(), None
    for message in messages:
        last = whole(message, tiles) if tiles.take(message.seq, tile_block(message)) else None
    return last
