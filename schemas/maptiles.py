"""A landmark map sent as the tiles that changed, so that a map output's steady cost does not grow with the map.

The plane is cut into square tiles of ``tile_size`` metres. A map message lists some tiles and, grouped by tile in
that order, every landmark each listed tile holds now (a listed tile with no landmark empties it). A message is
*full* when it lists every tile of the map (receivers drop the tiles it does not list) and a *delta* otherwise.

:class:`TileSender` (the producer, e.g. central) keeps the map its subscribers hold and lists a tile when its
landmarks changed: a landmark came or went, a mean moved more than ``tolerance_m``, or a covariance changed by more
than ``cov_tolerance`` of its size. Far from the robots nothing changes, so a delta's size follows what the robots
see, not the map's size: receivers hold the producer's map within ``tolerance_m``. Its first message is full. A full
message built on request (a state query: a late joiner, a receiver that missed a delta) is the map as it is, and
leaves the subscribers' map alone; the tiles in which it differed from that map beyond the tolerances are listed in
the next delta, so a receiver that applied it and then that delta holds the producer's map within twice the
tolerance (what it got in the reply and what the others hold may each be ``tolerance_m`` from the producer's).

:class:`TiledMap` (a receiver) applies messages in sequence order and says when it missed one; then it needs a full
message, and keeps the deltas that arrive meanwhile (at most ``max_pending``) to apply after it.

Pure numpy: no Zenoh, no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_OFFSET = np.int64(1 << 30)  # tile indices within ±2^30 (10^10 m at 10 m tiles): keys stay positive int64


@dataclass
class TileBlock:
    """Listed tiles (``tiles`` (k, 2) tile indices, ``counts`` (k,)) and their landmarks grouped in that order."""

    full: bool
    tile_size: float
    tiles: np.ndarray
    counts: np.ndarray
    means: np.ndarray
    covs: np.ndarray | None
    ids: np.ndarray | None


@dataclass
class _Rows:
    """Landmarks sorted by tile, then by id (or by x, y without ids); ``keys`` one int64 per tile."""

    keys: np.ndarray
    means: np.ndarray
    covs: np.ndarray | None
    ids: np.ndarray | None

    def take(self, mask: np.ndarray) -> "_Rows":
        return _Rows(self.keys[mask], self.means[mask], None if self.covs is None else self.covs[mask],
                     None if self.ids is None else self.ids[mask])


def tile_keys(means: np.ndarray, tile_size: float) -> np.ndarray:
    """One int64 per landmark naming its tile (``tile_size`` 0: every landmark in one tile)."""
    if tile_size <= 0:
        return np.zeros(means.shape[0], np.int64)
    index = np.clip(np.floor(means / tile_size), 1 - _OFFSET, _OFFSET - 1).astype(np.int64) + _OFFSET
    return (index[:, 0] << 32) | index[:, 1]


def keys_of(tiles: np.ndarray) -> np.ndarray:
    """Tile indices (k, 2) → one int64 each (:func:`tile_keys`)."""
    tiles = np.asarray(tiles, np.int64).reshape(-1, 2)
    return ((tiles[:, 0] + _OFFSET) << 32) | (tiles[:, 1] + _OFFSET)


def tiles_of(keys: np.ndarray) -> np.ndarray:
    """One int64 per tile → tile indices (k, 2)."""
    return np.stack([(keys >> 32) - _OFFSET, (keys & 0xFFFFFFFF) - _OFFSET], axis=1).astype(np.int64)


def _sorted(keys, means, covs, ids) -> _Rows:
    means = np.asarray(means, float).reshape(-1, 2)
    order = np.lexsort((ids, keys)) if ids is not None else np.lexsort((means[:, 1], means[:, 0], keys))
    return _Rows(np.asarray(keys, np.int64)[order], means[order], None if covs is None else np.asarray(covs)[order],
                 None if ids is None else np.asarray(ids, np.int64)[order])


def _concat(a: _Rows, b: _Rows) -> _Rows:
    join = (lambda x, y: None if x is None or y is None else np.concatenate([x, y]))
    rows = _Rows(np.concatenate([a.keys, b.keys]), np.concatenate([a.means, b.means]), join(a.covs, b.covs),
                 join(a.ids, b.ids))
    return _sorted(rows.keys, rows.means, rows.covs, rows.ids)


def _empty(with_covs: bool, with_ids: bool) -> _Rows:
    return _Rows(np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 2, 2)) if with_covs else None,
                 np.zeros(0, np.int64) if with_ids else None)


def changed_tiles(old: _Rows, new: _Rows, tolerance_m: float, cov_tolerance: float) -> np.ndarray:
    """Keys of the tiles whose landmarks differ between ``old`` and ``new`` (both sorted by :func:`_sorted`): a
    tile in one only, a different count, an id, a mean farther than ``tolerance_m``, a covariance farther than
    ``cov_tolerance`` of its Frobenius norm."""
    old_tiles, old_counts = np.unique(old.keys, return_counts=True)
    new_tiles, new_counts = np.unique(new.keys, return_counts=True)
    common, i_old, i_new = np.intersect1d(old_tiles, new_tiles, assume_unique=True, return_indices=True)
    same_count = old_counts[i_old] == new_counts[i_new]
    comparable = common[same_count]
    rows_old, rows_new = np.isin(old.keys, comparable), np.isin(new.keys, comparable)
    moved = np.hypot(*(new.means[rows_new] - old.means[rows_old]).T) > tolerance_m
    if old.ids is not None and new.ids is not None:
        moved |= new.ids[rows_new] != old.ids[rows_old]
    if old.covs is not None and new.covs is not None:
        before, after = old.covs[rows_old], new.covs[rows_new]
        moved |= np.linalg.norm(after - before, axis=(1, 2)) > cov_tolerance * np.linalg.norm(before, axis=(1, 2))
    return np.unique(np.concatenate([np.setxor1d(old_tiles, new_tiles, assume_unique=True), common[~same_count],
                                     new.keys[rows_new][moved]]))


def _block(rows: _Rows, listed: np.ndarray, full: bool, tile_size: float) -> TileBlock:
    """The landmarks of the ``listed`` tiles (sorted keys) of ``rows``, grouped by tile."""
    chosen = rows.take(np.isin(rows.keys, listed))
    tiles, counts = np.unique(chosen.keys, return_counts=True)
    all_counts = np.zeros(listed.shape[0], np.int64)
    all_counts[np.searchsorted(listed, tiles)] = counts
    return TileBlock(full, tile_size, tiles_of(listed), all_counts, chosen.means, chosen.covs, chosen.ids)


class TileSender:
    """The producer's side: what its subscribers hold, and the tiles that changed since (module docstring)."""

    def __init__(self, tile_size: float, tolerance_m: float, cov_tolerance: float):
        if tile_size <= 0 or tolerance_m < 0 or cov_tolerance < 0:
            raise ValueError("tile_size must be > 0; tolerances ≥ 0")
        self.tile_size = float(tile_size)
        self.tolerance_m = float(tolerance_m)
        self.cov_tolerance = float(cov_tolerance)
        self.sent: _Rows | None = None  # what the subscribers hold; None before the first (full) message
        self.owed = np.zeros(0, np.int64)  # tiles in which a full message given on request differed from ``sent``

    def _rows(self, means, covs, ids) -> _Rows:
        means = np.asarray(means, float).reshape(-1, 2)
        return _sorted(tile_keys(means, self.tile_size), means, covs, ids)

    def delta(self, means: np.ndarray, covs: np.ndarray | None = None, ids: np.ndarray | None = None) -> TileBlock:
        """The next published message: full the first time (and after :meth:`restart`), else the changed tiles."""
        now = self._rows(means, covs, ids)
        if self.sent is None:
            self.sent, self.owed = now, np.zeros(0, np.int64)
            return _block(now, np.unique(now.keys), True, self.tile_size)
        listed = np.union1d(changed_tiles(self.sent, now, self.tolerance_m, self.cov_tolerance), self.owed)
        self.sent = _concat(self.sent.take(~np.isin(self.sent.keys, listed)), now.take(np.isin(now.keys, listed)))
        self.owed = np.zeros(0, np.int64)
        return _block(now, listed, False, self.tile_size)

    def snapshot(self, means: np.ndarray, covs: np.ndarray | None = None, ids: np.ndarray | None = None) -> TileBlock:
        """A full message of the map as it is now, for one receiver (a state query); the next delta lists the tiles
        where it differs from what the subscribers hold."""
        now = self._rows(means, covs, ids)
        if self.sent is not None:
            self.owed = np.union1d(self.owed, changed_tiles(self.sent, now, self.tolerance_m, self.cov_tolerance))
        return _block(now, np.unique(now.keys), True, self.tile_size)

    def restart(self) -> None:
        """The next delta is full (e.g. after the producer restored its state from a checkpoint)."""
        self.sent, self.owed = None, np.zeros(0, np.int64)


