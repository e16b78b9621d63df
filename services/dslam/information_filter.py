"""The static extended information filter of D-SLAM (Wang, Huang, Dissanayake,
"Implementation Issues and Experimental Evaluation of D-SLAM", §2.2 and §3.2-3.3).

The state is the absolute landmark positions X = (x_1, y_1, ..., x_n, y_n)
only. The information matrix I is exactly sparse: a 2×2 block (i, j) is
non-zero only if landmarks i and j were observed together, because there is
no prediction step. I is kept as a :class:`BlockSparseMatrix` (blocks in a
dict-indexed array, a scipy CSR copy updated in place, and a small CSR of the
blocks created since the last rebuild), and the information vector i beside it.

- :meth:`InformationMap.update_scan` is phase II: z_map around a reference pair,
  new features first placed by eq. 9 (:func:`services.dslam.recast.initialise`),
  then eq. 10; :meth:`InformationMap.update_absolute` is phase I (positions
  measured from the known start pose); both go through :meth:`InformationMap.update`.
- Recovery: the mean and the covariance columns of the landmarks near the
  robots follow each update by its rank-k correction (a warm start that is
  exact for the linearised update), and PCG warm-started there checks the
  mean against I X̂ = i; columns not cached are one solve with a stored sparse
  LU factor of an earlier I, made exact by the cached columns of the landmarks
  the updates since have touched (``column_solver="corrected"``), or, the
  reference, block PCG preconditioned by that factor (made again when it has
  grown stale). Never an inverse of I.
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np
import scipy.linalg.blas
import scipy.sparse as sp
import scipy.sparse.linalg

from robots.gaussian import chi2_quantile, inv2
from services.dslam.recast import choose_reference, initialise, innovation, map_measurement, recast_points, scan_points


def rank_k_update(target: np.ndarray, left: np.ndarray, right: np.ndarray) -> None:
    """target −= left @ right in place (one BLAS call on the C-ordered ``target``, no temporary)."""
    if target.size == 0 or left.shape[1] == 0:
        return
    if not target.flags.c_contiguous:
        target -= left @ right
        return
    # Cᵀ is Fortran-ordered: Cᵀ ← Cᵀ − rightᵀ leftᵀ updates C where it lies.
    scipy.linalg.blas.dgemm(-1.0, right.T, left.T, beta=1.0, c=target.T, overwrite_c=True)


def block_rows(index: np.ndarray) -> np.ndarray:
    """Scalar rows (2k,) of the landmarks ``index`` (k,): 2i, 2i+1, ..."""
    index = np.asarray(index, np.int64)
    return (2 * index[:, None] + np.arange(2)).ravel()


def block_pcg(matvec, precondition, rhs: np.ndarray, start: np.ndarray, tol: np.ndarray | float,
              max_iter: int) -> tuple[np.ndarray, int, bool]:
    """Preconditioned conjugate gradients on every column of ``rhs`` at once.

    Stops when, in every column, the preconditioned residual (the block-Jacobi
    step) is at most ``tol`` (per column) in every entry, or after ``max_iter``
    iterations. Returns the solution, the iterations run and whether it converged.
    """
    x = np.array(start, float, copy=True)
    r = rhs - matvec(x)
    z = precondition(r)
    tol = np.broadcast_to(np.asarray(tol, float), z.shape[1:] if z.ndim > 1 else ())

    def converged(z: np.ndarray) -> bool:
        return bool(np.all(np.max(np.abs(z), axis=0) <= tol))

    if converged(z):
        return x, 0, True
    p = z.copy()
    rz = np.sum(r * z, axis=0)
    for iterations in range(1, max_iter + 1):
        ap = matvec(p)
        pap = np.sum(p * ap, axis=0)
        alpha = np.divide(rz, pap, out=np.zeros_like(rz), where=pap > 0)
        x += alpha * p
        r -= alpha * ap
        z = precondition(r)
        if converged(z):
            return x, iterations, True
        rz_next = np.sum(r * z, axis=0)
        beta = np.divide(rz_next, rz, out=np.zeros_like(rz), where=rz > 0)
        p = z + beta * p
        rz = rz_next
    return x, max_iter, False


class BlockSparseMatrix:
    """A symmetric matrix of 2×2 blocks over n landmarks (both (i, j) and (j, i) stored).

    Blocks live in one growing array indexed by a dict (i, j) → slot. A CSR
    copy of the blocks that existed at its last build is updated in place;
    blocks created since then are multiplied through a small second CSR until
    they are more than ``rebuild_fraction`` of the total, when the CSR is rebuilt
    (amortised O(1) per new block).
    """

    def __init__(self, capacity: int = 256, rebuild_fraction: float = 0.1):
        self.n = 0
        self.rebuild_fraction = rebuild_fraction
        self._slot: dict[tuple[int, int], int] = {}
        self._rows = np.zeros(capacity, np.int64)
        self._cols = np.zeros(capacity, np.int64)
        self._data = np.zeros((capacity, 2, 2))
        self._count = 0
        self._diag = np.zeros(capacity, np.int64)
        self._diag_inverse = np.zeros((capacity, 2, 2))
        self._csr: sp.csr_matrix | None = None
        self._pos = np.zeros((0, 4), np.int64)
        self._built = 0
        self._built_n = 0
        self._pending: sp.csr_matrix | None = None

    @property
    def blocks(self) -> int:
        return self._count

    @property
    def nnz(self) -> int:
        """Stored scalar entries (4 per block)."""
        return 4 * self._count

    def _new_slot(self, i: int, j: int) -> int:
        if self._count == self._rows.shape[0]:
            grow = self._rows.shape[0]
            self._rows = np.concatenate([self._rows, np.zeros(grow, np.int64)])
            self._cols = np.concatenate([self._cols, np.zeros(grow, np.int64)])
            self._data = np.concatenate([self._data, np.zeros((grow, 2, 2))])
        slot = self._count
        self._rows[slot], self._cols[slot] = i, j
        self._slot[(i, j)] = slot
        self._count += 1
        self._pending = None
        return slot

    def grow(self, count: int) -> None:
        """Add ``count`` landmarks with zero blocks."""
        if self.n + count > self._diag.shape[0]:
            grow = max(count, self._diag.shape[0])
            self._diag = np.concatenate([self._diag, np.zeros(grow, np.int64)])
            self._diag_inverse = np.concatenate([self._diag_inverse, np.zeros((grow, 2, 2))])
        for i in range(self.n, self.n + count):
            self._diag[i] = self._new_slot(i, i)
        self.n += count

    def add(self, index: np.ndarray, dense: np.ndarray) -> None:
        """Add a dense symmetric (2m, 2m) matrix over the distinct landmarks ``index`` (m,)."""
        idx = [int(i) for i in index]
        m = len(idx)
        blocks = np.asarray(dense, float).reshape(m, 2, m, 2).transpose(0, 2, 1, 3)
        lookup = self._slot
        slots = np.array([lookup.get((i, j)) if (i, j) in lookup else self._new_slot(i, j) for i in idx for j in idx],
                         np.int64).reshape(m, m)
        self._data[slots] += blocks
        touched = np.asarray(idx, np.int64)
        self._diag_inverse[touched] = inv2(self._data[self._diag[touched]])[0]
        built = slots < self._built
        if built.any():
            self._csr.data[self._pos[slots[built]]] += blocks[built].reshape(-1, 4)
        if not built.all():
            self._pending = None

    def diagonal_blocks(self) -> np.ndarray:
        """The (n, 2, 2) diagonal blocks."""
        return self._data[self._diag[: self.n]]

    def diagonal_inverse(self) -> np.ndarray:
        """Inverses (n, 2, 2) of the diagonal blocks (the block-Jacobi preconditioner), kept up to date by :meth:`add`."""
        return self._diag_inverse[: self.n]

    def block(self, i: int, j: int) -> np.ndarray:
        slot = self._slot.get((i, j))
        return np.zeros((2, 2)) if slot is None else self._data[slot].copy()

    def _assemble(self, start: int, stop: int, n: int) -> tuple[sp.csr_matrix, np.ndarray]:
        """CSR of the slots [start, stop) and, per slot, its 4 positions in the CSR data."""
        rows, cols = self._rows[start:stop], self._cols[start:stop]
        count = stop - start
        order = np.lexsort((cols, rows))
        r, c = rows[order], cols[order]
        per_row = np.bincount(r, minlength=n)
        first = np.concatenate([[0], np.cumsum(per_row)])[:-1]
        rank = np.arange(count) - first[r]
        indptr = np.concatenate([[0], np.cumsum(np.repeat(2 * per_row, 2))])
        top = indptr[2 * r] + 2 * rank
        bottom = indptr[2 * r + 1] + 2 * rank
        positions = np.stack([top, top + 1, bottom, bottom + 1], -1)
        indices = np.empty(4 * count, np.int64)
        indices[positions] = np.stack([2 * c, 2 * c + 1, 2 * c, 2 * c + 1], -1)
        data = np.empty(4 * count)
        data[positions] = self._data[start:stop][order].reshape(-1, 4)
        pos = np.empty((count, 4), np.int64)
        pos[order] = positions
        return sp.csr_matrix((data, indices, indptr), shape=(2 * n, 2 * n)), pos

    def rebuild(self) -> None:
        self._csr, self._pos = self._assemble(0, self._count, self.n)
        self._built, self._built_n = self._count, self.n
        self._pending = None

    def prepare(self) -> None:
        """Rebuild the CSR when the blocks created since the last build are too many."""
        pending = self._count - self._built
        if self._csr is None or pending > max(64, self.rebuild_fraction * self._built):
            self.rebuild()

    def matvec(self, x: np.ndarray) -> np.ndarray:
        """I @ x for x of shape (2n,) or (2n, k)."""
        if self._csr is None:
            self.rebuild()
        nb = 2 * self._built_n
        y = np.zeros_like(x)
        y[:nb] = self._csr @ x[:nb]
        if self._count > self._built:
            if self._pending is None or self._pending.shape[0] != 2 * self.n:
                self._pending, _ = self._assemble(self._built, self._count, self.n)
            y += self._pending @ x
        return y

    def tocsr(self) -> sp.csr_matrix:
        self.rebuild()
        return self._csr.copy()

    def memory_bytes(self) -> int:
        arrays = [self._rows, self._cols, self._data, self._diag, self._diag_inverse, self._pos]
        total = sum(a.nbytes for a in arrays) + 100 * len(self._slot)  # dict entries, roughly
        for m in (self._csr, self._pending):
            if m is not None:
                total += m.data.nbytes + m.indices.nbytes + m.indptr.nbytes
        return int(total)


class _LandmarkSlots:
    """Which landmarks' covariance columns a cache holds, in slots of two columns, least recently used first."""

    def __init__(self, capacity: int):
        self.capacity = capacity
        self.slot: OrderedDict[int, int] = OrderedDict()
        self._free: list[int] = []
        self.pinned: set[int] = set()  # never evicted (the corrected column solves need their columns)

    def __contains__(self, landmark: int) -> bool:
        return landmark in self.slot

    def __len__(self) -> int:
        return len(self.slot)

    def columns(self, landmarks) -> np.ndarray:
        """Positions (2k,) of the columns of ``landmarks`` (all cached) among the cache's columns."""
        slots = np.array([self.slot[int(i)] for i in landmarks], np.int64)
        return (2 * slots[:, None] + np.arange(2)).ravel()

    def touch(self, landmarks) -> None:
        for i in landmarks:
            if int(i) in self.slot:
                self.slot.move_to_end(int(i))

    def _release_beyond_capacity(self, keep) -> list[int]:
        """Forget the least recently used landmarks beyond the capacity, never those in ``keep`` nor pinned ones;
        their slots. The capacity grows to three times the largest request."""
        keep = {int(i) for i in keep}
        self.capacity = max(self.capacity, 3 * len(keep))
        released = []
        for landmark in list(self.slot):
            if len(self.slot) <= self.capacity:
                break
            if landmark not in keep and landmark not in self.pinned:
                released.append(self.slot.pop(landmark))
        return released


