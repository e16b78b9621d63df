"""Every particle's landmark map when a landmark has one slot in all particles (known and shared association),
stored in copy-on-write blocks.

FastSLAM's cost per scan should not grow with the map (Montemerlo et al., "FastSLAM: a factored solution to the
simultaneous localization and mapping problem", §4: particles share the landmarks they have not changed, in a
balanced tree, so resampling costs O(log L) per particle). Here the slots are cut into blocks of ``block`` slots;
each particle has a table naming the physical block that holds each of its blocks, and a block is shared by
every particle whose table names it. Resampling copies tables (one integer per block and particle), never
landmarks. A particle that changes a landmark first gets a private copy of that block (:meth:`AlignedMap.private`):
a scan copies the few blocks near the robot, whatever the size of the map.

Only the Gaussians (mean, covariance) differ between particles; hit counts, existence scores, labels and
validity are the same in every particle when every particle updates the same slots, so they are kept once per
slot. Freed slots (dropped tentative landmarks) are reused by the next new landmarks.
"""

from __future__ import annotations

import heapq

import numpy as np

from central.fastslam import kernels

BLOCK = 32  # slots per block: a scan's copies stay small, a table stays 1/32 of the map


class SlotTable(dict):
    """Landmark id → slot (known and shared association), a dict that also gives both as arrays: built once per change
    of the table, not once per scan (the association's mixtures read them every scan, the table changes far less)."""

    def __init__(self, *args, **kwargs):
        self._arrays: tuple[np.ndarray, np.ndarray] | None = None
        super().__init__(*args, **kwargs)

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(ids ``(n,)``, slots ``(n,)``) in the table's order, as copies the caller may change."""
        if self._arrays is None:
            count = len(self)
            self._arrays = (np.fromiter(self.keys(), np.int64, count), np.fromiter(self.values(), np.int64, count))
        return self._arrays[0].copy(), self._arrays[1].copy()

    def __setitem__(self, key, value) -> None:
        self._arrays = None
        super().__setitem__(key, value)

    def __delitem__(self, key) -> None:
        self._arrays = None
        super().__delitem__(key)

    def __ior__(self, other):
        self._arrays = None
        return super().__ior__(other)

    def update(self, *args, **kwargs) -> None:
        self._arrays = None
        super().update(*args, **kwargs)

    def setdefault(self, key, default=None):
        self._arrays = None
        return super().setdefault(key, default)

    def pop(self, *args):
        self._arrays = None
        return super().pop(*args)

    def popitem(self):
        self._arrays = None
        return super().popitem()

    def clear(self) -> None:
        self._arrays = None
        super().clear()


