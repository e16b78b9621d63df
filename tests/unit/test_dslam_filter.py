"""D-SLAM information filter: block-sparse storage, PCG, updates (eqs. 9, 10) and recovery against dense solves."""

import numpy as np
import pytest
import scipy.linalg

from robots.models import RangeBearingSensor, in_field_of_view
from services.dslam.information_filter import BlockSparseMatrix, InformationMap, block_pcg, block_rows

R = np.diag([0.05**2, np.radians(1.0) ** 2])


def test_block_sparse_matrix_matches_dense_accumulation_through_rebuilds():
    rng = np.random.default_rng(0)
    matrix = BlockSparseMatrix(capacity=4, rebuild_fraction=0.5)
    dense = np.zeros((0, 0))
    for step in range(60):
        if step % 5 == 0:
            matrix.grow(3)
            dense = np.pad(dense, ((0, 6), (0, 6)))
        index = rng.choice(matrix.n, size=min(matrix.n, rng.integers(1, 5)), replace=False)
        block = rng.standard_normal((2 * index.size, 2 * index.size))
        block = block @ block.T
        matrix.add(index, block)
        rows = block_rows(index)
        dense[np.ix_(rows, rows)] += block
        if step % 7 == 0:
            matrix.prepare()
        x = rng.standard_normal((2 * matrix.n, 2))
        np.testing.assert_allclose(matrix.matvec(x), dense @ x, atol=1e-9)
    np.testing.assert_allclose(matrix.tocsr().toarray(), dense, atol=1e-12)
    np.testing.assert_allclose(matrix.diagonal_blocks(), [dense[2 * i:2 * i + 2, 2 * i:2 * i + 2] for i in range(matrix.n)])
    pattern = dense.reshape(matrix.n, 2, matrix.n, 2).any(axis=(1, 3)) | np.eye(matrix.n, dtype=bool)
    assert matrix.nnz == 4 * np.count_nonzero(pattern)


def test_block_pcg_solves_several_right_hand_sides():
    rng = np.random.default_rng(1)
    a = rng.standard_normal((40, 40))
    a = a @ a.T + 40 * np.eye(40)
    b = rng.standard_normal((40, 3))
    x, iterations, converged = block_pcg(lambda v: a @ v, lambda r: r / np.diag(a)[:, None], b, np.zeros_like(b), 1e-12, 200)
    np.testing.assert_allclose(x, np.linalg.solve(a, b), atol=1e-9)
    assert converged and 0 < iterations <= 40
    _, again, _ = block_pcg(lambda v: a @ v, lambda r: r / np.diag(a)[:, None], b, x, 1e-9, 200)
    assert again == 0


def scan_sequence(seed: int, count: int = 60):
    """Noisy scans of a small random world from poses along a line: (observations, true ids) per scan."""
    rng = np.random.default_rng(seed)
    landmarks = np.column_stack([rng.uniform(0, 30, 40), rng.uniform(-4, 4, 40)])
    sensor = RangeBearingSensor()
    scans = []
    for k in range(count):
        pose = np.array([0.5 * k, 0.3 * np.sin(0.2 * k), 0.1 * np.cos(0.3 * k)])
        z = sensor.observe(pose, landmarks)
        seen = np.flatnonzero(in_field_of_view(z, 6.0, np.pi))
        z = z[seen] + rng.standard_normal((seen.size, 2)) @ np.linalg.cholesky(R).T
        scans.append((pose, z, seen))
    return landmarks, scans


def run_map(scans, cache_columns=64, noise=R, columns="factored", check_every=1, precision_loss=100.0):
    """Phase I on the first scan, phase II on the rest (known ids)."""
    m = InformationMap(tol=1e-10, column_tol=1e-12, column_max_iter=2000, cache_columns=cache_columns,
                       columns=columns, check_every=check_every, precision_loss=precision_loss)
    sensor = RangeBearingSensor()
    index_of = {}
    pose, z, seen = scans[0]
    g_pose, g_obs = sensor.inverse_jacobians(pose, z)
    cov = scipy.linalg.block_diag(*(g_obs @ noise @ np.swapaxes(g_obs, 1, 2)))
    added = m.update_absolute([], np.zeros((0, 2)), sensor.inverse(pose, z), cov)
    index_of.update(zip(seen.tolist(), added.tolist()))
    for pose, z, seen in scans[1:]:
        known = np.array([i in index_of for i in seen.tolist()], bool)
        mapped, new = np.flatnonzero(known), np.flatnonzero(~known)
        done = m.update_scan(z, noise, mapped, [index_of[i] for i in seen[mapped].tolist()], new)
        if done is not None:
            index_of.update(zip(seen[new].tolist(), done[0].tolist()))
        m.maintain()
    return m, index_of


