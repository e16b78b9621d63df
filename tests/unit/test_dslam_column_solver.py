"""Corrected column solves (one solve with a stale sparse LU factor, made exact by the cached columns of the
landmarks touched since) against the PCG reference and against dense inverses."""

import numpy as np
import pytest

from services.dslam.information_filter import InformationMap, block_rows
from tests.unit.test_dslam_filter import R, run_map, scan_sequence


def dense_inverse(m: InformationMap) -> np.ndarray:
    return np.linalg.inv(m.matrix.tocsr().toarray())  # the test's reference only


def build(scans, solver: str, columns: str, cache_columns: int = 3,
          correction_limit: int = 64) -> tuple[InformationMap, dict]:
    """As ``run_map`` (a tiny cache: columns evicted on the way), then the given column solver with a factor of
    that map, so that later solves use a stale one; returns the map and its landmark index of each true id."""
    m, index_of = run_map(scans, cache_columns=cache_columns, columns=columns)
    m.column_solver, m.correction_limit = solver, correction_limit
    m.factorise()
    return m, index_of


def continue_map(m: InformationMap, index_of: dict, scans) -> None:
    """Phase II on ``scans`` (known ids; the tests drive back along the way the map was built)."""
    for _, z, seen in scans:
        known = np.array([i in index_of for i in seen.tolist()], bool)
        mapped, new = np.flatnonzero(known), np.flatnonzero(~known)
        done = m.update_scan(z, R, mapped, [index_of[i] for i in seen[mapped].tolist()], new)
        if done is not None:
            index_of.update(zip(seen[new].tolist(), done[0].tolist()))
        m.maintain()