class AlignedMap:
    """Pooled blocks ``pool_mean (B, block, 2)``, ``pool_cov (B, block, 2, 2)``, their reference counts ``refs``,
    each particle's ``table (P, blocks)`` (−1: nothing written there yet) and the per-slot ``hits``, ``exist``,
    ``label``, ``valid``; ``used`` slots have ever been handed out."""

    def __init__(self, particles: int, block: int = BLOCK):
        self.block = block
        self.table = np.full((particles, 0), -1, np.int32)  # int32: resampling copies P × blocks of them
        self.pool_mean = np.zeros((0, block, 2))
        self.pool_cov = np.zeros((0, block, 2, 2))
        self.refs = np.zeros(0, np.int64)
        self.free_blocks = np.zeros(0, np.int64)
        self.free_count = np.zeros(1, np.int64)
        self.hits = np.zeros(0, np.int32)
        self.exist = np.zeros(0)
        self.label = np.zeros(0, np.int64)
        self.valid = np.zeros(0, bool)
        self.used = 0
        self._free_slots: list[int] = []

    @property
    def particles(self) -> int:
        return self.table.shape[0]

    @property
    def capacity(self) -> int:
        """Slots addressable without growing the tables."""
        return self.table.shape[1] * self.block

    @property
    def nbytes(self) -> int:
        """Memory of the map's arrays (pool, tables and per-slot data)."""
        arrays = (self.table, self.pool_mean, self.pool_cov, self.refs, self.free_blocks, self.hits, self.exist,
                  self.label, self.valid)
        return int(sum(a.nbytes for a in arrays))

    def blocks_in_use(self) -> int:
        """Physical blocks held by at least one particle (how much the particles share: P × blocks when nothing is)."""
        return int((self.refs > 0).sum())

    def counts(self) -> np.ndarray:
        """Landmarks per particle ``(P,)`` (the same in every particle)."""
        return np.full(self.particles, int(self.valid.sum()))

    # ------------------------------------------------------------------ slots
    def allocate(self, count: int) -> np.ndarray:
        """``count`` free slots (freed ones first, lowest first), marked empty; the caller fills them."""
        reused = [heapq.heappop(self._free_slots) for _ in range(min(count, len(self._free_slots)))]
        fresh = np.arange(self.used, self.used + count - len(reused), dtype=np.int64)
        self.used += fresh.size
        if self.used > self.capacity:
            self._grow_slots(-(-self.used // self.block))
        slots = np.concatenate([np.array(reused, np.int64), fresh])
        self.hits[slots], self.exist[slots], self.label[slots], self.valid[slots] = 0, 0.0, -1, False
        return slots

    def add(self, mean: np.ndarray, cov: np.ndarray, exist: float, hits, labels: np.ndarray) -> np.ndarray:
        """New landmarks ``labels`` ``(m,)`` with Gaussians ``mean``, ``cov`` (per particle ``(P, m, ...)``, or one for
        every particle ``(m, ...)``: :meth:`write`), existence score ``exist`` and ``hits`` (a count or ``(m,)``,
        kept within int32); returns their slots."""
        slots = self.allocate(len(labels))
        self.write(slots, mean, cov)
        self.exist[slots], self.hits[slots] = exist, np.minimum(hits, np.iinfo(np.int32).max)
        self.label[slots], self.valid[slots] = labels, True
        return slots

    def release(self, slots: np.ndarray) -> None:
        """Drop the landmarks in ``slots`` from every particle; their slots go back to :meth:`allocate`."""
        for slot in np.asarray(slots, np.int64).ravel().tolist():
            if self.valid[slot]:
                self.valid[slot] = False
                heapq.heappush(self._free_slots, slot)

    def _grow_slots(self, blocks: int) -> None:
        blocks = max(blocks, 2 * self.table.shape[1])
        extra = blocks - self.table.shape[1]
        self.table = np.concatenate([self.table, np.full((self.particles, extra), -1, np.int32)], 1)
        slots = extra * self.block
        self.hits = np.concatenate([self.hits, np.zeros(slots, np.int32)])
        self.exist = np.concatenate([self.exist, np.zeros(slots)])
        self.label = np.concatenate([self.label, np.full(slots, -1, np.int64)])
        self.valid = np.concatenate([self.valid, np.zeros(slots, bool)])

    # ------------------------------------------------------------------ blocks
    def _reserve_blocks(self, count: int) -> None:
        """At least ``count`` free physical blocks (the pool doubles when short)."""
        if int(self.free_count[0]) >= count:
            return
        old = self.refs.size
        size = max(2 * old, old + count - int(self.free_count[0]), 16)
        self.pool_mean = np.concatenate([self.pool_mean, np.zeros((size - old, self.block, 2))])
        self.pool_cov = np.concatenate([self.pool_cov, np.zeros((size - old, self.block, 2, 2))])
        self.refs = np.concatenate([self.refs, np.zeros(size - old, np.int64)])
        free = np.concatenate([self.free_blocks[: int(self.free_count[0])], np.arange(old, size, dtype=np.int64)])
        self.free_blocks = np.zeros(size, np.int64)
        self.free_blocks[: free.size] = free
        self.free_count[0] = free.size

    def reserve_private(self, slots: np.ndarray) -> np.ndarray:
        """The blocks holding ``slots`` (sorted, distinct), with free physical blocks enough for every particle to
        take a copy of each (:meth:`private`, or a kernel that copies one particle at a time)."""
        blocks = np.unique(np.asarray(slots, np.int64) // self.block)
        self._reserve_blocks(self.particles * blocks.size)
        return blocks

    def private(self, slots: np.ndarray) -> None:
        """Give every particle a block of its own for each block holding one of ``slots`` (copy on write)."""
        blocks = self.reserve_private(slots)
        kernels.private_blocks(self.table, blocks, self.refs, self.pool_mean, self.pool_cov, self.free_blocks,
                               self.free_count)

    def select(self, index: np.ndarray) -> None:
        """Keep particles ``index`` (with repetition): tables are copied, blocks shared; unheld blocks are freed."""
        self.table = self.table[index]
        held = self.table[self.table >= 0]
        self.refs = np.bincount(held, minlength=self.refs.size).astype(np.int64)
        free = np.flatnonzero(self.refs == 0)
        self.free_blocks[: free.size] = free
        self.free_count[0] = free.size

    # ------------------------------------------------------------------ Gaussians
    def gather(self, particle: np.ndarray, slot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(means, covariances) of landmark ``slot`` in ``particle`` (broadcast index arrays; zeros where nothing
        was written)."""
        particle, slot = np.broadcast_arrays(np.asarray(particle, np.int64), np.asarray(slot, np.int64))
        phys = self.table[particle, slot // self.block]
        offset = slot % self.block
        held = phys >= 0
        mean = np.where(held[..., None], self.pool_mean[np.maximum(phys, 0), offset], 0.0)
        cov = np.where(held[..., None, None], self.pool_cov[np.maximum(phys, 0), offset], 0.0)
        return mean, cov

    def write(self, slots: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> None:
        """Set landmark ``slots`` ``(m,)`` of every particle to ``mean`` ``(P, m, 2)`` and ``cov`` ``(P, m, 2, 2)``.

        The same Gaussian for every particle (``mean`` ``(m, 2)``, ``cov`` ``(m, 2, 2)``) written into blocks that no
        particle holds yet is stored once and shared (a map loaded or agreed by all particles)."""
        slots = np.asarray(slots, np.int64)
        blocks = slots // self.block
        if mean.ndim == 2 and np.all(self.table[:, np.unique(blocks)] < 0):
            for b in np.unique(blocks).tolist():
                self._reserve_blocks(1)
                count = int(self.free_count[0]) - 1
                phys = int(self.free_blocks[count])
                self.free_count[0] = count
                self.pool_mean[phys], self.pool_cov[phys] = 0.0, 0.0
                inside = blocks == b
                self.pool_mean[phys, slots[inside] % self.block] = mean[inside]
                self.pool_cov[phys, slots[inside] % self.block] = cov[inside]
                self.table[:, b] = phys
                self.refs[phys] = self.particles
            return
        self.private(slots)
        mean = np.broadcast_to(mean, (self.particles,) + slots.shape + (2,))
        cov = np.broadcast_to(cov, (self.particles,) + slots.shape + (2, 2))
        phys = self.table[:, blocks]
        self.pool_mean[phys, slots % self.block] = mean
        self.pool_cov[phys, slots % self.block] = cov