class ColumnCache(_LandmarkSlots):
    """Covariance columns (2n, 2) of recently used landmarks, in one dense array, least recently used first out."""

    def __init__(self, capacity: int):
        super().__init__(capacity)
        self.data = np.zeros((0, 0))

    def rows(self, rows: np.ndarray, positions: np.ndarray | slice = slice(None)) -> np.ndarray:
        """P[rows, columns at ``positions``] (every slot by default)."""
        return self.data[rows][:, positions]

    def full(self, positions: np.ndarray, size: int) -> np.ndarray:
        """The full-length columns (size, k) at ``positions``."""
        return self.data[:size, positions]

    def resize_rows(self, rows: int) -> None:
        """Make room for ``rows`` state rows (new landmarks get zero rows, filled by the caller)."""
        if rows > self.data.shape[0]:
            grown = np.zeros((max(rows, 2 * self.data.shape[0]), self.data.shape[1]))
            grown[: self.data.shape[0]] = self.data
            self.data = grown

    def insert(self, landmark: int, column: np.ndarray) -> None:
        """Store the (2n, 2) column of ``landmark`` (a free slot, or a new one)."""
        if landmark in self.slot:
            slot = self.slot[landmark]
        elif self._free:
            slot = self._free.pop()
        else:
            slot = self.data.shape[1] // 2
            self.data = np.concatenate([self.data, np.zeros((self.data.shape[0], 2))], axis=1)
        self.resize_rows(column.shape[0])
        self.data[:, 2 * slot: 2 * slot + 2] = 0.0
        self.data[: column.shape[0], 2 * slot: 2 * slot + 2] = column
        self.slot[landmark] = slot
        self.slot.move_to_end(landmark)

    def nbytes(self) -> int:
        return int(self.data.nbytes)

    def evict(self, keep=()) -> None:
        """Drop least recently used columns beyond the capacity (never those in ``keep``).

        The capacity grows to three times the largest request, so that a sensor
        that sees many landmarks does not solve their columns anew each scan.
        Pinned landmarks stay too (beyond the capacity).
        """
        self._free.extend(self._release_beyond_capacity(keep))


