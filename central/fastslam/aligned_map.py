"""Every particle's landmark map when a landmark has one slot in all particles (known and shared association),
stored in copy-on-write blocks.

FastSLAM's cost per scan should not grow with the map (Montemerlo et al., "FastSLAM: a factored solution to the
simultaneous localization and mapping problem", §4: particles share the landmarks they have not changed, in a
balanced tree, so resampling costs O(log L) per particle). Here the slots are cut into blocks of ``block`` slots;
each particle has a table naming the physical block that holds each of its blocks, and a block is shared by
every particle whose table names it. A particle that changes a landmark first gets a private copy of that block
(:meth:`AlignedMap.private`): a scan copies the few blocks near the robot, whatever the size of the map.
Resampling copies table entries, never landmarks, and only those of the columns where the particles may disagree
(blocks copied since every particle last held the same one): the rest of every table is the same in all rows.

Only the Gaussians (mean, covariance) differ between particles; hit counts, existence scores, labels and
validity are the same in every particle when every particle updates the same slots, so they are kept once per
slot. Freed slots (dropped tentative landmarks) are reused by the next new landmarks.

The landmarks near a point come from a grid over the slots (:meth:`AlignedMap.near`), so the shared association's
candidate search does not read the whole map (Nieto, Guivant, Nebot and Thrun, "Real time data association for
FastSLAM": a scan's cost must not grow with the map). Each slot is filed under the centre of the box holding its
particles' means (its anchor); no particle's mean lies farther from it than half the box's diagonal (its spread),
and neither does any mixture of them. So the grid cells within the radius plus the spread of a point hold every
landmark whose mixture lies within the radius. A slot whose block was written since is filed again before the
next search.
"""

from __future__ import annotations

import heapq

import numpy as np

from central.fastslam import kernels

