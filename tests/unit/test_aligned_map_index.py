"""The shared map's spatial index and its resampling of the columns the particles disagree on
(:class:`central.fastslam.aligned_map.AlignedMap`), against the definitions they shortcut: every landmark's
mixture computed from every particle, and reference counts counted again from the whole tables."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from central.fastslam import kernels
from central.fastslam.aligned_map import INDEX_CELLS_PER_RADIUS, AlignedMap

PARTICLES, BLOCK = 30, 4


def new_landmarks(lmap: AlignedMap, rng: np.random.Generator, count: int) -> np.ndarray:
    """``count`` landmarks over a 60 m square, each particle's mean its own (a few spread wider than the grid)."""
    centre = rng.uniform(-30.0, 30.0, (1, count, 2))
    spread = np.where(rng.random((1, count, 1)) < 0.1, 15.0, 0.3)
    mean = centre + rng.normal(0.0, 1.0, (PARTICLES, count, 2)) * spread
    cov = np.broadcast_to(np.eye(2) * 0.1, (PARTICLES, count, 2, 2))
    return lmap.add(mean, cov, 1.0, 1, rng.integers(0, 10**6, count))


def mixture_means(lmap: AlignedMap, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(valid slots, their weighted means over every particle): the definition the index must not miss."""
    slots = np.flatnonzero(lmap.valid)
    means, _ = lmap.gather(np.arange(PARTICLES)[:, None], slots[None])
    return slots, np.einsum("p,pkj->kj", weights, means)


def check_searches(lmap: AlignedMap, rng: np.random.Generator) -> int:
    """Every valid landmark whose mixture (random weights) lies within the radius is found, in the order the
    landmarks were added in, and nothing invalid; returns how many slots the searches left out."""
    left_out = 0
    for _ in range(5):
        weights = rng.dirichlet(np.full(PARTICLES, 0.3))
        slots, means = mixture_means(lmap, weights)
        point, radius = rng.uniform(-30.0, 30.0, 2), rng.uniform(3.0, 12.0)
        found = lmap.near(point, radius)
        inside = set(slots[np.hypot(*(means - point).T) < radius].tolist())
        assert inside <= set(found.tolist())
        assert lmap.valid[found].all()
        assert np.all(np.diff(lmap.serial[found]) > 0)
        left_out += int(lmap.valid.sum()) - found.size
    return left_out


@pytest.mark.parametrize("seed", [0, 1])
def test_near_finds_the_landmarks_a_scan_moved_when_only_their_slots_are_filed_again(seed):
    """The FastSLAM 2.0 kernel files again only the slots it updated (from the box of their new means), not their
    blocks: between such updates and resampling, a search still finds every landmark whose mixture is in the disc."""
    rng = np.random.default_rng(seed)
    lmap = AlignedMap(PARTICLES, block=BLOCK)
    new_landmarks(lmap, rng, 120)
    lmap.near(np.zeros(2), 8.0)
    for _ in range(15):
        slots = np.sort(rng.choice(np.flatnonzero(lmap.valid), 6, replace=False))
        blocks = lmap.reserve_private(slots, refile=False)  # as the kernel: private copies, the blocks not marked
        kernels.private_blocks(lmap.table, blocks, lmap.refs, lmap.pool_mean, lmap.pool_cov, lmap.free_blocks,
                               lmap.free_count)
        means, _ = lmap.gather(np.arange(PARTICLES)[:, None], slots[None])
        means = means + rng.normal(0.0, 1.0, (PARTICLES, slots.size, 2)) * np.where(rng.random(slots.size) < 0.4, 8.0, 0.3)[:, None]
        phys = lmap.table[:, slots // BLOCK]
        lmap.pool_mean[phys, slots % BLOCK] = means
        box = np.concatenate([means.min(0), means.max(0)], 1)
        lmap.refile_slots(slots, box)
        lmap.select(np.sort(rng.integers(0, PARTICLES, PARTICLES)))
        check_searches(lmap, rng)
    lmap.refile_slots(slots, np.tile([0.0, 0.0, 0.0, 0.0], (slots.size, 1)))  # filed at the origin: found there
    assert set(slots.tolist()) <= set(lmap.near(np.zeros(2), 0.5).tolist())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_near_finds_every_landmark_whose_mixture_lies_within_the_radius(seed):
    """Through writes that move landmarks across cells, releases, reused slots, resampling and growth, a search
    returns a superset of the landmarks whose mixture lies in the disc — and far fewer than the whole map."""
    rng = np.random.default_rng(seed)
    lmap = AlignedMap(PARTICLES, block=BLOCK)
    new_landmarks(lmap, rng, 200)
    lmap.near(np.zeros(2), 8.0)  # the first search sets the grid's cell
    assert lmap.index_cell == pytest.approx(8.0 / INDEX_CELLS_PER_RADIUS)
    left_out = check_searches(lmap, rng)
    for _ in range(12):
        moved = rng.choice(np.flatnonzero(lmap.valid), 15, replace=False)
        means, covs = lmap.gather(np.arange(PARTICLES)[:, None], moved[None])
        jump = rng.normal(0.0, 1.0, (PARTICLES, moved.size, 2)) * np.where(rng.random(moved.size) < 0.3, 9.0, 0.2)[:, None]
        lmap.write(moved, means + jump, covs)  # some move several cells, in some particles only
        lmap.release(rng.choice(np.flatnonzero(lmap.valid), 8, replace=False))
        new_landmarks(lmap, rng, 12)  # reuses the freed slots, then grows
        lmap.select(np.sort(rng.integers(0, PARTICLES, PARTICLES)))
        left_out += check_searches(lmap, rng)
    assert left_out > 0.5 * 13 * 5 * lmap.valid.sum()  # the index does prune


def test_the_index_survives_a_checkpoint_also_one_written_before_it():
    rng = np.random.default_rng(4)
    lmap = AlignedMap(PARTICLES, block=BLOCK)
    new_landmarks(lmap, rng, 120)
    lmap.release(np.arange(0, 40, 3))
    new_landmarks(lmap, rng, 10)  # into freed slots: the order added differs from the slots' order
    expected = lmap.near(np.array([3.0, -2.0]), 10.0)
    restored = pickle.loads(pickle.dumps(lmap))
    np.testing.assert_array_equal(restored.near(np.array([3.0, -2.0]), 10.0), expected)
    state = lmap.__getstate__()
    order = np.flatnonzero(lmap.valid)[np.argsort(lmap.serial[lmap.valid])]
    for name in ("serial", "added", "mixed", "index_cell"):
        del state[name]
    old = AlignedMap.__new__(AlignedMap)
    old.__setstate__(state)
    old.set_order(order)  # what the filter does on a restore
    np.testing.assert_array_equal(old.near(np.array([3.0, -2.0]), 10.0), expected)
    assert old.mixed == lmap.mixed


@pytest.mark.parametrize("seed, compiled", [(0, True), (1, True), (0, False)])
def test_resampling_only_the_mixed_columns_counts_as_a_full_recount(seed, compiled):
    """Each resampling copies only the columns where particles may disagree; the reference counts, free blocks
    and every particle's Gaussians are those of copying every row whole (a dense reference), by the kernel and by
    its numpy reference."""
    rng = np.random.default_rng(seed)
    lmap = AlignedMap(PARTICLES, block=BLOCK)
    slots = lmap.add(rng.normal(0.0, 10.0, (200, 2)), np.broadcast_to(np.eye(2), (200, 2, 2)), 1.0, 1,
                     np.arange(200))  # an agreed map: stored once
    dense = np.broadcast_to(lmap.gather(0, slots)[0], (PARTICLES, 200, 2)).copy()
    copied_columns = []
    for _ in range(25):
        touched = rng.choice(slots, 6, replace=False)
        step = rng.normal(0.0, 0.1, (PARTICLES, touched.size, 2))
        means, covs = lmap.gather(np.arange(PARTICLES)[:, None], touched[None])
        lmap.write(touched, means + step, covs)
        dense[:, touched] += step
        index = np.sort(rng.choice(PARTICLES, PARTICLES, p=rng.dirichlet(np.full(PARTICLES, 0.2))))
        copied_columns.append(len(lmap.mixed))
        lmap.select(index, compiled)
        dense = dense[index]
        held = lmap.table[lmap.table >= 0]
        np.testing.assert_array_equal(lmap.refs, np.bincount(held, minlength=lmap.refs.size))
        assert sorted(lmap.free_blocks[: int(lmap.free_count[0])].tolist()) == np.flatnonzero(lmap.refs == 0).tolist()
        differ = set(np.flatnonzero(~np.all(lmap.table == lmap.table[:1], 0)).tolist())
        assert differ <= lmap.mixed
        np.testing.assert_array_equal(lmap.gather(np.arange(PARTICLES)[:, None], slots[None])[0], dense)
    assert max(copied_columns) < lmap.table.shape[1]  # resampling never copied whole tables
    assert lmap.blocks_in_use() < PARTICLES * lmap.table.shape[1] / 4  # the particles still share most blocks
