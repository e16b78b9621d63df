"""The compiled FastSLAM kernels against their numpy references, on seeded inputs and on whole seeded runs."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from central.fastslam import association, evidence, kernels, proposal, reacquire, resampling, shared
from central.fastslam.aligned_map import AlignedMap
from central.fastslam.config import FastSlamConfig
from central.fastslam.core import FastSlam
from robots.gaussian import sandwich2, systematic_resample
from robots.models import AckermannModel, RangeBearingSensor, UnicycleModel, integrate_controls, se2_compose
from robots.simulator import simulate
from schemas.contract import OdomEvent, ScanEvent


def feed(estimator, dataset):
    for event in dataset.events():
        if isinstance(event, OdomEvent):
            estimator.on_odometry(event)
        elif isinstance(event, ScanEvent):
            estimator.on_scan(event)


def random_map(seed: int, particles: int = 40, slots: int = 12) -> AlignedMap:
    """Landmarks every particle holds, each particle's Gaussians its own, in blocks of 4 slots."""
    rng = np.random.default_rng(seed)
    lmap = AlignedMap(particles, block=4)
    index = lmap.allocate(slots)
    root = rng.normal(0.0, 0.3, (particles, slots, 2, 2))
    lmap.write(index, rng.uniform(-8.0, 8.0, (1, slots, 2)) + rng.normal(0.0, 0.3, (particles, slots, 2)),
               root @ np.swapaxes(root, -1, -2) + 0.01 * np.eye(2))
    lmap.exist[index] = rng.uniform(0.0, 6.0, slots)
    lmap.hits[index] = rng.integers(1, 9, slots)
    lmap.valid[index] = True
    return lmap


def gaussians(lmap: AlignedMap) -> tuple[np.ndarray, np.ndarray]:
    return lmap.gather(np.arange(lmap.particles)[:, None], np.arange(lmap.used)[None])


def test_kernels_are_compiled():
    assert kernels.AVAILABLE  # numba is a declared dependency
    assert hasattr(kernels.known_update_kernel, "signatures")


@pytest.mark.parametrize("seed, offset", [(0, (0.0, 0.0)), (1, (0.4, -0.2)), (2, (1.2, 0.3))])
def test_known_update_kernel_gives_the_reference_update(seed, offset):
    rng = np.random.default_rng(seed)
    sensor = RangeBearingSensor(offset)
    reference, compiled = random_map(seed), random_map(seed)
    reference.select(np.repeat(np.arange(20), 2))  # pairs of particles share blocks: the update copies them
    compiled.select(np.repeat(np.arange(20), 2))
    poses = np.zeros((40, 2, 3))  # a robot's poses are a strided view, as in the filter
    poses[:, 1] = rng.normal([0.5, -0.5, 2.0], [0.3, 0.3, 0.2], (40, 3))
    pose = poses[:, 1]
    slots = np.array([3, 7, 0, 11])
    truth = gaussians(reference)[0][0, slots] + rng.normal(0.0, 0.5, (4, 2))
    z = sensor.observe(pose[0], truth) + rng.normal(0.0, [0.05, 0.02], (4, 2))
    r = np.array([[0.04, 0.001], [0.001, 0.003]])
    slam = SimpleNamespace(map=reference, pose=poses, config=FastSlamConfig(exist_hit=1.0, exist_max=6.0))
    robot = SimpleNamespace(index=1, sensor=sensor)
    expected = association.known_update_reference(slam, robot, slots, z, r)
    got = kernels.known_update(compiled, sensor, pose, slots, z, r, 1.0, 6.0)
    assert np.ptp(expected) > 1.0  # the particles disagree: agreement is not trivial
    np.testing.assert_allclose(got, expected, rtol=1e-10, atol=1e-10)
    for a, b in zip(gaussians(compiled), gaussians(reference)):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(compiled.exist, reference.exist, rtol=1e-12)
    np.testing.assert_array_equal(compiled.hits, reference.hits)
    before = random_map(seed)
    before.select(np.repeat(np.arange(20), 2))
    moved = np.abs(gaussians(compiled)[0] - gaussians(before)[0]).max(axis=(0, 2))
    assert (moved[slots] > 0).all() and (np.delete(moved, slots) == 0).all()  # those slots, and only those, moved
    assert compiled.blocks_in_use() > before.blocks_in_use()