class FactoredColumns(_LandmarkSlots):
    """Covariance columns of recently used landmarks kept as B T: full-length base vectors B, a small mixing matrix T.

    An update of D-SLAM (Wang, Huang, Dissanayake, "D-SLAM: a decoupled solution to simultaneous localization and
    mapping") over landmarks O already cached corrects every cached column by P[:, O] times a small matrix, so the
    columns stay in the span of the base vectors: only T (bases × cached columns) changes, and the mean's change
    P[:, O] w is kept as base coefficients ``shift`` until the mean is read in full. The per-scan work is independent
    of the map size; full-length vectors are touched only to add base vectors (a column solved, new features) and to
    compact the base once evicted columns leave too many unused vectors. The rows of the base vectors are stored
    contiguously (``base`` is bases × state rows), so a few rows of every column are a small gather.
    """

    def __init__(self, capacity: int):
        super().__init__(capacity)
        self.base = np.zeros((0, 0))  # (base capacity, state-row capacity); rows [: self.used] in use
        self.mix = np.zeros((0, 0))  # (base capacity, 2 × slot capacity)
        self.shift = np.zeros(0)  # (base capacity,) coefficients of the mean change not yet added to the mean
        self.scale = np.zeros(0)  # (base capacity,) largest magnitude in each base vector
        self.used = 0
        self.size = 0  # state rows (2n)

    def rows(self, rows: np.ndarray, positions: np.ndarray | slice = slice(None)) -> np.ndarray:
        """P[rows, columns at ``positions``] (every slot by default): |rows| × 2b times 2b × columns."""
        return self.base[: self.used, rows].T @ self.mix[: self.used, positions]

    def diagonal_blocks(self, landmarks: np.ndarray) -> np.ndarray:
        """The (k, 2, 2) blocks P[i, i] of the cached ``landmarks`` (k,), without the k × k submatrix."""
        rows = self.base[: self.used, block_rows(landmarks)].reshape(self.used, -1, 2)
        cols = self.mix[: self.used, self.columns(landmarks)].reshape(self.used, -1, 2)
        return np.einsum("bka,bkc->kac", rows, cols)

    def full(self, positions: np.ndarray, size: int) -> np.ndarray:
        """The full-length columns (size = 2n, k) at ``positions`` of ``mix``."""
        return (self.mix[: self.used, positions].T @ self.base[: self.used, : size]).T

    def shift_rows(self, rows: np.ndarray) -> np.ndarray:
        """The pending mean change at ``rows``."""
        return self.shift[: self.used] @ self.base[: self.used, rows]

    def take_shift(self) -> np.ndarray:
        """The pending mean change (2n,), now cleared."""
        change = self.shift[: self.used] @ self.base[: self.used, : self.size]
        self.shift[:] = 0.0
        return change

    def clear_shift(self) -> None:
        self.shift[:] = 0.0

    def resize_rows(self, rows: int) -> None:
        """Make room for ``rows`` state rows (new rows of the base vectors are zero, filled by the caller)."""
        if rows > self.base.shape[1]:
            grown = np.zeros((self.base.shape[0], max(rows, 2 * self.base.shape[1])))
            grown[: self.used, : self.size] = self.base[: self.used, : self.size]  # the reserved room stays unwritten
            self.base = grown
        self.size = rows

    def __getstate__(self) -> dict:
        """Pickled without the room reserved beyond the base vectors in use (a checkpoint stays small); it is
        reserved again when the next vectors are added."""
        state = dict(self.__dict__)
        used = self.used
        state["base"] = self.base[:used, : self.size].copy()
        state["mix"], state["shift"], state["scale"] = self.mix[:used].copy(), self.shift[:used].copy(), self.scale[:used].copy()
        return state

    def reserved_bases(self) -> int:
        """Base vectors to allocate room for: as many as the cache can use before :meth:`wants_compaction`, and a
        batch more. Growing the base copies it (at 10^5 landmarks 1.6 MB a vector: 0.1–0.4 s within a scan); the
        room beyond ``used`` is zeros the system allocates only when written."""
        return 4 * self.capacity + 128

    def add_bases(self, count: int, zero: bool = True) -> np.ndarray:
        """Append ``count`` base vectors, zero unless the caller writes them whole (``zero`` False); their indices."""
        need = self.used + count
        if need > self.base.shape[0]:
            cap = max(need, 2 * self.base.shape[0], self.reserved_bases())
            base = np.zeros((cap, self.base.shape[1]))
            base[: self.used] = self.base[: self.used]
            mix = np.zeros((cap, self.mix.shape[1]))
            mix[: self.used] = self.mix[: self.used]
            shift, scale = np.zeros(cap), np.zeros(cap)
            shift[: self.used], scale[: self.used] = self.shift[: self.used], self.scale[: self.used]
            self.base, self.mix, self.shift, self.scale = base, mix, shift, scale
        added = np.arange(self.used, need)
        if zero:
            self.base[added] = 0.0
        self.mix[added] = 0.0
        self.shift[added] = 0.0
        self.scale[added] = 0.0
        self.used = need
        return added

    def new_slots(self, landmarks: list[int]) -> np.ndarray:
        """Zero columns for ``landmarks`` (not cached); return their positions (2k,) in ``mix``."""
        for landmark in landmarks:
            if self._free:
                slot = self._free.pop()
            else:
                slot = self.mix.shape[1] // 2
                self.mix = np.concatenate([self.mix, np.zeros((self.mix.shape[0], 2))], axis=1)
            self.slot[landmark] = slot
            self.slot.move_to_end(landmark)
        positions = self.columns(landmarks)
        self.mix[:, positions] = 0.0
        return positions

    def insert_solved(self, landmarks: list[int], columns: np.ndarray) -> None:
        """Store the solved (2n, 2k) columns of ``landmarks`` as new base vectors."""
        bases = self.add_bases(columns.shape[1])
        self.base[bases, : self.size] = columns.T
        self.scale[bases] = np.max(np.abs(columns), axis=0)
        positions = self.new_slots(landmarks)
        self.mix[bases, positions] = 1.0

    def insert_corrected(self, landmarks: list[int], solved: np.ndarray, positions: np.ndarray,
                         coefficients: np.ndarray) -> None:
        """Store the columns solved − P[:, cached at ``positions``] ``coefficients`` of ``landmarks``: ``solved``,
        as rows (2k, up to 2n; the rows beyond are zero), becomes new base vectors, the correction only mixes the
        cached columns' coefficients."""
        correction = self.mix[: self.used, positions] @ coefficients
        used = self.used
        bases = self.add_bases(solved.shape[0], zero=False)
        known = solved.shape[1]
        self.base[used: used + bases.size, :known] = solved
        self.base[used: used + bases.size, known:] = 0.0
        self.scale[bases] = np.max(np.abs(solved), axis=1)
        new = self.new_slots(landmarks)
        self.mix[bases, new] = 1.0
        self.mix[:used, new] = -correction

    def evict(self, keep=()) -> None:
        """As :meth:`ColumnCache.evict` (pinned landmarks stay); the columns dropped are zeroed (their base vectors stay until compaction)."""
        for slot in self._release_beyond_capacity(keep):
            self.mix[:, 2 * slot: 2 * slot + 2] = 0.0
            self._free.append(slot)

    def precision_loss(self) -> float:
        """How much larger the terms of B T are than the variances it gives (cached columns): the factor by which
        rounding in B T exceeds rounding in explicit columns. It grows as updates shrink the covariances."""
        if not self.slot:
            return 1.0
        rows = block_rows(np.fromiter(self.slot.keys(), np.int64, len(self.slot)))
        positions = self.columns(self.slot.keys())
        terms = self.scale[: self.used] @ np.abs(self.mix[: self.used, positions])
        variances = np.einsum("bk,bk->k", self.base[: self.used, rows], self.mix[: self.used, positions])
        return float(np.max(terms / np.maximum(np.abs(variances), 1e-300)))

    def wants_compaction(self, precision_loss: float) -> bool:
        """Time for :meth:`compact`: more base vectors than twice the cached columns (and some slack), or B T
        losing more than ``precision_loss`` in relative precision."""
        return self.used > 4 * len(self.slot) + 64 or self.precision_loss() > precision_loss

    def compact(self) -> None:
        """Make the cached columns themselves the base (B ← B T, T ← 1); the pending shift must be taken first."""
        landmarks = list(self.slot)
        positions = self.columns(landmarks) if landmarks else np.zeros(0, np.int64)
        rows = max(positions.size, self.reserved_bases())
        base = np.zeros((rows, self.base.shape[1]))
        base[: positions.size, : self.size] = self.mix[: self.used, positions].T @ self.base[: self.used, : self.size]
        self.base, self.used = base, positions.size
        self.scale = np.zeros(rows)
        self.scale[: positions.size] = np.max(np.abs(base[: positions.size]), axis=1) if positions.size else 0.0
        self.mix = np.eye(rows, positions.size)
        self.shift = np.zeros(rows)
        self.slot = OrderedDict((landmark, k) for k, landmark in enumerate(landmarks))
        self._free = []

    def nbytes(self) -> int:
        """Bytes of the base vectors in use and of the mixing matrix (the room reserved beyond them is not written)."""
        return int(self.used * self.base.shape[1] * self.base.itemsize + self.mix.nbytes + self.shift.nbytes)