@pytest.mark.parametrize("columns", ["factored", "explicit"])
def test_corrected_columns_equal_the_pcg_reference_and_the_dense_inverse(columns):
    """With a tiny cache (columns solved anew, a factor many updates old) the corrected solves give the PCG
    reference's mean and columns, and the dense inverse, with one factorisation and no iterations."""
    _, scans = scan_sequence(2)
    (corrected, ids), (reference, reference_ids) = (build(scans, solver, columns) for solver in ("corrected", "pcg"))
    factorisations, solves = corrected.factorisations, corrected.column_solves
    continue_map(corrected, ids, scans[::-1])
    continue_map(reference, reference_ids, scans[::-1])
    assert corrected.n == reference.n
    assert corrected.factorisations == factorisations and corrected.column_solves > solves
    assert corrected._touched and corrected.cache.pinned == set(corrected._touched)
    np.testing.assert_allclose(corrected.mean, reference.mean, atol=1e-9)
    np.testing.assert_allclose(corrected.mean, np.linalg.solve(corrected.matrix.tocsr().toarray(), corrected.vector),
                               atol=1e-7)
    cov = dense_inverse(corrected)
    landmarks = np.array([0, 3, corrected.n // 2, corrected.n - 1])
    np.testing.assert_allclose(corrected.covariance_columns(landmarks), cov[:, block_rows(landmarks)],
                               atol=1e-9, rtol=1e-6)
    np.testing.assert_allclose(corrected.covariance_columns(landmarks), reference.covariance_columns(landmarks),
                               atol=1e-9, rtol=1e-6)
    ids, marginals = corrected.cached_marginals()
    np.testing.assert_allclose(marginals, [cov[2 * i:2 * i + 2, 2 * i:2 * i + 2] for i in ids], atol=1e-10, rtol=1e-6)


def test_the_correction_is_what_makes_a_stale_factor_exact():
    """The factor's own solve is wrong after the updates (the correction is not a no-op), the corrected one is not."""
    _, scans = scan_sequence(3)
    m, ids = build(scans, "corrected", "factored")
    continue_map(m, ids, scans[:-30:-1])
    cov = dense_inverse(m)
    target = next(i for i in range(m.n) if i not in m.cache)
    rows = block_rows([target])
    rhs = np.zeros((m._factor_size, 2))
    rhs[rows, [0, 1]] = 1.0
    stale = m._factor.solve(rhs)
    assert np.max(np.abs(stale - cov[: m._factor_size, rows])) > 1e-6
    np.testing.assert_allclose(m.covariance_columns(np.array([target])), cov[:, rows], atol=1e-10, rtol=1e-7)


def test_touched_landmarks_stay_cached_and_the_limit_refactorises():
    """Touched landmarks are never evicted; past ``correction_limit`` of them the factor is made afresh, still exact."""
    _, scans = scan_sequence(4)
    m, ids = build(scans, "corrected", "factored", correction_limit=4)
    factorisations = m.factorisations
    continue_map(m, ids, scans[::-1])
    assert m.factorisations > factorisations
    assert len(m._touched) <= 4 and set(m._touched) <= set(m.cache.slot)
    cov = dense_inverse(m)
    ids, marginals = m.cached_marginals()
    np.testing.assert_allclose(marginals, [cov[2 * i:2 * i + 2, 2 * i:2 * i + 2] for i in ids], atol=1e-10, rtol=1e-6)
    np.testing.assert_allclose(m.mean, np.linalg.solve(m.matrix.tocsr().toarray(), m.vector), atol=1e-7)


def test_changing_the_cache_refactorises_before_a_corrected_solve():
    """A new, empty cache holds no touched columns: the next solve makes a fresh factor rather than a wrong column."""
    _, scans = scan_sequence(5)
    m, ids = build(scans, "corrected", "factored")
    continue_map(m, ids, scans[:-20:-1])
    count = m.factorisations
    m.use_columns("explicit", 3)
    cov = dense_inverse(m)
    np.testing.assert_allclose(m.covariance_columns(np.array([1])), cov[:, block_rows([1])], atol=1e-10, rtol=1e-7)
    assert m.factorisations == count + 1


def test_unknown_column_solver_is_refused():
    with pytest.raises(ValueError):
        InformationMap(column_solver="amg")


@pytest.mark.parametrize("columns", ["factored", "explicit"])
def test_columns_solved_off_the_scan_are_exact_after_later_updates(columns):
    """A column job solved with the factor, taken after more updates touched other landmarks, caches the columns of
    the dense inverse of the current I, so the next request solves nothing; a landmark cached meanwhile is kept."""
    _, scans = scan_sequence(2)
    m, ids = build(scans, "corrected", columns)
    want = [i for i in range(m.n) if i not in m.cache][:4]
    job = m.column_job(want + [want[0]], limit=8)
    assert job is not None and job.landmarks == want
    raw = job.run()  # as a worker thread would, before the updates below
    continue_map(m, ids, scans[::-1][:8])
    assert m._touched, "the updates since the job must need the correction"
    taken = m.take_columns(job, raw)
    assert taken == len([i for i in want if i in m.cache]) and m.columns_prefetched == taken > 0
    solves = m.column_solves
    cov = dense_inverse(m)
    np.testing.assert_allclose(m.covariance_columns(np.array(want)), cov[:, block_rows(np.array(want))],
                               atol=1e-9, rtol=1e-6)
    assert m.column_solves == solves


def test_a_column_job_is_dropped_when_the_factor_changed():
    """A job solved with a factor the map has since replaced is not taken (counted): its solves would not be
    corrected by the right changes."""
    _, scans = scan_sequence(2)
    m, _ = build(scans, "corrected", "factored")
    want = [i for i in range(m.n) if i not in m.cache][:3]
    job = m.column_job(want, limit=8)
    raw = job.run()
    m.factorise()
    assert m.take_columns(job, raw) == 0
    assert m.columns_prefetch_dropped == 3 and not any(i in m.cache for i in want)
    m._factor = None
    assert m.column_job(want, limit=8) is None  # no factor: the scan that needs the columns makes one


def test_a_pickled_factored_cache_leaves_its_reserved_room_out_and_carries_on():
    """The base reserves room for the vectors to come; a checkpoint does not carry it, and the restored cache gives
    the same columns and takes new ones."""
    import pickle

    _, scans = scan_sequence(2)
    m, ids = build(scans, "corrected", "factored")
    cache = m.cache
    assert cache.base.shape[0] > cache.used  # room reserved beyond the vectors in use
    restored = pickle.loads(pickle.dumps(m))
    assert restored.cache.base.shape == (cache.used, cache.size)
    cached = np.array(list(cache.slot))
    np.testing.assert_array_equal(restored.cache.full(restored.cache.columns(cached), cache.size),
                                  cache.full(cache.columns(cached), cache.size))
    want = np.array([i for i in range(m.n) if i not in m.cache][:2])
    np.testing.assert_allclose(restored.covariance_columns(want), dense_inverse(m)[:, block_rows(want)],
                               atol=1e-9, rtol=1e-6)