@pytest.mark.parametrize("model, steer", [(UnicycleModel(), 0.8), (AckermannModel(2.83, 0.76), 0.3)])
@pytest.mark.parametrize("seed", [0, 1])
def test_integrate_controls_kernel_gives_the_reference_motion(model, steer, seed):
    rng = np.random.default_rng(seed)
    count = 17
    controls = np.column_stack([rng.uniform(0.0, 4.0, count), rng.uniform(-steer, steer, count)])
    controls[3, 1] = 1e-7  # straight: the series branch of sin(h)/h
    dts = rng.uniform(0.01, 0.2, count)
    root = rng.normal(0.0, 0.1, (count, 2, 2))
    covs = root @ np.swapaxes(root, -1, -2)
    expected = integrate_controls(model, controls, dts, covs)
    got = kernels.integrate_controls(model, controls, dts, covs)
    assert np.linalg.norm(expected[0][:2]) > 1.0
    np.testing.assert_allclose(got[0], expected[0], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(got[1], expected[1], rtol=1e-10, atol=1e-14)


@pytest.mark.parametrize("moved", [False, True])
def test_weighted_pose_kernel_gives_the_reference_moments(moved):
    rng = np.random.default_rng(3)
    pose = rng.normal([1.0, 2.0, 3.1], [0.5, 0.5, 0.1], (50, 3))  # headings across ±π
    w = rng.uniform(0.0, 1.0, 50)
    w /= w.sum()
    delta = np.array([0.8, -0.1, 0.2])
    root = rng.normal(0.0, 0.1, (3, 3))
    delta_cov = root @ root.T
    got = kernels.weighted_pose(pose, w, (delta, delta_cov) if moved else None)
    if moved:
        rotation = np.zeros((50, 3, 3))
        rotation[:, 0, 0] = rotation[:, 1, 1] = np.cos(pose[:, 2])
        rotation[:, 1, 0], rotation[:, 0, 1] = np.sin(pose[:, 2]), -np.sin(pose[:, 2])
        rotation[:, 2, 2] = 1.0
        extra = np.einsum("p,pij,jk,plk->il", w, rotation, delta_cov, rotation)
        mean, cov = resampling.weighted_pose(se2_compose(pose, delta), w)
        cov = cov + extra
    else:
        mean, cov = resampling.weighted_pose(pose, w)
    np.testing.assert_allclose(got[0], mean, atol=1e-12)
    np.testing.assert_allclose(got[1], 0.5 * (cov + cov.T), atol=1e-12)


@pytest.mark.parametrize("offset", [(0.0, 0.0), (0.5, -0.3)])
def test_create_kernel_puts_new_landmarks_where_the_reference_does(offset):
    """New landmarks in every particle, into blocks the particles share and blocks not written yet: the kernel's
    Gaussians are the inverse sensor model's (and G R Gᵀ), and the shared blocks' other landmarks are untouched."""
    rng = np.random.default_rng(11)
    sensor = RangeBearingSensor(offset=offset)
    pose = rng.normal([0.0, 0.0, 0.5], [1.0, 1.0, 0.3], (40, 3))
    z = np.array([[4.0, 0.3], [7.5, -1.0], [2.0, 2.5]])
    r = np.array([[0.04, 0.001], [0.001, 0.002]])
    maps = {}
    for compiled in (True, False):
        lmap = random_map(2)  # 12 slots in blocks of 4: the first new ones fill no block, the rest a fresh one
        before = gaussians(lmap)
        slots = lmap.allocate(3)
        if compiled:
            kernels.create(lmap, sensor, pose, slots, z, r)
            lmap.register(slots, 1.0, 1, np.array([7, 8, 9]))
        else:
            _, g = sensor.inverse_jacobians(pose[:, None], z[None])
            lmap.write(slots, sensor.inverse(pose[:, None], z[None]), sandwich2(g, r))
            lmap.register(slots, 1.0, 1, np.array([7, 8, 9]))
        maps[compiled] = lmap
        for a, b in zip(before, lmap.gather(np.arange(40)[:, None], np.arange(12)[None])):
            np.testing.assert_array_equal(a, b)
    for a, b in zip(gaussians(maps[True]), gaussians(maps[False])):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14)
    assert maps[True].valid[12:15].all() and list(maps[True].label[12:15]) == [7, 8, 9]
    assert np.ptp(gaussians(maps[True])[0][:, 12, 0]) > 0.5  # each particle's own