class ColumnJob:
    """Covariance columns solved off the scan (a worker thread between scans, :meth:`InformationMap.column_job`).

    Only the expensive part: b = I₀⁻¹ e_j for each landmark j, one multi-column solve with the stored sparse LU
    factor of I₀ (SuperLU releases the GIL while it solves, and only reads the factor). Made exact for the updates
    since and stored in the cache by :meth:`InformationMap.take_columns`, on the thread that owns the map.
    """

    def __init__(self, factor, size: int, landmarks: list[int]):
        self.factor, self.size, self.landmarks = factor, size, landmarks

    def run(self) -> np.ndarray:
        """The solves as rows (2k, size), the layout of the cache's base vectors; touches nothing but the factor
        it was given."""
        k = len(self.landmarks)
        rhs = np.zeros((self.size, 2 * k))
        rhs[block_rows(np.array(self.landmarks, np.int64)), np.arange(2 * k)] = 1.0
        return np.ascontiguousarray(self.factor.solve(rhs).T)


class InformationMap:
    """Information matrix, information vector and recovered mean of the absolute landmark map.

    Recovery (§3.2-3.3). Each update needs the covariance columns of the old
    landmarks it involves; they are kept in a :class:`FactoredColumns` (``columns="factored"``)
    or, the reference, a :class:`ColumnCache` of full columns (``columns="explicit"``); a column
    not there is solved by block PCG from a warm start (the column of the
    nearest cached landmark, preconditioned by a stored sparse LU factor of an
    earlier I). With those columns, the rank-k correction of the
    update gives the new mean and the new cached columns exactly (for the
    linearised measurement); the mean is then checked against I X̂ = i by PCG
    warm-started there, which usually stops at once: :meth:`maintain` does that every
    ``check_every`` scans (the check is one product with I, O(nnz)). Nothing inverts I.
    """

    columns_prefetched = 0  # class defaults: a map checkpointed before column jobs existed carries on
    columns_prefetch_dropped = 0

    def __init__(self, tol: float = 1e-5, max_iter: int = 200, column_tol: float = 1e-9,
                 column_max_iter: int = 100, cache_columns: int = 64, track_columns: bool = True,
                 refactor_iterations: int = 15, columns: str = "factored", check_every: int = 1,
                 precision_loss: float = 100.0, column_solver: str = "corrected", correction_limit: int = 64):
        if columns not in ("factored", "explicit"):
            raise ValueError(f"columns must be factored or explicit, not {columns!r}")
        if column_solver not in ("corrected", "pcg"):
            raise ValueError(f"column_solver must be corrected or pcg, not {column_solver!r}")
        self.column_solver = column_solver
        self.correction_limit = correction_limit
        self._delta: dict[tuple[int, int], np.ndarray] = {}  # I − (the factored I), by 2×2 block
        self._touched: dict[int, None] = {}  # landmarks whose rows of I changed since the factorisation
        self.matrix = BlockSparseMatrix()
        self.track_columns = track_columns
        self.refactor_iterations = refactor_iterations
        self._factor = None
        self._factor_size = 0
        self.factorisations = 0
        self.vector = np.zeros(0)
        self._mean = np.zeros(0)
        self.tol = tol
        self.max_iter = max_iter
        self.column_tol = column_tol
        self.column_max_iter = column_max_iter
        self.factored = columns == "factored"
        self.cache = FactoredColumns(cache_columns) if self.factored else ColumnCache(cache_columns)
        self.check_every = check_every
        self.precision_loss = precision_loss
        self._since_check = 0
        self._unchecked = False
        self.recovery_iterations = 0
        self.column_iterations = 0
        self.column_solves = 0
        self.column_iterations_total = 0
        self.column_direct_solves = 0
        self.recovery_unconverged = 0
        self.columns_prefetched = 0  # columns a ColumnJob solved off the scan and the cache took
        self.columns_prefetch_dropped = 0  # ... and that it could not take (the factor changed meanwhile)

    @property
    def n(self) -> int:
        return self.matrix.n

    @property
    def mean(self) -> np.ndarray:
        """The recovered mean (2n,), with the change the factored columns still hold added first."""
        if self.factored and np.any(self.cache.shift[: self.cache.used]):
            self._mean += self.cache.take_shift()
        return self._mean

    @mean.setter
    def mean(self, value: np.ndarray) -> None:
        self._mean = value
        if self.factored:
            self.cache.clear_shift()

    @property
    def means(self) -> np.ndarray:
        """Current landmark estimates (n, 2) (a view of the recovered mean)."""
        return self.mean.reshape(-1, 2)

    def stale_means(self) -> np.ndarray:
        """The landmark estimates (n, 2) without the change the factored columns still hold (the last scans' small
        corrections): good enough to choose landmarks by distance, without the O(n) update of the whole mean."""
        return self._mean.reshape(-1, 2)

    def landmark_means(self, index) -> np.ndarray:
        """Estimates (k, 2) of the landmarks ``index`` (k,), without bringing the whole mean up to date."""
        rows = block_rows(np.asarray(index, np.int64).reshape(-1))
        values = self._mean[rows]
        if self.factored:
            values = values + self.cache.shift_rows(rows)
        return values.reshape(-1, 2)

    def use_columns(self, columns: str, capacity: int) -> None:
        """Keep covariance columns as ``columns`` (factored or explicit) from now on, starting from an empty cache."""
        self._mean = self.mean
        self.factored = columns == "factored"
        self.cache = FactoredColumns(capacity) if self.factored else ColumnCache(capacity)
        self.cache.resize_rows(2 * self.n)
        self._factor = None  # the new cache lacks the touched columns a corrected solve needs
        self._forget_changes()

    # ---------------------------------------------------------------- updates
    def update(self, old: np.ndarray, jacobian: np.ndarray, residual: np.ndarray, noise: np.ndarray,
               new_positions: np.ndarray | None = None, gate: float | None = None) -> np.ndarray | None:
        """EIF update (eq. 10) with a measurement over old landmarks and new features; returns the new indices.

        ``jacobian`` (k, 2m_old + 2m_new) has its columns in the order [old..., new...]
        and is evaluated at the current estimates of the old landmarks and at
        ``new_positions`` (m_new, 2), the first estimates of the new features
        (eq. 9); ``residual`` is z − h at that point (angles wrapped); ``noise`` the
        measurement covariance. Each new feature must own exactly two rows of the
        measurement (the rows that involve it), through an invertible 2×2 block.

        I += ∇Hᵀ R⁻¹ ∇H and i += ∇Hᵀ R⁻¹ (ν + ∇H X̂); the mean and the cached
        columns follow by the rank-k correction (see the class docstring).

        Without column tracking (``track_columns`` False: a map built in bulk),
        only I and i change and the mean waits for :meth:`recover`.

        With ``gate``, the update is refused (None returned, nothing changed) when
        the joint NIS of the rows predicted by the map, νᵀ(∇H P ∇Hᵀ + R)⁻¹ν, exceeds
        it: one wrong association among the reference features would distort
        every row of z_map.
        """
        old = np.asarray(old, np.int64)
        if np.unique(old).shape[0] != old.shape[0]:
            raise ValueError("a landmark appears twice in one measurement")
        new_positions = np.zeros((0, 2)) if new_positions is None else np.asarray(new_positions, float).reshape(-1, 2)
        m_old, m_new = old.shape[0], new_positions.shape[0]
        jacobian = np.asarray(jacobian, float)
        residual = np.asarray(residual, float)
        noise = np.asarray(noise, float)
        split = 2 * m_old
        new_rows = np.any(jacobian[:, split:] != 0.0, axis=1) if m_new else np.zeros(jacobian.shape[0], bool)
        if int(new_rows.sum()) != 2 * m_new:
            raise ValueError("each new feature must own exactly two measurement rows")
        linearised = np.concatenate([self.landmark_means(old).ravel(), new_positions.ravel()])
        old_rows = ~new_rows
        added = np.zeros(0, np.int64)
        if not self.track_columns:
            added = self._grow(new_positions)
            self._unchecked = True
        else:
            if m_old:
                self._ensure_columns(old)
            a = jacobian[old_rows][:, :split]
            delta = np.zeros(split)
            if m_old and old_rows.any():
                delta = self._correct_old(old, a, residual[old_rows], noise[np.ix_(old_rows, old_rows)], gate)
                if delta is None:
                    return None
            if m_new:
                added = self._add_new(old, a, jacobian[new_rows], residual, noise, new_rows, new_positions, delta)
        chain = np.concatenate([old, added])
        weighted = np.linalg.solve(noise, np.column_stack([jacobian, residual + jacobian @ linearised]))
        product = jacobian.T @ weighted
        dense = 0.5 * (product[:, :-1] + product[:, :-1].T)
        self.matrix.add(chain, dense)
        if self.column_solver == "corrected" and self._factor is not None:
            self._record_change(chain, dense)
        self.vector[block_rows(chain)] += product[:, -1]
        self.cache.touch(chain)
        self._evict(chain)
        return added

    def _correct_old(self, old: np.ndarray, a: np.ndarray, nu: np.ndarray, noise: np.ndarray,
                     gate: float | None) -> np.ndarray | None:
        """Kalman form of the update on the old landmarks: mean change, cached columns corrected.

        Returns the mean change at the old landmarks' rows, or None, changing
        nothing, when the NIS of ``nu`` exceeds ``gate``.
        """
        if self.factored:
            return self._correct_old_factored(old, a, nu, noise, gate)
        size = 2 * self.n
        cols = self.cache.data
        p_old = cols[:size, self.cache.columns(old)]
        rows_old = block_rows(old)
        s = a @ p_old[rows_old] @ a.T + noise
        solved = np.linalg.solve(s, np.column_stack([(p_old @ a.T).T, nu]))
        if gate is not None and float(nu @ solved[:, -1]) > gate:
            return None
        gain = solved[:, :-1].T  # P_O Aᵀ S⁻¹ (2n, k)
        delta = gain @ nu
        self.mean += delta
        rank_k_update(cols[:size], gain, a @ cols[rows_old])  # every slot, free ones too: one pass
        return delta[rows_old]

    def _correct_old_factored(self, old: np.ndarray, a: np.ndarray, nu: np.ndarray, noise: np.ndarray,
                              gate: float | None) -> np.ndarray | None:
        """:meth:`_correct_old` on :class:`FactoredColumns`: P ← P − P_O Aᵀ S⁻¹ A P_O· becomes T ← T − T_O Aᵀ S⁻¹ A P_O·,
        and the mean change P_O Aᵀ S⁻¹ ν is kept as base coefficients T_O Aᵀ S⁻¹ ν (work independent of n). The
        gain is formed as in the explicit update (S solved against (P_O Aᵀ)ᵀ), so that both round alike."""
        cache = self.cache
        rows_old = block_rows(old)
        positions = cache.columns(old)
        p_rows = cache.rows(rows_old)  # P[O, every slot]
        p_old = p_rows[:, positions]
        s = a @ p_old @ a.T + noise
        mix_old = cache.mix[: cache.used, positions]
        rows = np.vstack([mix_old @ a.T, p_old @ a.T])  # T_O Aᵀ over P_OO Aᵀ: the gains' coefficients and rows O
        solved = np.linalg.solve(s, np.column_stack([rows.T, nu]))
        if gate is not None and float(nu @ solved[:, -1]) > gate:
            return None
        gain = solved[:, :-1].T  # T_O Aᵀ S⁻¹ over P_OO Aᵀ S⁻¹
        change = gain @ nu
        cache.shift[: cache.used] += change[: cache.used]
        cache.mix[: cache.used] -= gain[: cache.used] @ (a @ p_rows)
        return change[cache.used:]

    def _add_new(self, old, a, jac_new, residual, noise, new_rows, new_positions, delta_old) -> np.ndarray:
        """Append the new features with their exact mean and covariance columns.

        Rows of the new features: z_F = B x_O + C f + w_F, with w_F correlated
        with the old rows' noise: w_F = K w_O + ε, K = R_FO R_OO⁻¹. The flat prior
        of f makes f = C⁻¹(z_F − K z_O − (B − K A) x_O − ε): its cross-covariance
        with the state is −P_O Mᵀ and its covariance M P_OO Mᵀ + C⁻¹ Σ_ε C⁻ᵀ,
        with M = C⁻¹ (B − K A) and Σ_ε = R_FF − K R_OF.
        """
        m_old = old.shape[0]
        split = 2 * m_old
        old_rows = ~new_rows
        b, c = jac_new[:, :split], jac_new[:, split:]
        r_ff = noise[np.ix_(new_rows, new_rows)]
        r_fo = noise[np.ix_(new_rows, old_rows)]
        if old_rows.any():
            gain = np.linalg.solve(noise[np.ix_(old_rows, old_rows)], r_fo.T).T
        else:
            gain = np.zeros((r_fo.shape[0], 0))
        c_inv = np.linalg.inv(c)  # block-diagonal 2×2 blocks of the new features, not the information matrix
        m = c_inv @ (b - gain @ a)
        rows_old = block_rows(old)
        shift = c_inv @ (residual[new_rows] - gain @ residual[old_rows]) - m @ delta_old
        means = new_positions.ravel() + shift
        own = c_inv @ (r_ff - gain @ r_fo.T) @ c_inv.T
        if self.factored:
            return self._add_new_factored(old, m, means, own)
        size = 2 * self.n
        cols = self.cache.data
        p_old = cols[:size, self.cache.columns(old)] if m_old else np.zeros((size, 0))
        new_block = m @ p_old[rows_old] @ m.T + own
        cross = -p_old @ m.T
        extension = -m @ cols[rows_old] if m_old else 0.0
        added = self._grow(means.reshape(-1, 2))
        self.cache.data[size: 2 * self.n] = extension
        full = np.vstack([cross, 0.5 * (new_block + new_block.T)])
        for j, landmark in enumerate(added.tolist()):
            self.cache.insert(landmark, full[:, 2 * j: 2 * j + 2])
        return added

    def _add_new_factored(self, old: np.ndarray, m: np.ndarray, means: np.ndarray, own: np.ndarray) -> np.ndarray:
        """:meth:`_add_new` on :class:`FactoredColumns`: the new rows of every base vector are −M times its old rows
        (so every cached column gets −M P_O·), the new columns mix the old ones by −T_O Mᵀ, and two unit base
        vectors per new feature carry its own noise C⁻¹ Σ_ε C⁻ᵀ."""
        cache = self.cache
        used = cache.used
        base_rows = -(cache.base[:used, block_rows(old)] @ m.T)
        mix_new = -(cache.mix[:used, cache.columns(old)] @ m.T) if old.size else np.zeros((used, m.shape[0]))
        added = self._grow(means.reshape(-1, 2))
        rows = block_rows(added)
        cache.base[:used, rows] = base_rows
        if base_rows.size:
            cache.scale[:used] = np.maximum(cache.scale[:used], np.max(np.abs(base_rows), axis=1))
        self._mean[rows] -= cache.shift[:used] @ base_rows  # the pending change does not concern the new rows
        bases = cache.add_bases(rows.size)
        cache.base[bases, rows] = 1.0
        cache.scale[bases] = 1.0
        positions = cache.new_slots(added.tolist())
        cache.mix[:used, positions] = mix_new
        cache.mix[np.ix_(bases, positions)] = 0.5 * (own + own.T)
        return added

    def _grow(self, positions: np.ndarray) -> np.ndarray:
        """Append landmarks with zero information and the given estimates; return their indices."""
        start = self.n
        self.matrix.grow(positions.shape[0])
        self.vector = np.concatenate([self.vector, np.zeros(2 * positions.shape[0])])
        self._mean = np.concatenate([self._mean, positions.ravel()])
        self.cache.resize_rows(2 * self.n)
        return np.arange(start, self.n)

    def _evict(self, keep) -> None:
        """Drop least recently used columns; compact the factored base when it holds too many unused vectors."""
        self.cache.evict(keep=keep)
        if self.factored and self.cache.wants_compaction(self.precision_loss):
            self._mean = self.mean
            self.cache.compact()

    def update_absolute(self, old: np.ndarray, old_positions: np.ndarray, new_positions: np.ndarray,
                        cov: np.ndarray) -> np.ndarray:
        """Phase I: positions measured from a known pose, of old landmarks and of new features; returns new indices.

        ``cov`` is the joint covariance (2(m_old + m_new) square) of all the positions, old first.
        """
        old = np.asarray(old, np.int64)
        old_positions = np.asarray(old_positions, float).reshape(-1, 2)
        new_positions = np.asarray(new_positions, float).reshape(-1, 2)
        residual = np.concatenate([old_positions.ravel() - self.mean[block_rows(old)], np.zeros(new_positions.size)])
        jacobian = np.eye(residual.shape[0])
        return self.update(old, jacobian, residual, cov, new_positions)

    def update_scan(self, observations: np.ndarray, noise: np.ndarray, mapped: np.ndarray, index: np.ndarray,
                    new: np.ndarray, min_reference_distance: float = 0.0,
                    gate_probability: float | None = None) -> tuple[np.ndarray, ...] | None:
        """Phase II with one scan: reference pair, z_map (eq. 3), new features (eq. 9), update (eq. 10).

        ``mapped`` are the rows of ``observations`` (m, 2) of mapped landmarks,
        ``index`` their map indices, ``new`` the rows of features to add. Returns
        (indices given to the new features, map indices in z_map order, z_map,
        R_map) or None when fewer than two mapped landmarks (far enough apart) are
        seen, when a feature lies on the first reference (z_map not finite), or
        when z_map fails the χ² test at ``gate_probability``.
        """
        points, covs = scan_points(observations, noise)
        m = points.shape[0]
        joint = np.zeros((m, 2, m, 2))
        joint[np.arange(m), :, np.arange(m), :] = covs
        return self.update_points(points, joint.reshape(2 * m, 2 * m), mapped, index, new, min_reference_distance,
                                  gate_probability)

    def update_points(self, points: np.ndarray, cov: np.ndarray, mapped: np.ndarray, index: np.ndarray,
                      new: np.ndarray, min_reference_distance: float = 0.0,
                      gate_probability: float | None = None) -> tuple[np.ndarray, ...] | None:
        """Phase II with points (m, 2) in any robot-attached frame and their joint covariance (2m, 2m).

        As :meth:`update_scan` (which calls it with one scan's points): the rows
        ``mapped`` are landmarks ``index``, the rows ``new`` features to add.
        """
        mapped, index, new = (np.asarray(a, np.int64) for a in (mapped, index, new))
        if mapped.size < 2:
            return None
        points = np.asarray(points, float)
        cov = np.asarray(cov, float)
        spread = np.einsum("kaka->k", cov.reshape(points.shape[0], 2, points.shape[0], 2))
        first, second = choose_reference(points, mapped, spread)
        if np.linalg.norm(points[first] - points[second]) < min_reference_distance:
            return None
        where = dict(zip(mapped.tolist(), index.tolist()))
        others = [k for k in mapped.tolist() if k not in (first, second)]
        order = np.array([first, second, *others, *new.tolist()], np.int64)
        rows = np.stack([2 * order, 2 * order + 1], -1).ravel()
        with np.errstate(divide="ignore", invalid="ignore"):  # checked just below
            z_map, r_map = recast_points(points[order], cov[np.ix_(rows, rows)])
        if not (np.all(np.isfinite(z_map)) and np.all(np.isfinite(r_map))):
            return None  # a feature on the first reference has no bearing from it: refused, never NaN in the map
        old = np.array([where[first], where[second], *[where[k] for k in others]], np.int64)
        positions = np.zeros((0, 2))
        if new.size:
            rows = 2 * (len(others) + np.arange(new.size)) + 1
            reference = self.landmark_means(old[:2])
            positions = initialise(reference[0], reference[1], np.stack([z_map[rows], z_map[rows + 1]], -1))
        predicted, jac = map_measurement(np.vstack([self.landmark_means(old), positions]))
        gate = None
        if gate_probability is not None:
            gate = chi2_quantile(gate_probability, z_map.shape[0] - 2 * new.size)
        added = self.update(old, jac.reshape(jac.shape[0], -1), innovation(z_map, predicted), r_map, positions, gate)
        if added is None:
            return None
        return added, np.concatenate([old, added]), z_map, r_map

    # --------------------------------------------------------------- recovery
    def _precondition(self):
        inverse = self.matrix.diagonal_inverse()

        def apply(r: np.ndarray) -> np.ndarray:
            if r.ndim == 1:
                return np.einsum("nab,nb->na", inverse, r.reshape(-1, 2)).ravel()
            k = r.shape[1]
            return np.einsum("nab,nbk->nak", inverse, r.reshape(-1, 2, k)).reshape(-1, k)

        return apply

    def maintain(self) -> int:
        """Once per scan: :meth:`recover` on every ``check_every``-th call, or at once after updates the cached
        columns did not follow (``track_columns`` off); return the iterations run.

        Between checks the rank-k corrections keep the mean exact for the linearised updates, so
        the check (one product with I, O(nnz)) only guards against drift."""
        self._since_check += 1
        if self._unchecked or self._since_check >= self.check_every:
            return self.recover()
        return 0

    def recover(self, max_iter: int | None = None) -> int:
        """Solve I X̂ = i by PCG warm-started at the current X̂ (§3.3); return the iterations run."""
        self._since_check, self._unchecked = 0, False
        if self.n == 0:
            return 0
        self.matrix.prepare()
        self.mean, iterations, converged = block_pcg(self.matrix.matvec, self._precondition(), self.vector, self.mean,
                                                     self.tol, self.max_iter if max_iter is None else max_iter)
        self.recovery_iterations = iterations
        self.recovery_unconverged += not converged
        return iterations

    def __getstate__(self) -> dict:
        """Pickled without the sparse LU factor (SuperLU does not pickle): a restored map factorises afresh when it
        next needs the factor, so its covariance columns agree with the original's to the solver's tolerance."""
        state = dict(self.__dict__)
        state["_factor"], state["_factor_size"] = None, 0
        return state

    def factorise(self) -> None:
        """Sparse LU factorisation of the current I (symmetric ordering, diagonal pivots: a Cholesky in effect).

        Kept as the preconditioner of the covariance-column solves while it serves
        them in few iterations; the matrix keeps changing, the factor does not.
        """
        self._factor = scipy.sparse.linalg.splu(self.matrix.tocsr().tocsc(), permc_spec="MMD_AT_PLUS_A",
                                                diag_pivot_thresh=0.0, options={"SymmetricMode": True})
        self._factor_size = 2 * self.n
        self.factorisations += 1
        self._forget_changes()

    def _forget_changes(self) -> None:
        """Start recording the changes of I afresh (a new factor, or a cache without the touched columns)."""
        self._delta, self._touched = {}, {}
        self.cache.pinned = set()

    def _record_change(self, chain: np.ndarray, dense: np.ndarray) -> None:
        """Add the (2m, 2m) information ``dense`` over the landmarks ``chain`` to the change since the factorisation
        and pin their columns; past ``correction_limit`` touched landmarks, drop the factor (made afresh when next needed)."""
        idx = [int(i) for i in chain]
        m = len(idx)
        blocks = dense.reshape(m, 2, m, 2)
        for a, i in enumerate(idx):
            for b, j in enumerate(idx):
                previous = self._delta.get((i, j))
                self._delta[(i, j)] = blocks[a, :, b, :] if previous is None else previous + blocks[a, :, b, :]
            self._touched[i] = None
        self.cache.pinned.update(idx)
        if len(self._touched) > self.correction_limit:
            self._factor = None
            self._forget_changes()

    def _change_matrix(self, touched: np.ndarray) -> np.ndarray:
        """The recorded change of I on the rows and columns of ``touched`` (dense, 2u × 2u)."""
        where = {int(t): k for k, t in enumerate(touched)}
        change = np.zeros((touched.size, 2, touched.size, 2))
        for (i, j), block in self._delta.items():
            change[where[i], :, where[j], :] = block
        return change.reshape(2 * touched.size, 2 * touched.size)

    def solve_exactly(self) -> None:
        """Recover the mean by one sparse LU solve (after a map built in bulk); the factor is kept."""
        self.factorise()
        self.mean = self._factor.solve(self.vector)

    def _factor_precondition(self):
        """The stored LU factor on the landmarks it knows, block Jacobi on those added since."""
        factor, size = self._factor, self._factor_size
        jacobi = self._precondition()

        def apply(r: np.ndarray) -> np.ndarray:
            out = jacobi(r)
            out[:size] = factor.solve(np.ascontiguousarray(r[:size]))
            return out

        return apply

    def _ensure_columns(self, landmarks: np.ndarray) -> None:
        """Solve the covariance columns of ``landmarks`` not in the cache (:meth:`_solve_corrected`, or the reference:).

        Block PCG warm-started from the column of the nearest cached landmark,
        preconditioned by a stored sparse LU factor of I (made afresh when it has
        grown stale: more than ``refactor_iterations`` iterations, or no convergence).
        """
        missing = [int(i) for i in landmarks if int(i) not in self.cache]
        self.cache.touch([int(i) for i in landmarks if int(i) in self.cache])
        if not missing:
            return
        if self.column_solver == "corrected":
            self._solve_corrected(missing)
            return
        missing_arr = np.array(missing, np.int64)
        size, k = 2 * self.n, len(missing)
        self.matrix.prepare()
        rhs = np.zeros((size, 2 * k))
        rhs[block_rows(missing_arr), np.arange(2 * k)] = 1.0
        start = np.zeros((size, 2 * k))
        cached = np.fromiter(self.cache.slot.keys(), np.int64, len(self.cache))
        diag_inverse = self.matrix.diagonal_inverse()
        cached_means, missing_means = self.landmark_means(cached), self.landmark_means(missing_arr)
        for j, lm in enumerate(missing):
            if cached.size:
                nearest = int(cached[np.argmin(np.sum((cached_means - missing_means[j]) ** 2, axis=1))])
                start[:, 2 * j: 2 * j + 2] = self.cache.full(self.cache.columns([nearest]), size)
            else:
                start[2 * lm: 2 * lm + 2, 2 * j: 2 * j + 2] = diag_inverse[lm]
        scale = np.abs(start[block_rows(missing_arr), np.arange(2 * k)])
        if self._factor is None:
            self.factorise()
        columns, iterations, converged = block_pcg(self.matrix.matvec, self._factor_precondition(), rhs, start,
                                                   self.column_tol * np.maximum(scale, 1e-12), self.column_max_iter)
        if not converged or iterations > self.refactor_iterations:
            self._factor = None
        if not converged:  # the rank-k corrections need exact columns: a fresh factor solves them
            self.factorise()
            columns = self._factor.solve(rhs)
            self.column_direct_solves += k
        self.column_iterations = iterations
        self.column_iterations_total += iterations
        self.column_solves += k
        if self.factored:
            self.cache.insert_solved(missing, columns)
            return
        for j, lm in enumerate(missing):
            self.cache.insert(lm, columns[:, 2 * j: 2 * j + 2])

    def _solve_corrected(self, missing: list[int]) -> None:
        """Covariance columns of ``missing`` (not cached) by one solve with the stored factor, made exact.

        The factor is of an earlier I₀; since then I = I₀ + ΔI with ΔI non-zero only on the landmarks U touched by
        the updates. For b = I₀⁻¹ e_j (the solve), I b = e_j + ΔI b, so I⁻¹ e_j = b − P[:, U] (ΔI b)[U]: the
        cached columns of U (pinned since they were touched) correct b exactly, without iterations. All of a
        scan's columns are one multi-column solve. The factor is made afresh only when there is none (or a
        touched landmark's column is not cached, after updates the columns did not follow).
        """
        touched = np.fromiter(self._touched, np.int64, len(self._touched))
        missing_arr = np.array(missing, np.int64)
        if (self._factor is None or any(int(t) not in self.cache for t in touched)
                or 2 * int(missing_arr.max()) + 2 > self._factor_size):
            self.factorise()
            touched = np.zeros(0, np.int64)
        self._insert_corrected(missing, ColumnJob(self._factor, self._factor_size, missing).run(), touched)
        self.column_iterations = 0
        self.column_solves += len(missing)

    def _insert_corrected(self, missing: list[int], raw: np.ndarray, touched: np.ndarray) -> None:
        """Cache the columns of ``missing`` from their solves ``raw`` = I₀⁻¹ e_j, as rows (2k, the factor's size:
        the landmarks added since are zero), corrected by the cached columns of the ``touched`` landmarks (see
        :meth:`_solve_corrected`)."""
        size, known = 2 * self.n, raw.shape[1]
        rows = block_rows(touched)
        at_touched = np.zeros((rows.size, raw.shape[0]))
        inside = rows < known
        at_touched[inside] = raw[:, rows[inside]].T
        coefficients = self._change_matrix(touched) @ at_touched
        positions = self.cache.columns(touched) if touched.size else np.zeros(0, np.int64)
        if self.factored:
            self.cache.insert_corrected(missing, raw, positions, coefficients)
            return
        solved = np.zeros((size, raw.shape[0]))
        solved[:known] = raw.T
        columns = solved - self.cache.full(positions, size) @ coefficients
        for j, lm in enumerate(missing):
            self.cache.insert(lm, columns[:, 2 * j: 2 * j + 2])

    def column_job(self, landmarks, limit: int) -> ColumnJob | None:
        """The solve that would cache the columns of up to ``limit`` of ``landmarks`` (nearest first) not cached
        yet, for a worker thread to run between scans (:meth:`take_columns` stores them); None when there is
        nothing to do, or no factor to do it with (a scan makes one when it needs it).

        ``landmarks`` is the working set the robots will soon need: those cached count as used now, and the
        cache grows to hold it beside the columns pinned for the correction (else each job would evict the last
        one's columns)."""
        if self.column_solver != "corrected" or self._factor is None:
            return None
        landmarks = list(dict.fromkeys(int(i) for i in landmarks))
        self.cache.touch(landmarks)
        self.cache.capacity = max(self.cache.capacity, len(landmarks) + len(self.cache.pinned))
        missing = self.solvable_off_scan(landmarks)
        return ColumnJob(self._factor, self._factor_size, missing[:limit]) if missing else None

    def solvable_off_scan(self, landmarks) -> list[int]:
        """Those of ``landmarks`` whose columns a :class:`ColumnJob` could solve now: not cached, and known to the
        stored factor (none without a factor, or with the PCG reference)."""
        if self.column_solver != "corrected" or self._factor is None:
            return []
        return [i for i in dict.fromkeys(int(i) for i in landmarks)
                if i not in self.cache and 2 * i + 2 <= self._factor_size]

    def take_columns(self, job: ColumnJob, raw: np.ndarray) -> int:
        """Cache the columns a :class:`ColumnJob` solved, made exact for the updates since; the number taken. None
        are taken if the factor changed meanwhile, or a touched landmark's column is no longer cached (both as
        the scan's own solve would find them); a landmark cached meanwhile keeps its column."""
        touched = np.fromiter(self._touched, np.int64, len(self._touched))
        if job.factor is not self._factor or any(int(t) not in self.cache for t in touched):
            self.columns_prefetch_dropped += len(job.landmarks)
            return 0
        keep = [k for k, lm in enumerate(job.landmarks) if lm not in self.cache]
        if not keep:
            return 0
        missing = [job.landmarks[k] for k in keep]
        self._insert_corrected(missing, raw[block_rows(np.array(keep, np.int64))], touched)
        self.columns_prefetched += len(missing)
        self._evict(missing)
        return len(missing)

    def covariance_columns(self, landmarks: np.ndarray) -> np.ndarray:
        """Columns (2n, 2k) of I⁻¹ for ``landmarks`` (k,): from the cache, solved by PCG where missing."""
        landmarks = np.asarray(landmarks, np.int64)
        if landmarks.size == 0:
            return np.zeros((2 * self.n, 0))
        self._ensure_columns(landmarks)
        columns = np.array(self.cache.full(self.cache.columns(landmarks), 2 * self.n))
        self._evict(landmarks)
        return columns

    def joint_covariance(self, landmarks: np.ndarray) -> np.ndarray:
        """The (2k, 2k) covariance submatrix of ``landmarks`` (their columns solved or cached, only k rows read)."""
        landmarks = np.asarray(landmarks, np.int64)
        self._ensure_columns(landmarks)
        sub = self.cache.rows(block_rows(landmarks), self.cache.columns(landmarks))
        self._evict(landmarks)
        return 0.5 * (sub + sub.T)

    def marginals(self, landmarks: np.ndarray) -> np.ndarray:
        """The (k, 2, 2) marginal covariances of ``landmarks`` (their columns solved or cached)."""
        landmarks = np.asarray(landmarks, np.int64)
        if landmarks.size == 0:
            return np.zeros((0, 2, 2))
        k = landmarks.shape[0]
        sub = self.joint_covariance(landmarks).reshape(k, 2, k, 2)
        return sub[np.arange(k), :, np.arange(k), :]

    def cached_marginals(self) -> tuple[np.ndarray, np.ndarray]:
        """(landmark indices, (k, 2, 2) marginal covariances) of the cached columns (the landmarks near the robots)."""
        ids = np.fromiter(self.cache.slot.keys(), np.int64, len(self.cache))
        if ids.size == 0:
            return ids, np.zeros((0, 2, 2))
        if self.factored:
            covs = self.cache.diagonal_blocks(ids)
        else:
            k = ids.size
            cols = self.cache.rows(block_rows(ids), self.cache.columns(ids))
            covs = cols.reshape(k, 2, k, 2)[np.arange(k), :, np.arange(k), :]
        return ids, 0.5 * (covs + np.swapaxes(covs, 1, 2))

    def all_marginals(self, batch: int = 256) -> np.ndarray:
        """Every landmark's (n, 2, 2) marginal covariance, by one sparse LU and batched solves (for reports)."""
        if self.n == 0:
            return np.zeros((0, 2, 2))
        lu = scipy.sparse.linalg.splu(self.matrix.tocsr().tocsc())
        out = np.empty((self.n, 2, 2))
        for start in range(0, self.n, batch):
            chunk = np.arange(start, min(self.n, start + batch))
            rhs = np.zeros((2 * self.n, 2 * chunk.shape[0]))
            rhs[block_rows(chunk), np.arange(2 * chunk.shape[0])] = 1.0
            cols = lu.solve(rhs)
            sub = cols[block_rows(chunk)].reshape(chunk.shape[0], 2, chunk.shape[0], 2)
            out[chunk] = sub[np.arange(chunk.shape[0]), :, np.arange(chunk.shape[0]), :]
        return 0.5 * (out + np.swapaxes(out, 1, 2))

    def normalised_error(self, truth: np.ndarray) -> float:
        """(X̂ − X)ᵀ I (X̂ − X): the map NEES with the full information matrix (χ² with 2n dof if consistent)."""
        error = self.mean - np.asarray(truth, float).ravel()
        self.matrix.prepare()
        return float(error @ self.matrix.matvec(error))

    def memory_bytes(self) -> int:
        return self.matrix.memory_bytes() + self.vector.nbytes + self._mean.nbytes + self.cache.nbytes()