BLOCK = 32  # slots per block: a scan's copies stay small, a table stays 1/32 of the map
INDEX_CELLS_PER_RADIUS = 4  # the index's grid cell: a quarter of the first search's radius (a search reads about 100 cells)
UNFILED, IN_CELL, WIDE = 0, 1, 2  # where the spatial index holds a slot
_NO_SLOTS = np.zeros(0, np.int64)


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
    ``label``, ``valid`` and ``serial`` (the order the landmarks were added in); ``used`` slots have ever been
    handed out."""

    def __init__(self, particles: int, block: int = BLOCK, index_cell: float | None = None):
        self.block = block
        self.index_cell = index_cell  # m; None: chosen by the first search (INDEX_CELLS_PER_RADIUS)
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
        self.serial = np.zeros(0, np.int64)
        self.used = 0
        self.added = 0  # landmarks ever added: the next serial
        self._free_slots: list[int] = []
        self.mixed: set[int] = set()  # table columns whose particles may hold different blocks
        self._index_reset()

    def _index_reset(self) -> None:
        """An empty spatial index with every block to be filed (after a restore, as the index is not pickled, and
        when the slots grow)."""
        capacity = self.valid.size
        self._bucket = np.full(1 << max(4, capacity.bit_length()), -1, np.int32)  # hashed grid cell → first slot
        self._following = np.full(capacity, -1, np.int32)  # slot → the next slot in its bucket's list
        self._filed_state = np.zeros(capacity, np.int8)  # per slot: UNFILED, IN_CELL or WIDE
        self._filed_cell = np.zeros((capacity, 2), np.int32)  # per slot: its grid cell when IN_CELL
        self._wide: set[int] = set()  # slots every search checks
        self._dirty: set[int] = set(range(self.table.shape[1]))  # blocks written since they were filed
        self._position = np.full(self.refs.size, -1, np.int64)  # scratch of the mixture kernel: −1 between calls

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        for name in ("_bucket", "_following", "_filed_state", "_filed_cell", "_wide", "_dirty", "_position"):
            state.pop(name, None)
        return state

    def __setstate__(self, state: dict) -> None:
        """Restore a pickled map (a checkpoint), also one written before the spatial index and the mixed
        columns: its landmarks are numbered in slot order until :meth:`set_order` gives the order they were added
        in, its mixed columns are found in the tables. Every block is filed again."""
        self.__dict__.update(state)
        if "serial" not in state:
            self.serial, self.added = np.arange(self.valid.size, dtype=np.int64), self.valid.size
            self.index_cell = None
        if "mixed" not in state:
            self._count_refs()
        self._index_reset()

    def set_order(self, slots: np.ndarray) -> None:
        """Number landmarks ``slots`` 0, 1, … in the order given (the order they were added in)."""
        slots = np.asarray(slots, np.int64)
        self.serial[slots] = np.arange(slots.size)
        self.added = max(self.added, slots.size)

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
                  self.label, self.valid, self.serial, self._bucket, self._following, self._filed_state,
                  self._filed_cell, self._position)
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
        self.register(slots, exist, hits, labels)
        return slots

    def register(self, slots: np.ndarray, exist: float, hits, labels: np.ndarray) -> None:
        """Make the landmarks just written in ``slots`` (:meth:`allocate`, then their Gaussians) valid, with
        existence score ``exist``, ``hits`` and ``labels``, numbered in the order they were added in."""
        self.exist[slots], self.hits[slots] = exist, np.minimum(hits, np.iinfo(np.int32).max)
        self.label[slots], self.valid[slots] = labels, True
        self.serial[slots] = self.added + np.arange(slots.size)
        self.added += slots.size

    def release(self, slots: np.ndarray) -> None:
        """Drop the landmarks in ``slots`` from every particle; their slots go back to :meth:`allocate`."""
        for slot in np.asarray(slots, np.int64).ravel().tolist():
            if self.valid[slot]:
                self.valid[slot] = False
                heapq.heappush(self._free_slots, slot)
                self._dirty.add(slot // self.block)

    def _grow_slots(self, blocks: int) -> None:
        blocks = max(blocks, 2 * self.table.shape[1])
        extra = blocks - self.table.shape[1]
        self.table = np.concatenate([self.table, np.full((self.particles, extra), -1, np.int32)], 1)
        slots = extra * self.block
        self.hits = np.concatenate([self.hits, np.zeros(slots, np.int32)])
        self.exist = np.concatenate([self.exist, np.zeros(slots)])
        self.label = np.concatenate([self.label, np.full(slots, -1, np.int64)])
        self.valid = np.concatenate([self.valid, np.zeros(slots, bool)])
        self.serial = np.concatenate([self.serial, np.zeros(slots, np.int64)])
        self._index_reset()  # filed again at the next search, in a grid sized for the slots

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

    def reserve_private(self, slots: np.ndarray, refile: bool = True) -> np.ndarray:
        """The blocks holding ``slots`` (sorted, distinct), with free physical blocks enough for every particle to
        take a copy of each (:meth:`private`, or a kernel that copies one particle at a time). ``refile``: the
        blocks are filed again in the spatial index before the next search (False: the caller files the slots it
        changes, :meth:`refile_slots`)."""
        held = sorted({slot // self.block for slot in np.asarray(slots, np.int64).tolist()})  # a scan's few slots
        self._reserve_blocks(self.particles * len(held))
        if refile:
            self._dirty.update(held)
        self.mixed.update(held)
        return np.array(held, np.int64)

    def private(self, slots: np.ndarray) -> None:
        """Give every particle a block of its own for each block holding one of ``slots`` (copy on write)."""
        blocks = self.reserve_private(slots)
        kernels.private_blocks(self.table, blocks, self.refs, self.pool_mean, self.pool_cov, self.free_blocks,
                               self.free_count)

    def select(self, index: np.ndarray, compiled: bool = True) -> None:
        """Keep particles ``index`` (with repetition): tables are copied, blocks shared; unheld blocks are freed.

        Only the ``mixed`` columns of the tables (blocks some particle copied since every particle last held
        the same one) can differ between particles: the others are the same in every row and stay as they are,
        so resampling costs the part of the map the particles disagree on, not the whole map."""
        index = np.asarray(index, np.int64)
        if index.size != self.particles:  # the particle count changes: every row is copied
            self.table = self.table[index]
            self._count_refs()
            return
        mixed = np.array(sorted(self.mixed), np.int64)
        if not mixed.size:
            return
        if compiled:  # the kernel; the numpy below is its reference
            uniform = kernels.select_kernel(self.table, mixed, index, self.refs, self.free_blocks, self.free_count)
            self.mixed.difference_update(mixed[uniform].tolist())
            return
        old = self.table[:, mixed]
        new = old[index]
        self.table[:, mixed] = new
        held, count = np.unique(old[old >= 0], return_counts=True)
        self.refs[held] -= count
        held_now, count_now = np.unique(new[new >= 0], return_counts=True)
        self.refs[held_now] += count_now
        freed = held[self.refs[held] == 0]
        start = int(self.free_count[0])
        self.free_blocks[start:start + freed.size] = freed
        self.free_count[0] = start + freed.size
        self.mixed.difference_update(mixed[np.all(new == new[:1], 0)].tolist())

    def _count_refs(self) -> None:
        """Reference counts, free blocks and mixed columns counted again from the tables."""
        held = self.table[self.table >= 0]
        self.refs = np.bincount(held, minlength=self.refs.size).astype(np.int64)
        free = np.flatnonzero(self.refs == 0)
        self.free_blocks[: free.size] = free
        self.free_count[0] = free.size
        self.mixed = set(np.flatnonzero(~np.all(self.table == self.table[:1], 0)).tolist())

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
            self._dirty.update(np.unique(blocks).tolist())
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

    def scratch_positions(self) -> np.ndarray:
        """One entry per physical block, all −1: scratch for :func:`central.fastslam.kernels.marginal_map_kernel`,
        which leaves it all −1 (kept so that a search allocates nothing the size of the map)."""
        if self._position.size != self.refs.size:
            self._position = np.full(self.refs.size, -1, np.int64)
        return self._position

    # ------------------------------------------------------------------ spatial index
    def near(self, point: np.ndarray, radius: float) -> np.ndarray:
        """Slots of the landmarks whose mixture over the particles (any weights) may lie within ``radius`` of
        ``point`` (a superset: the caller computes the mixtures and cuts), in the order they were added in."""
        if self.index_cell is None:
            self.index_cell = max(float(radius) / INDEX_CELLS_PER_RADIUS, 0.1)
        self._file_dirty()
        # a slot's anchor lies within its spread (at most a cell) of any mixture of its particles' means: the cells
        # within radius + cell of the point hold every slot whose mixture may lie within the radius
        wide = np.array(sorted(self._wide), np.int64) if self._wide else _NO_SLOTS
        return kernels.near_kernel(np.asarray(point, float), float(radius), float(self.index_cell), self._bucket,
                                   self._following, self._filed_state, self._filed_cell, self.valid, wide, self.serial)

    def refile_slots(self, slots: np.ndarray, box: np.ndarray) -> None:
        """File ``slots`` again in the spatial index under ``box`` ``(m, 4)``, the box (low x, low y, high x, high y)
        of every particle's mean of each, as the FastSLAM 2.0 kernel leaves it after updating them. Only the slots a
        scan changed are filed again, not their blocks: the blocks' other slots were copied, not changed, and
        resampling only drops particles, so the box they were filed under still holds every particle's mean."""
        if self.index_cell is None:  # no search yet: the first files every block
            self._dirty.update(np.unique(np.asarray(slots, np.int64) // self.block).tolist())
            return
        wide_slots, states = kernels.refile_slots_kernel(np.asarray(slots, np.int64), box, self.valid, self.index_cell,
                                                         self._filed_state, self._filed_cell, self._bucket,
                                                         self._following)
        self._note_wide(wide_slots, states)

    def _note_wide(self, slots: np.ndarray, states: np.ndarray) -> None:
        for slot, state in zip(slots.tolist(), states.tolist()):
            if state == WIDE:
                self._wide.add(slot)
            else:
                self._wide.discard(slot)

    def _file_dirty(self) -> None:
        """File again the slots of the blocks written since the last search (:func:`central.fastslam.kernels.
        refile_kernel`)."""
        if not self._dirty:
            return
        blocks = np.array(sorted(self._dirty), np.int64)
        self._dirty.clear()
        slots, states = kernels.refile_kernel(self.table, self.pool_mean, self.valid, blocks, self.block,
                                              self.index_cell, self._filed_state, self._filed_cell, self._bucket,
                                              self._following)
        self._note_wide(slots, states)