@pytest.mark.parametrize("moved", [False, True])
def test_pose_belief_kernel_moves_the_mean_as_the_reference(moved):
    """The belief the shared association gates from: the weighted mean composed with the pending motion (not every
    particle moved), its covariance plus J Σ_Δ Jᵀ at the mean's heading."""
    rng = np.random.default_rng(5)
    pose = rng.normal([1.0, -2.0, 3.0], [0.4, 0.4, 0.2], (60, 3))
    w = rng.dirichlet(np.ones(60))
    delta = np.array([0.5, 0.1, -0.3])
    root = rng.normal(0.0, 0.1, (3, 3))
    delta_cov = root @ root.T
    mean, cov = kernels.pose_belief_kernel(pose, w, delta, delta_cov, moved)
    expected_mean, expected_cov = resampling.weighted_pose(pose, w)
    if moved:
        c, s = np.cos(expected_mean[2]), np.sin(expected_mean[2])
        jac = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        expected_mean, expected_cov = se2_compose(expected_mean, delta), expected_cov + jac @ delta_cov @ jac.T
    np.testing.assert_allclose(mean, expected_mean, atol=1e-12)
    np.testing.assert_allclose(cov, expected_cov, atol=1e-12)
    assert moved == (not np.allclose(mean, resampling.weighted_pose(pose, w)[0]))


@pytest.mark.parametrize("seed", range(4))
def test_drift_kernels_give_the_reference_drift(seed):
    """The drift's growth along a motion and its Kalman update by 1–5 matched detections (one after the other in the
    kernel, all at once in the reference), from a zero drift and from a full one."""
    rng = np.random.default_rng(seed)
    root = rng.normal(0.0, 0.2, (3, 3))
    drift = None if seed == 0 else root @ root.T
    delta, heading = rng.normal(0.0, 1.0, 3), rng.uniform(-np.pi, np.pi)
    root = rng.normal(0.0, 0.1, (3, 3))
    motion_cov = root @ root.T
    grown = kernels.drift_accumulate(drift, heading, delta, motion_cov, 0.01)
    expected = reacquire.accumulate(drift, heading, delta, motion_cov, 0.01)
    np.testing.assert_allclose(grown, expected, rtol=1e-12, atol=1e-15)
    count = 1 + seed
    h_x = rng.normal(0.0, 1.0, (count, 2, 3))
    root = rng.normal(0.0, 0.1, (count, 2, 2))
    noise = root @ np.swapaxes(root, -1, -2) + 1e-3 * np.eye(2)
    conditioned = kernels.drift_condition(grown, h_x, noise)
    np.testing.assert_allclose(conditioned, reacquire.condition(grown, h_x, noise), rtol=1e-8, atol=1e-12)
    assert np.trace(conditioned) < np.trace(grown)