@pytest.mark.parametrize("columns", ["factored", "explicit"])
@pytest.mark.parametrize("cache_columns", [64, 3])
def test_recovery_equals_dense_solve(cache_columns, columns):
    """Mean, cached covariance columns and every marginal equal dense solves of I X = i, even with a tiny cache."""
    _, scans = scan_sequence(2)
    m, _ = run_map(scans, cache_columns=cache_columns, columns=columns)
    dense = m.matrix.tocsr().toarray()
    np.testing.assert_allclose(m.mean, np.linalg.solve(dense, m.vector), atol=1e-7)
    cov = np.linalg.inv(dense)  # the test's reference only
    landmarks = np.array([0, m.n // 2, m.n - 1])
    np.testing.assert_allclose(m.covariance_columns(landmarks), cov[:, block_rows(landmarks)], atol=1e-9, rtol=1e-6)
    ids, marginals = m.cached_marginals()
    np.testing.assert_allclose(marginals, [cov[2 * i:2 * i + 2, 2 * i:2 * i + 2] for i in ids], atol=1e-10, rtol=1e-6)
    np.testing.assert_allclose(m.all_marginals(), [cov[2 * i:2 * i + 2, 2 * i:2 * i + 2] for i in range(m.n)],
                               atol=1e-10, rtol=1e-6)
    if cache_columns == 3:
        assert m.column_solves > 0


def test_information_matrix_links_only_landmarks_seen_together():
    _, scans = scan_sequence(3)
    m, index_of = run_map(scans)
    together = np.zeros((m.n, m.n), bool)
    for _, _, seen in scans[1:]:
        idx = [index_of[i] for i in seen.tolist() if i in index_of]
        if len(idx) >= 2:
            together[np.ix_(idx, idx)] = True
    pattern = m.matrix.tocsr().toarray().reshape(m.n, 2, m.n, 2).any(axis=(1, 3))
    off = ~np.eye(m.n, dtype=bool)
    assert not np.any(pattern & ~together & off)


def test_noiseless_scans_give_the_exact_map():
    landmarks, scans = scan_sequence(4)
    sensor = RangeBearingSensor()
    exact = [(pose, sensor.observe(pose, landmarks[seen]), seen) for pose, _, seen in scans]
    m, index_of = run_map(exact, noise=np.diag([1e-12, 1e-14]))
    order = np.array(sorted(index_of, key=index_of.get))
    np.testing.assert_allclose(m.means, landmarks[order], atol=1e-6)


def test_a_new_feature_must_own_two_rows():
    m = InformationMap()
    m.update_absolute([], np.zeros((0, 2)), np.array([[1.0, 2.0]]), np.eye(2))
    with pytest.raises(ValueError):
        m.update([0], np.ones((3, 4)), np.zeros(3), np.eye(3), np.array([[3.0, 3.0]]))


def test_map_nees_uses_the_information_matrix():
    m = InformationMap()
    m.update_absolute([], np.zeros((0, 2)), np.array([[1.0, 2.0], [3.0, 4.0]]), np.diag([0.5, 0.5, 2.0, 2.0]))
    truth = np.array([[0.0, 2.0], [3.0, 6.0]])
    assert m.normalised_error(truth) == pytest.approx(1.0 / 0.5 + 4.0 / 2.0)


@pytest.mark.parametrize("cache_columns, check_every, precision_loss", [(64, 16, 100.0), (3, 1, 100.0), (8, 4, 1.0)])
def test_factored_columns_follow_the_explicit_reference(cache_columns, check_every, precision_loss):
    """The factored columns (B T) give the explicit reference's mean, columns and marginals on the same scans: with
    a large cache, with a tiny one (evictions and base compactions), and compacting after every update."""
    _, scans = scan_sequence(2)
    explicit, _ = run_map(scans, cache_columns=cache_columns, columns="explicit")
    factored, _ = run_map(scans, cache_columns=cache_columns, columns="factored", check_every=check_every,
                          precision_loss=precision_loss)
    assert factored.n == explicit.n and set(factored.cache.slot) == set(explicit.cache.slot)
    np.testing.assert_allclose(factored.mean, explicit.mean, atol=1e-9)
    landmarks = np.array(sorted(set(explicit.cache.slot) | {0}))  # landmark 0 solved afresh with a tiny cache
    np.testing.assert_allclose(factored.covariance_columns(landmarks), explicit.covariance_columns(landmarks),
                               atol=1e-12, rtol=1e-8)
    ids, marginals = factored.cached_marginals()
    reference_ids, reference = explicit.cached_marginals()
    order = np.argsort(ids), np.argsort(reference_ids)
    np.testing.assert_array_equal(ids[order[0]], reference_ids[order[1]])
    np.testing.assert_allclose(marginals[order[0]], reference[order[1]], atol=1e-12, rtol=1e-8)
    if precision_loss == 1.0:
        assert factored.cache.used == 2 * len(factored.cache)  # compacted: the cached columns are the base
    if cache_columns == 3:
        assert factored.column_solves > 0


def test_factored_update_keeps_the_mean_change_pending_and_exact():
    """The mean change of a factored update is held as base coefficients (the stored mean untouched) until read;
    the landmark means read meanwhile, and the mean read after, equal the dense solve of I X = i."""
    _, scans = scan_sequence(6)
    m, index_of = run_map(scans[:-1], check_every=1000)
    pose, z, seen = scans[-1]
    known = np.array([i in index_of for i in seen.tolist()], bool)
    stored = m._mean.copy()
    assert m.update_scan(z, R, np.flatnonzero(known), [index_of[i] for i in seen[known].tolist()],
                         np.zeros(0, np.int64)) is not None
    np.testing.assert_array_equal(m._mean, stored)
    exact = np.linalg.solve(m.matrix.tocsr().toarray(), m.vector)
    index = np.arange(m.n)
    np.testing.assert_allclose(m.landmark_means(index).ravel(), exact, atol=1e-7)
    assert np.max(np.abs(m.landmark_means(index).ravel() - stored)) > 1e-6  # the update did move the mean
    np.testing.assert_allclose(m.mean, exact, atol=1e-7)
    assert not np.any(m.cache.shift)


def test_maintain_checks_the_mean_every_few_scans_and_after_untracked_updates():
    m = InformationMap(check_every=3)
    m.update_absolute([], np.zeros((0, 2)), np.array([[1.0, 2.0], [3.0, 4.0]]), np.eye(4))
    m.vector[:2] += 1.0  # the mean no longer solves I X = i: a check would move it
    assert [m.maintain() for _ in range(3)][:2] == [0, 0]
    np.testing.assert_allclose(m.mean, np.linalg.solve(m.matrix.tocsr().toarray(), m.vector), atol=1e-9)
    m.track_columns = False
    m.update_absolute([0], np.array([[1.5, 2.5]]), np.zeros((0, 2)), np.eye(2))
    assert m.maintain() > 0  # an update the columns did not follow: checked at once


def test_a_feature_on_the_first_reference_is_refused_and_leaves_the_map_finite():
    """z_map gives each feature's bearing and distance from the first reference (eq. 3): a feature on it has no
    bearing, its recast is not finite, and the update is refused rather than putting NaN into the map (seen on
    MR.CLAM Dataset 1 through a local map). The same points with the feature elsewhere update it."""
    def seeded() -> InformationMap:
        info = InformationMap()
        info.update_absolute(np.zeros(0, np.int64), np.zeros((0, 2)), np.array([[1.0, 0.0], [2.0, 0.0], [1.5, 1.0]]),
                             np.eye(6) * 0.01)
        return info
    info = seeded()
    before = info.matrix.tocsr().toarray().copy()
    on_reference = np.array([[1.0, 0.0], [2.0, 0.0], [1.0, 0.0]])
    assert info.update_points(on_reference, np.eye(6) * 0.01, np.arange(3), np.arange(3), np.zeros(0, np.int64),
                              0.3, 0.99) is None
    assert np.array_equal(info.matrix.tocsr().toarray(), before) and np.all(np.isfinite(info.means))
    info = seeded()
    assert info.update_points(np.array([[1.0, 0.0], [2.0, 0.0], [1.5, 1.0]]), np.eye(6) * 0.01, np.arange(3),
                              np.arange(3), np.zeros(0, np.int64), 0.3, 0.99) is not None