class TiledMap:
    """A receiver's map, assembled from full messages and deltas in sequence order (module docstring)."""

    def __init__(self, max_pending: int = 256):
        self.rows: _Rows | None = None
        self.last_seq: int | None = None
        self.tile_size = 0.0
        self.pending: dict[int, TileBlock] = {}  # deltas that arrived after a missed one: seq → block
        self.max_pending = max_pending
        self.gaps = 0

    @property
    def ready(self) -> bool:
        return self.rows is not None

    def take(self, seq: int, block: TileBlock, reply: bool = False) -> bool:
        """Apply a message; False when a message before it is missing (then a full one is needed: ask for it).

        ``reply``: a full message answering a state query, which repeats the number of the next published message
        (so the delta numbered ``seq`` is applied after it)."""
        if block.full:
            self._replace(block)
            self.last_seq = seq - 1 if reply else seq
            self._apply_pending()
            return True
        if self.rows is None or seq > self.last_seq + 1:
            if len(self.pending) >= self.max_pending:
                self.pending.pop(min(self.pending))
            self.pending[seq] = block
            self.gaps += int(self.rows is not None and len(self.pending) == 1)
            return False
        if seq == self.last_seq + 1:
            self._patch(block)
            self.last_seq = seq
            self._apply_pending()
        return True  # seq ≤ last_seq: an old delta, already part of the map

    def _apply_pending(self) -> None:
        for seq in sorted(self.pending):
            if seq <= self.last_seq:
                del self.pending[seq]
            elif seq == self.last_seq + 1:
                self._patch(self.pending.pop(seq))
                self.last_seq = seq
            else:
                break

    def _block_rows(self, block: TileBlock) -> _Rows:
        if block.tiles.shape[0] == 0 and block.means.shape[0]:  # an untiled full message: the whole map in one block
            keys = tile_keys(block.means, block.tile_size)
        else:
            keys = np.repeat(keys_of(block.tiles), block.counts)
        return _sorted(keys, block.means, block.covs, block.ids)

    def _replace(self, block: TileBlock) -> None:
        self.tile_size = block.tile_size
        self.rows = self._block_rows(block)

    def _patch(self, block: TileBlock) -> None:
        listed = keys_of(block.tiles)
        self.rows = _concat(self.rows.take(~np.isin(self.rows.keys, listed)), self._block_rows(block))

    def landmarks(self) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """Means (n, 2), covariances (n, 2, 2) or None, ids (n,) or None of the whole map."""
        rows = self.rows if self.rows is not None else _empty(False, False)
        return rows.means, rows.covs, rows.ids

    def block(self) -> TileBlock:
        """The whole map as a full message's block."""
        rows = self.rows if self.rows is not None else _empty(False, False)
        return _block(rows, np.unique(rows.keys), True, self.tile_size)