def test_joint_blocks_kernel_gives_the_reference_blocks():
    """JCBB's inputs: the landmarks some detection gates, and their predicted detections' joint covariance."""
    rng = np.random.default_rng(7)
    gated = rng.random((5, 9)) < 0.3
    gated[:, 4] = False  # a landmark no detection gates is left out
    h_x, own = rng.normal(0.0, 1.0, (9, 2, 3)), rng.normal(0.0, 1.0, (9, 2, 2))
    root = rng.normal(0.0, 0.3, (3, 3))
    reach, joint = kernels.joint_blocks_kernel(gated, h_x, own, root @ root.T)
    expected_reach, expected_joint = shared.joint_blocks(gated, h_x, own, root @ root.T)
    assert 4 not in reach and reach.size == expected_reach.size > 2
    np.testing.assert_array_equal(reach, expected_reach)
    np.testing.assert_allclose(joint, expected_joint, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("size, count", [(1, 5), (4, 2), (7, 3), (400, 50), (1000, 200), (50, 200)])
def test_association_draw_kernel_gives_the_systematic_draw_and_its_runs(size, count):
    rng = np.random.default_rng(size + count)
    for trial in range(20):
        w = rng.random(size) ** (1 + 10 * trial) if trial else np.ones(size)  # even (draws on the steps) to one heavy
        if trial % 5 == 4:
            w[rng.random(size) < 0.5] = 0.0
            w[0] = max(w[0], 1e-3)
        w = w / w.sum()
        expected_rows, expected_shares = shared.association_draw_reference(w, count)
        rows, shares = kernels.association_draw_kernel(w, float(w.sum()), count, 0.5)
        np.testing.assert_array_equal(rows, expected_rows)
        assert np.array_equal(shares, expected_shares)  # bit for bit
        drawn = systematic_resample(w, count, None, offset=0.5)  # the reference is the systematic draw's runs
        assert np.array_equal(np.repeat(expected_rows, np.round(expected_shares * count).astype(int)), drawn)


def test_marginal_map_and_gating_kernels_give_the_reference_on_a_run():
    """A shared-association filter part way through a run: the landmark mixtures near a point and the gating of a
    scan against them, by kernel and by reference."""
    data = simulate("arena", robots=2, seed=1, duration=10.0)
    slam = FastSlam(FastSlamConfig(particles=20, association="shared", seed=0), [log.info for log in data.robots.values()])
    feed(slam, data)
    point = slam.map.gather(0, next(iter(slam.known_slots.values())))[0] + 0.3
    results = {}
    for compiled in (True, False):
        slam.config = slam.config.model_copy(update={"compiled": compiled})
        results[compiled] = shared.marginal_map(slam, (point, 4.0))
    assert 0 < results[True][0].size < len(slam.known_slots)
    for got, expected in zip(results[True], results[False]):
        np.testing.assert_allclose(got, expected, rtol=1e-10, atol=1e-12)
    robot = slam.robots["r1"]
    _, _, mean, cov = results[True]
    rng = np.random.default_rng(0)
    tentative = np.arange(mean.shape[0]) % 2 == 0
    pose, spread, drift = np.array([point[0] - 1.0, point[1], -0.2]), np.diag([0.1, 0.2, 0.05]), np.diag([0.3, 0.3, 0.01])
    z = np.vstack([np.column_stack([rng.uniform(0.5, 5.0, 5), rng.uniform(-3.0, 3.0, 5)]), [[12.0, 0.0]]])  # the last: fresh
    r = np.diag([0.01, 0.002])
    for flags in (tentative, ~tentative):  # the landmark in view is tentative, then not
        gating = {}
        for compiled in (True, False):
            slam.config = slam.config.model_copy(update={"compiled": compiled})
            gating[compiled] = shared._gating(slam, robot, pose, mean, cov, flags, spread, drift, r, z)
        assert np.ptp(gating[False][4]) > 10.0
        for got, expected in zip(gating[True][:5], gating[False][:5]):
            np.testing.assert_allclose(got, expected, rtol=1e-10, atol=1e-12)
        gated, fresh, in_view = gating[False][5:]
        assert gated.any() and not gated.all() and fresh.any() and not in_view.all()
        assert in_view.any() == (flags is tentative)
        for got, expected in zip(gating[True][5:], gating[False][5:]):
            np.testing.assert_array_equal(got, expected)


@pytest.mark.parametrize("seed, offset", [(0, (0.0, 0.0)), (3, (0.4, -0.2))])
def test_proposal_kernel_gives_the_reference_moments(seed, offset):
    """The FastSLAM 2.0 proposal's shift, posterior and weight: detection after detection in the kernel, all at once
    in the reference (the same update when the detections' noises are independent)."""
    rng = np.random.default_rng(seed)
    sensor = RangeBearingSensor(offset)
    lmap = random_map(seed)
    poses = np.zeros((40, 2, 3))
    poses[:, 0] = rng.normal([0.5, -0.5, 2.0], [0.3, 0.3, 0.2], (40, 3))
    root = rng.normal(0.0, 0.2, (40, 3, 3))
    prior = root @ np.swapaxes(root, -1, -2) + np.diag([0.01, 0.01, 0.001])
    prior[5] = 0.0  # a robot that has not moved: the proposal is the pose itself
    slots = np.array([3, 7, 0, 11, 5])
    truth = gaussians(lmap)[0][0, slots]
    z = sensor.observe(poses[0, 0], truth) + rng.normal(0.0, [0.1, 0.05], (5, 2))
    r = np.array([[0.04, 0.001], [0.001, 0.003]])
    slam = SimpleNamespace(map=lmap, pose=poses)
    robot = SimpleNamespace(index=0, sensor=sensor)
    n, m = 40, slots.size
    expected = proposal.proposal_moments_reference(slam, robot, z, r, prior, np.repeat(np.arange(n), m),
                                                   np.tile(np.arange(m), n), np.tile(slots, n))
    got = kernels.proposal_moments(lmap, sensor, poses[:, 0], prior, slots, z, r)
    assert np.ptp(expected[2]) > 1.0 and np.abs(expected[0]).max() > 0.05  # the scan moves and weighs particles apart
    for a, b in zip(got, expected):
        np.testing.assert_allclose(a, b, rtol=1e-8, atol=1e-10)
    assert np.all(got[0][5] == 0.0) and np.all(got[1][5] == 0.0)


@pytest.mark.parametrize("association, proposal_name", [("known", "fastslam1"), ("shared", "fastslam1"),
                                                         ("known", "fastslam2"), ("shared", "fastslam2")])
def test_whole_run_with_kernels_matches_the_reference(association, proposal_name):
    """Every kernel in the loop: a seeded noisy run gives the reference's poses and map (the random draws are the
    same, so only rounding may differ). Unicycle robots: with a rank-deficient motion covariance (a car standing
    still) a rounding difference can switch the square root of the draw from Cholesky to eigenvectors, another
    valid draw; the Ackermann integration is compared on its own above."""
    data = simulate("arena", robots=2, seed=3, duration=25.0, clutter_rate=0.5)
    infos = [log.info for log in data.robots.values()]
    runs = {}
    for compiled in (True, False):
        slam = FastSlam(FastSlamConfig(particles=30, association=association, seed=4, compiled=compiled,
                                       proposal=proposal_name), infos)
        feed(slam, data)
        runs[compiled] = slam
    assert runs[False].counts["resamples"] > 0 and runs[False].counts["detections"] > 100
    np.testing.assert_allclose(runs[True].pose, runs[False].pose, atol=1e-8)
    np.testing.assert_allclose(runs[True].logw, runs[False].logw, atol=1e-6)
    got, expected = runs[True].landmark_map(), runs[False].landmark_map()
    assert len(expected.means) > 5
    np.testing.assert_allclose(got.means, expected.means, atol=1e-8)
    for rid, (pose, cov) in runs[False].poses().items():
        np.testing.assert_allclose(runs[True].poses()[rid][0], pose, atol=1e-8)
        np.testing.assert_allclose(runs[True].poses()[rid][1], cov, atol=1e-10)


@pytest.mark.parametrize("half_fov, permanent", [(np.inf, np.inf), (0.5 * np.pi, 5.0)])
def test_negative_evidence_kernel_gives_the_reference_weights_and_deletions(half_fov, permanent):
    """Candidates on every side of the range limits and of the field of view's edge, some associated, some not: the
    kernel's miss weights, existence scores, deletions and count are the reference's (libm's erf and log1p differ
    from Cephes' and numpy's in the last bits only)."""
    rng = np.random.default_rng(11)
    particles, width, capacity = 30, 9, 40
    cand = np.stack([rng.choice(capacity, width, replace=False) for _ in range(particles)])
    zhat = np.stack([rng.uniform(-1.0, 32.0, (particles, width)), rng.uniform(-3.0, 3.0, (particles, width))], -1)
    considered = rng.random((particles, width)) < 0.7
    limits = np.array([0.5, 30.0, half_fov, 0.4, 0.05, 0.9, 1.0, 0.0, permanent])
    exist = rng.uniform(0.0, 3.0, (particles, capacity))
    hits = rng.integers(1, 9, (particles, capacity)).astype(np.int32)
    state = {name: (exist.copy(), np.ones((particles, capacity), bool)) for name in ("kernel", "reference")}
    got = kernels.negative_evidence_kernel(cand, zhat, considered, limits, state["kernel"][0], hits, state["kernel"][1])
    expected = evidence.negative_evidence_reference(cand, zhat, considered, limits, state["reference"][0], hits,
                                                    state["reference"][1])
    assert 5 < expected[-1] < considered.sum() - 5  # some deleted, some not
    assert np.all(expected[:-1] < 0.0) and np.any(np.isclose(zhat[..., 0], 30.0, atol=0.5) & considered)
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(state["kernel"][0], state["reference"][0], rtol=1e-12, atol=1e-14)
    np.testing.assert_array_equal(state["kernel"][1], state["reference"][1])
    touched = np.zeros((particles, capacity), bool)
    touched[np.nonzero(considered)[0], cand[considered]] = True
    assert np.array_equal(state["kernel"][0][~touched], exist[~touched])  # only the unassociated candidates age
    assert np.all(state["kernel"][1][~touched])
