"""Central FastSLAM core: batched prediction, noiseless worlds, consistency, MHT, clutter, bad input, robots joining."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.stats import chi2

from benchmarks.support.paper001 import two_beacons
from central.fastslam.config import FastSlamConfig
from central.fastslam import resampling, shared
from central.fastslam.core import FastSlam, make_estimator
from central.fastslam.aligned_map import AlignedMap, SlotTable
from central.fastslam.landmarks import LandmarkMap
from robots.gaussian import systematic_resample
from robots.models import AckermannModel, UnicycleModel, integrate_controls, se2_accumulate, se2_compose, wrap_angle
from robots.simulator import simulate
from robots.worlds import _sensor, make_world
from schemas.contract import OdomEvent, RunOptions, ScanEvent, SettingsError


def feed(estimator, dataset, robots=None):
    for event in dataset.events(robots=robots):
        if isinstance(event, OdomEvent):
            estimator.on_odometry(event)
        elif isinstance(event, ScanEvent):
            estimator.on_scan(event)


def nearest(means: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Distance from each estimated landmark to the nearest true one."""
    return np.linalg.norm(means[:, None] - truth[None], axis=-1).min(1)


def snapshot(f: FastSlam) -> list:
    return [f.pose.copy(), f.logw.copy(), f.map.mean.copy(), f.map.cov.copy(), f.map.valid.copy(), f.map.exist.copy(),
            {rid: (list(r.controls), r.pose_time, r.last_odom_stamp, r.last_scan_stamp) for rid, r in f.robots.items()}]


def test_se2_accumulate_is_sequential_composition():
    rng = np.random.default_rng(0)
    increments = rng.normal(0, [0.3, 0.1, 0.4], (25, 3))
    pose = np.zeros(3)
    expected = [pose]
    for inc in increments:
        pose = se2_compose(pose, inc)
        expected.append(pose)
    np.testing.assert_allclose(se2_accumulate(increments), np.array(expected), atol=1e-12)


@pytest.mark.parametrize("model, controls", [
    (UnicycleModel(), np.column_stack([np.full(12, 1.0), np.linspace(-0.6, 0.8, 12)])),
    (AckermannModel(2.83, 0.76), np.column_stack([np.full(12, 4.0), np.linspace(-0.2, 0.3, 12)])),
])
def test_batched_prediction_matches_stepwise_draws(model, controls):
    """One draw from N(Δ̄, Σ_Δ) per interval has the moments of one draw per control (first order)."""
    rng = np.random.default_rng(1)
    dts = np.full(controls.shape[0], 0.05)
    cov = np.diag([0.05**2, 0.03**2])
    delta, sigma = integrate_controls(model, controls, dts, np.broadcast_to(cov, (controls.shape[0], 2, 2)))
    n = 20000
    pose = np.zeros((n, 3))
    for u, dt in zip(controls, dts):
        pose = model.step(pose, u + rng.multivariate_normal(np.zeros(2), cov, n), dt)
    np.testing.assert_allclose(pose.mean(0), delta, atol=4e-3)
    resid = pose - delta
    resid[:, 2] = wrap_angle(resid[:, 2])
    np.testing.assert_allclose(np.cov(resid.T), sigma, atol=0.05 * np.abs(sigma).max())


def test_landmark_map_appends_compacts_and_grows():
    lm = LandmarkMap(3, capacity=2)
    lm.reserve(2)
    slots = lm.append(np.array([0, 0, 2]), np.arange(6.0).reshape(3, 2), np.tile(np.eye(2), (3, 1, 1)), 1.0,
                      np.array([7, 8, 9]))
    assert slots.tolist() == [0, 1, 0] and lm.used.tolist() == [2, 0, 1]
    lm.valid[0, 0] = False
    lm.reserve(2)  # particle 0 needs 4 slots: compaction frees one, then the capacity doubles
    assert lm.capacity == 4 and lm.used.tolist() == [1, 0, 1]
    np.testing.assert_allclose(lm.mean[0, 0], [2.0, 3.0])
    assert lm.label[0, 0] == 8
    lm.select(np.array([2, 2, 0]))
    assert lm.counts().tolist() == [1, 1, 1] and lm.label[:, 0].tolist() == [9, 9, 8]


def test_aligned_map_shares_blocks_after_resampling_and_copies_on_write():
    """Resampling copies block tables, not landmarks; a particle that changes a landmark gets its own copy of that
    block, and the other particles keep theirs."""
    lm = AlignedMap(3, block=4)
    slots = lm.allocate(6)  # two blocks
    means = np.arange(36.0).reshape(3, 6, 2)
    lm.write(slots, means, np.broadcast_to(np.eye(2), (3, 6, 2, 2)))
    assert lm.blocks_in_use() == 6
    lm.select(np.array([1, 1, 1]))  # every particle a copy of particle 1: one set of blocks, shared
    assert lm.blocks_in_use() == 2 and lm.refs.max() == 3
    np.testing.assert_array_equal(lm.gather(np.arange(3)[:, None], slots[None])[0], np.broadcast_to(means[1], (3, 6, 2)))
    changed = lm.gather(np.arange(3)[:, None], slots[None])[0]
    changed[0, 5] = [-1.0, -2.0]
    lm.write(slots[5:], changed[:, 5:], np.broadcast_to(np.eye(2), (3, 1, 2, 2)))  # the second block, all particles
    assert lm.blocks_in_use() == 4  # the first block still shared by all three, the second now one per particle
    after = lm.gather(np.arange(3)[:, None], slots[None])[0]
    np.testing.assert_array_equal(after[0, 5], [-1.0, -2.0])
    np.testing.assert_array_equal(after[1:], np.broadcast_to(means[1], (2, 6, 2)))


def test_aligned_map_reuses_released_slots_and_stores_an_agreed_map_once():
    lm = AlignedMap(4, block=4)
    slots = lm.allocate(5)
    lm.label[slots], lm.valid[slots] = np.arange(10, 15), True
    lm.release(slots[[1, 3]])
    assert lm.counts().tolist() == [3, 3, 3, 3]
    again = lm.allocate(3)
    assert again.tolist() == [1, 3, 5] and not lm.valid[again].any() and (lm.label[again] == -1).all()
    fresh = AlignedMap(100, block=4)
    agreed = fresh.allocate(40)
    fresh.write(agreed, np.arange(80.0).reshape(40, 2), np.broadcast_to(np.eye(2), (40, 2, 2)))
    assert fresh.blocks_in_use() == 10  # one copy for 100 particles
    np.testing.assert_array_equal(fresh.gather(99, agreed)[0], np.arange(80.0).reshape(40, 2))


def test_shared_association_reuses_the_slots_of_dropped_tentative_landmarks(monkeypatch):
    """Clutter makes and drops many tentative landmarks: their slots are reused, every id keeps its landmark,
    and the estimate is the one the filter gives without reuse (which only saves memory)."""
    data = simulate("arena", robots=1, seed=5, duration=40.0, clutter_rate=3.0)

    def run() -> FastSlam:
        slam = FastSlam(FastSlamConfig(particles=10, association="shared", seed=0), [log.info for log in data.robots.values()])
        feed(slam, data)
        return slam

    slam = run()
    assert slam.counts["landmarks_dropped_tentative"] > 4 * slam.map.capacity  # slots reused many times over
    assert sorted(slam.known_slots.values()) == np.flatnonzero(slam.map.valid).tolist()
    assert slam.map.label[list(slam.known_slots.values())].tolist() == list(slam.known_slots.keys())
    monkeypatch.setattr(AlignedMap, "release", lambda self, slots: self.valid.__setitem__(np.asarray(slots), False))
    sprawling = run()
    assert sprawling.map.capacity > 4 * slam.map.capacity
    np.testing.assert_allclose(slam.landmark_map().means, sprawling.landmark_map().means, atol=1e-9)
    np.testing.assert_allclose(slam.poses()["r1"][0], sprawling.poses()["r1"][0], atol=1e-9)


def test_slot_table_arrays_follow_every_change():
    """The id and slot arrays of the table, kept between scans, are rebuilt after any change of it."""
    table = SlotTable({4: 0, 7: 1})
    steps = [lambda t: t.__setitem__(9, 2), lambda t: t.__delitem__(4), lambda t: t.update({11: 3}),
             lambda t: t.setdefault(12, 5), lambda t: t.pop(7), lambda t: t.__ior__({13: 6}), lambda t: t.popitem(),
             lambda t: t.clear()]
    for step in steps:
        ids, slots = table.arrays()
        ids[:] = -1  # copies: the table's own arrays are untouched
        step(table)
        ids, slots = table.arrays()
        assert ids.tolist() == list(table.keys()) and slots.tolist() == list(table.values())


def test_weights_follow_every_change_of_the_log_weights():
    """The normalised weights, computed once per change of the log-weights, follow assignments and += alike."""
    slam = FastSlam(FastSlamConfig(particles=5, association="shared", seed=0))
    np.testing.assert_array_equal(slam.weights(), np.full(5, 0.2))
    slam.logw += np.arange(5.0)
    np.testing.assert_array_equal(slam.weights(), resampling.weights(np.arange(5.0)))
    slam.logw = np.array([0.0, -np.inf, 0.0, -np.inf, 0.0])
    np.testing.assert_array_equal(slam.weights(), [1 / 3, 0.0, 1 / 3, 0.0, 1 / 3])
    assert slam.effective_particles() == pytest.approx(3.0)


def quiet_world(name: str = "arena"):
    """A world whose noise is negligible next to its sensor's stated accuracy."""
    world = make_world(name, 0)
    return dataclasses.replace(world, sensor=_sensor(6.0, 1.2, 1e-3, 1e-4, min_range=0.3), control_std=(1e-7, 1e-7))


@pytest.mark.parametrize("association", ["known", "shared", "nn", "mht"])
def test_noiseless_world_gives_the_true_map_and_path(association):
    data = simulate(quiet_world(), robots=2, seed=0, duration=20.0)
    infos = [log.info.model_copy(update={"start_pose_cov": np.zeros((3, 3))}) for log in data.robots.values()]
    slam = FastSlam(FastSlamConfig(particles=10, association=association, seed=0), infos)
    feed(slam, data)
    estimate = slam.landmark_map()
    seen = {int(i) for log in data.robots.values() for i in log.det_id if i >= 0}
    if association == "shared":  # a landmark seen fewer than confirm_hits times stays tentative
        counts = np.bincount(np.concatenate([log.det_id for log in data.robots.values()]))
        seen = {i for i in seen if counts[i] >= slam.config.confirm_hits}
    assert len(estimate.means) == len(seen)
    assert nearest(estimate.means, data.landmarks).max() < 0.01
    for rid, (pose, _) in slam.poses().items():
        error = pose - data.robots[rid].truth_pose[-1]
        assert np.hypot(error[0], error[1]) < 0.01 and abs(wrap_angle(error[2])) < 1e-3
    assert not slam.rejected


def test_known_association_is_consistent():
    """Pose NEES averaged over seeded runs stays within the two-sided 95 % χ² bounds at most time steps."""
    runs = 5
    nees = []
    for seed in range(runs):
        data = simulate("arena", robots=1, seed=seed, duration=10.0)
        slam = make_estimator(RunOptions("fastslam", "known", 300, seed), [log.info for log in data.robots.values()])
        values = []
        for event in data.events():
            if isinstance(event, OdomEvent):
                slam.on_odometry(event)
                continue
            slam.on_scan(event)
            mean, cov = slam.poses()["r1"]
            error = mean - data.robots["r1"].truth_at(np.array([event.stamp]))[0]
            error[2] = wrap_angle(error[2])
            values.append(error @ np.linalg.solve(cov, error))
        nees.append(values[1:])
    average = np.mean(nees, 0)
    low, high = chi2.ppf([0.025, 0.975], 3 * runs) / runs
    inside = (average > low) & (average < high)
    assert inside.mean() >= 0.8, f"ANEES inside [{low:.2f}, {high:.2f}] at only {inside.mean():.0%} of steps"


def test_mht_keeps_and_separates_two_close_beacons():
    """Howard, "Multi-robot simultaneous localization and mapping using particle filters", Fig. 2-3: two beacons
    18 cm apart with 15 cm range noise end up as two landmarks, one on each."""
    world = two_beacons()
    data = simulate(world, robots=1, seed=0, duration=70.0)
    slam = FastSlam(FastSlamConfig(particles=50, association="mht", seed=0), [data.robots["r1"].info])
    feed(slam, data)
    assert slam.counts["mht_splits"] > 0
    means = slam.landmark_map().means
    pair = world.landmarks[:2]
    near = means[np.linalg.norm(means - pair.mean(0), axis=1) < 0.4]
    assert len(near) == 2
    error = np.linalg.norm(near[:, None] - pair[None], axis=-1)
    own = error.argmin(1)
    assert sorted(own.tolist()) == [0, 1], "both landmarks are nearest the same beacon"
    assert error[[0, 1], own].max() < 0.5 * np.linalg.norm(pair[0] - pair[1]), "a landmark is not on its own beacon"
    separation = np.linalg.norm(near[0] - near[1])
    assert 0.09 < separation < 0.3


@pytest.mark.parametrize("association", ["nn", "mht"])
def test_clutter_born_landmarks_die_in_per_particle_association(association):
    """Clutter-born landmarks never reach the published map, and most die inside the filter too (those never seen
    again stay tentative)."""
    data = simulate("arena", robots=1, seed=3, duration=25.0, clutter_rate=1.5)
    slam = FastSlam(FastSlamConfig(particles=20, association=association, seed=0), [data.robots["r1"].info])
    feed(slam, data)
    clutter = int((data.robots["r1"].det_id < 0).sum())
    assert clutter > 250
    assert slam.counts["landmarks_deleted"] > 0
    means = slam.landmark_map().means
    assert len(means) >= 10
    assert nearest(means, data.landmarks).max() < 0.5, "a landmark born of clutter reached the map"
    best = slam.best_particle()
    valid = slam.map.valid[best]
    survivors = int((nearest(slam.map.mean[best, valid], data.landmarks) > 0.5).sum())
    assert survivors < 0.15 * clutter, f"{survivors} clutter-born landmarks of {clutter} clutter detections survive"


def test_shared_association_keeps_clutter_out_of_the_map_and_the_weights():
    """Clutter starts tentative landmarks that never weigh particles, never reach the map and are dropped when
    missed; the map holds the true landmarks and at most a few spurious ones. (Robot-to-robot detections are
    left out: this is about clutter alone.)"""
    data = simulate("arena", robots=2, seed=3, duration=25.0, clutter_rate=1.5)
    slam = FastSlam(FastSlamConfig(particles=20, association="shared", seed=0, robot_detections=False),
                    [log.info for log in data.robots.values()])
    feed(slam, data)
    clutter = sum(int((log.det_id < 0).sum()) for log in data.robots.values())
    assert clutter > 500
    assert slam.counts["landmarks_dropped_tentative"] + slam.counts["detections_ignored"] > 0.8 * clutter
    means = slam.landmark_map().means
    true_seen = {int(i) for log in data.robots.values() for i in log.det_id if i >= 0}
    assert len(means) >= 0.9 * len(true_seen)
    assert int((nearest(means, data.landmarks) > 0.5).sum()) <= 2, "clutter reached the map"
    for rid, (pose, _) in slam.poses().items():
        assert np.hypot(*(pose[:2] - data.robots[rid].truth_pose[-1, :2])) < 0.5


def test_marginal_map_near_a_point_is_the_full_marginal_cut_to_a_disc():
    """The association asks for the landmarks near the robot only: the same means and covariances as the whole
    marginal map, for exactly the landmarks whose mean lies within the radius."""
    data = simulate("arena", robots=2, seed=1, duration=10.0)
    slam = FastSlam(FastSlamConfig(particles=20, association="shared", seed=0), [log.info for log in data.robots.values()])
    feed(slam, data)
    ids, _, means, covs = shared.marginal_map(slam)
    point, radius = means[0] + 0.3, 4.0
    near_ids, _, near_means, near_covs = shared.marginal_map(slam, (point, radius))
    inside = np.hypot(*(means - point).T) < radius
    assert 0 < inside.sum() < len(ids)
    np.testing.assert_array_equal(near_ids, ids[inside])
    np.testing.assert_allclose(near_means, means[inside], atol=1e-12)
    np.testing.assert_allclose(near_covs, covs[inside], atol=1e-12)
    w, slots = resampling.weights(slam.logw), np.array([slam.known_slots[int(i)] for i in near_ids])
    particle_means, particle_covs = slam.map.gather(np.arange(w.size)[:, None], slots[None])
    spread = np.einsum("p,pki,pkj->kij", w, *[particle_means - near_means] * 2)
    own = np.einsum("p,pkij->kij", w, particle_covs)
    np.testing.assert_allclose(near_covs, own + spread, atol=1e-12)  # mixture: mean covariance + spread of means


def test_association_mixtures_come_from_a_weighted_draw_of_particles_when_the_filter_holds_more():
    """With more particles than ``association_particles``, the mixtures the association gates against are those of
    that many particles drawn systematically by weight (kernel and reference alike), close to the whole mixture;
    the published map still mixes every particle."""
    data = simulate("arena", robots=2, seed=1, duration=10.0)
    config = FastSlamConfig(particles=400, association="shared", seed=0, association_particles=50)
    slam = FastSlam(config, [log.info for log in data.robots.values()])
    feed(slam, data)
    w = resampling.weights(slam.logw)
    assert np.ptp(w) > 0  # unequal weights: the draw is not trivially uniform
    _, _, all_means, all_covs = shared.marginal_map(slam)
    point = all_means[0] + 0.3
    results = {}
    for compiled in (True, False):
        slam.config = config.model_copy(update={"compiled": compiled})
        results[compiled] = shared.marginal_map(slam, (point, 4.0))
    ids, slots, means, covs = results[True]
    assert ids.size > 0
    for got, expected in zip(results[True], results[False]):
        np.testing.assert_allclose(got, expected, rtol=1e-10, atol=1e-12)
    drawn = systematic_resample(w, 50, None, offset=0.5)
    particle_means, particle_covs = slam.map.gather(drawn[:, None], slots[None])
    np.testing.assert_allclose(means, particle_means.mean(0), atol=1e-12)
    spread = np.einsum("pki,pkj->kij", *[particle_means - means] * 2) / drawn.size
    np.testing.assert_allclose(covs, particle_covs.mean(0) + spread, atol=1e-12)
    full = {int(i): k for k, i in enumerate(shared.marginal_map(slam)[0])}
    rows = [full[int(i)] for i in ids]
    scale = np.sqrt(all_covs[rows][:, [0, 1], [0, 1]])
    assert np.all(np.abs(means - all_means[rows]) < 0.5 * scale + 1e-9)  # a Monte Carlo estimate of the same mixture
    slam.config = config.model_copy(update={"association_particles": 0})
    every_ids, _, every_means, _ = shared.marginal_map(slam, (point, 4.0))
    np.testing.assert_allclose(every_means, all_means[[full[int(i)] for i in every_ids]], atol=1e-12)


def test_shared_association_tentative_landmarks_do_not_weigh_particles():
    """A detection that starts or updates a tentative landmark leaves the weights as they were."""
    data = simulate("arena", robots=1, seed=0, duration=3.0)
    slam = FastSlam(FastSlamConfig(particles=30, association="shared", confirm_hits=1000, seed=0), [data.robots["r1"].info])
    feed(slam, data)
    assert slam.counts["detections_matched"] > 10
    assert np.ptp(slam.logw) == 0.0 and slam.counts.get("resamples", 0) == 0
    assert len(slam.landmark_map().means) == 0
    weighed = FastSlam(FastSlamConfig(particles=30, association="shared", confirm_hits=1, seed=0), [data.robots["r1"].info])
    feed(weighed, data)
    assert np.ptp(weighed.logw) > 0.0 or weighed.counts["resamples"] > 0


@pytest.mark.parametrize("solver", ["jcbb", "exact"])
def test_shared_association_survives_drift_beyond_the_particle_cloud(solver):
    """Odometry far worse than its model (every particle off by more than its gate): per-particle nn starts
    duplicates, shared association re-finds the mapped landmarks."""
    world = dataclasses.replace(make_world("arena", 0), control_std=(0.03, 0.15))
    data = simulate(world, robots=1, seed=2, duration=60.0)
    log = data.robots["r1"]
    log.odom_cov = log.odom_cov / 100.0  # the model believes the odometry 10× more precise than it is
    counts = {}
    for association in ("nn", "shared"):
        slam = FastSlam(FastSlamConfig(particles=30, association=association, shared_solver=solver, seed=0), [log.info])
        feed(slam, data)
        counts[association] = len(slam.landmark_map().means)
    true_seen = len({int(i) for i in log.det_id if i >= 0})
    assert counts["shared"] <= true_seen + 2
    assert counts["nn"] > true_seen + 4


def test_bad_input_is_counted_and_never_corrupts_the_state():
    data = simulate("arena", robots=1, seed=0, duration=2.0)
    slam = FastSlam(FastSlamConfig(particles=20, association="nn", seed=0), [data.robots["r1"].info])
    feed(slam, data)
    before = snapshot(slam)
    good_odom = data.robots["r1"].odom(len(data.robots["r1"].odom_stamp) - 1)
    good_scan = data.robots["r1"].scan(len(data.robots["r1"].scan_stamp) - 1)
    bad = [
        dataclasses.replace(good_odom, control=np.array([np.nan, 0.0]), stamp=good_odom.stamp + 1),
        dataclasses.replace(good_odom, dt=-0.1, stamp=good_odom.stamp + 1),
        dataclasses.replace(good_odom, control_cov=np.array([[1.0, 2.0], [2.0, 1.0]]), stamp=good_odom.stamp + 1),
        dataclasses.replace(good_odom, control=np.zeros(3), stamp=good_odom.stamp + 1),
        dataclasses.replace(good_odom, stamp=good_odom.stamp - 5.0),
        dataclasses.replace(good_odom, robot_id="ghost"),
        dataclasses.replace(good_scan, ranges=np.full(good_scan.ranges.shape, np.nan), stamp=good_scan.stamp + 1),
        dataclasses.replace(good_scan, ranges=-np.abs(good_scan.ranges) - 1, stamp=good_scan.stamp + 1),
        dataclasses.replace(good_scan, bearings=np.zeros(good_scan.ranges.size + 1), stamp=good_scan.stamp + 1),
        dataclasses.replace(good_scan, noise_cov=np.array([[0.01, 0.0], [0.0, -1.0]]), stamp=good_scan.stamp + 1),
        dataclasses.replace(good_scan, stamp=good_scan.stamp - 5.0),
        dataclasses.replace(good_scan, stamp=float("nan")),
    ]
    for event in bad:
        accepted = slam.on_odometry(event) if isinstance(event, OdomEvent) else slam.on_scan(event)
        assert not accepted
    after = snapshot(slam)
    for a, b in zip(before[:-1], after[:-1]):
        np.testing.assert_array_equal(a, b)
    assert before[-1] == after[-1]
    assert sum(slam.rejected.values()) == len(bad)
    assert {"bad_odometry", "time_backwards", "unknown_robot", "bad_scan_values", "negative_range", "bad_scan_shape",
            "bad_scan_noise"} <= set(slam.rejected)
    assert not slam.place_robot("r1", np.zeros(3), np.eye(3))


def test_robot_with_unknown_start_waits_until_placed():
    data = simulate("arena", robots=2, seed=0, duration=5.0, unknown_start=[False, True])
    slam = FastSlam(FastSlamConfig(particles=200, association="known", seed=0), [log.info for log in data.robots.values()])
    assert set(slam.poses()) == {"r1"} and slam.is_waiting("r2") and not slam.is_waiting("r1")
    feed(slam, data, robots=["r2"])
    assert slam.rejected["robot_not_placed"] > 0 and slam.map.counts().max() == 0
    truth = data.robots["r2"].truth_pose[-1]
    assert not slam.place_robot("r2", truth, np.full((3, 3), np.nan))
    assert not slam.place_robot("r2", truth, np.eye(3), stamp=float("nan"))
    assert slam.place_robot("r2", truth, np.diag([0.04, 0.04, 0.01]), stamp=float(data.robots["r2"].truth_stamp[-1]))
    assert slam.has_robot("r2") and not slam.is_waiting("r2")
    assert slam.pose_stamp("r2") == data.robots["r2"].truth_stamp[-1]
    pose, cov = slam.poses()["r2"]
    np.testing.assert_allclose(pose[:2], truth[:2], atol=0.05)
    np.testing.assert_allclose(np.diag(cov), [0.04, 0.04, 0.01], rtol=0.3)
    assert not slam.place_robot("r2", truth, np.eye(3))


def test_a_robot_placed_mid_run_moves_on_from_the_placement_time():
    """A pose fix at time t and the controls after it: the robot ends where the truth does."""
    data = simulate("arena", robots=1, seed=2, duration=12.0, unknown_start=[True])
    log = data.robots["r1"]
    slam = FastSlam(FastSlamConfig(particles=50, association="known", seed=0), [log.info])
    fix = int(np.searchsorted(log.truth_stamp, log.truth_stamp[0] + 4.0))
    slam.place_robot("r1", log.truth_pose[fix], np.diag([1e-4, 1e-4, 1e-5]), stamp=float(log.truth_stamp[fix]))
    for event in log.events(with_truth=False):
        if event.stamp > log.truth_stamp[fix]:
            (slam.on_odometry if isinstance(event, OdomEvent) else slam.on_scan)(event)
    pose, _ = slam.poses()["r1"]
    assert slam.pose_stamp("r1") == pytest.approx(log.end_stamp)
    assert np.hypot(*(pose[:2] - log.truth_pose[-1, :2])) < 0.15


def test_a_robot_that_has_not_moved_can_be_parked_again():
    data = simulate("arena", robots=2, seed=0, duration=2.0)
    slam = FastSlam(FastSlamConfig(particles=10, association="known", seed=0), [log.info for log in data.robots.values()])
    assert slam.unplace("r1") is not None and slam.is_waiting("r1") and not slam.has_robot("r1")
    assert slam.has_robot("r2") and not slam.is_waiting("r2") and set(slam.poses()) == {"r2"}
    assert slam.robots["r2"].index == 0 and slam.pose.shape[1] == 1
    feed(slam, data, robots=["r2"])
    assert slam.unplace("r2") is None and slam.unplace("ghost") is None
    pose, _ = slam.poses()["r2"]
    assert np.hypot(*(pose[:2] - data.robots["r2"].truth_pose[-1, :2])) < 0.1


def test_a_robot_joining_later_shares_the_map():
    data = simulate("arena", robots=2, seed=1, duration=20.0)
    slam = FastSlam(FastSlamConfig(particles=30, association="known", seed=0), [data.robots["r1"].info])
    feed(slam, data, robots=["r1"])
    landmarks_before = set(slam.known_slots)
    slam.add_robot(data.robots["r2"].info)
    feed(slam, data, robots=["r2"])
    assert set(slam.poses()) == {"r1", "r2"}
    assert len(set(slam.known_slots) & landmarks_before) > 0
    pose, _ = slam.poses()["r2"]
    assert np.hypot(*(pose[:2] - data.robots["r2"].truth_pose[-1, :2])) < 0.3


def test_registered_as_an_estimator():
    from services.estimators import make_estimator as registry_make

    data = simulate("arena", robots=1, seed=0, duration=1.0)
    infos = [data.robots["r1"].info]
    options = RunOptions("fastslam", "mht", 7, 3, settings={"proposal": "fastslam2", "exclusive": False})
    slam = registry_make(options, infos)
    assert isinstance(slam, FastSlam)
    assert slam.config.particles == 7 and slam.config.proposal == "fastslam2" and not slam.config.exclusive
    assert slam.config.association == "mht" and slam.config.seed == 3
    assert make_estimator(RunOptions("fastslam", "nn"), infos).config.particles == FastSlamConfig().particles
    with pytest.raises(ValueError):
        registry_make(RunOptions("fastslam", "jcbb"), infos)
    with pytest.raises(ValueError):
        registry_make(RunOptions("fastslam", "nn", settings={"no_such_setting": 1}), infos)


@pytest.mark.parametrize("association, proposal, folds", [
    ("shared", "auto", True), ("known", "auto", False), ("nn", "auto", False), ("mht", "auto", False),
    ("known", "fastslam2", True), ("shared", "fastslam1", False),
])
def test_auto_proposal_is_fastslam2_with_shared_association_only(association, proposal, folds):
    """``auto`` folds the scan into the proposal where the association is one per scan (shared): there one kernel
    does it; known ids keep FastSLAM 1.0 and its paper figures unless asked."""
    config = FastSlamConfig(association=association, proposal=proposal)
    assert config.fastslam2 is folds
    assert FastSlamConfig().proposal == "auto" and FastSlamConfig().fastslam2


@pytest.mark.parametrize("association, settings, named", [
    ("jcbb", {}, "association"),
    ("nn", {"no_such_setting": 1}, "no_such_setting"),
    ("nn", {"max_obs_range": "abc"}, "max_obs_range"),
    ("nn", {"proposal": "fastslam3"}, "proposal"),
    ("nn", {"gate_probability": 0.999, "new_landmark_probability": 0.99}, "new_landmark_probability"),
])
def test_bad_settings_are_one_line_errors(association, settings, named):
    """A bad ``--set`` name or value is a SettingsError of one line naming the setting, never a numpy error."""
    with pytest.raises(SettingsError) as error:
        make_estimator(RunOptions("fastslam", association, settings=settings), [])
    message = str(error.value)
    assert "\n" not in message and named in message and "fastslam" in message


def test_same_seed_same_result():
    data = simulate("arena", robots=2, seed=2, duration=3.0, clutter_rate=1.0)
    results = []
    for _ in range(2):
        slam = FastSlam(FastSlamConfig(particles=10, association="mht", seed=5), [log.info for log in data.robots.values()])
        feed(slam, data)
        results.append((slam.pose.copy(), slam.landmark_map().means))
    np.testing.assert_array_equal(results[0][0], results[1][0])
    np.testing.assert_array_equal(results[0][1], results[1][1])


def test_fastslam2_proposal_tracks_a_robot():
    data = simulate("arena", robots=1, seed=4, duration=20.0)
    slam = FastSlam(FastSlamConfig(particles=20, association="nn", proposal="fastslam2", seed=0), [data.robots["r1"].info])
    feed(slam, data)
    pose, _ = slam.poses()["r1"]
    assert np.hypot(*(pose[:2] - data.robots["r1"].truth_pose[-1, :2])) < 0.2
    assert nearest(slam.landmark_map().means, data.landmarks).max() < 0.3
    assert math.isfinite(slam.effective_particles())


def test_turn_slip_widens_the_drawn_heading_only_when_set():
    """``turn_slip``: the buffered motion's heading variance grows by the robot's announced turn_slip_var per radian
    turned; off by default, and a robot announcing none is unchanged."""
    from central.fastslam import motion

    data = simulate("arena", robots=1, duration=1.0)
    info = data.robots["r1"].info.model_copy(update={"turn_slip_var": 0.02})
    events = [OdomEvent("r1", k, 0.1 * (k + 1), 0.1, np.array([0.5, -0.4]), np.diag([1e-4, 1e-4])) for k in range(5)]

    def pending(config: FastSlamConfig, robot_info) -> tuple[np.ndarray, np.ndarray]:
        slam = FastSlam(config, [robot_info])
        for event in events:
            slam.on_odometry(event)
        return motion.pending_motion(slam.robots["r1"], slam.config)

    delta, plain = pending(FastSlamConfig(particles=4, seed=0), info)
    _, slipped = pending(FastSlamConfig(particles=4, seed=0, turn_slip=True), info)
    assert delta[2] == pytest.approx(-0.2)
    assert slipped[2, 2] - plain[2, 2] == pytest.approx(0.02 * 0.2, rel=1e-9)
    np.testing.assert_allclose(np.delete(slipped.ravel(), 8), np.delete(plain.ravel(), 8))
    _, unannounced = pending(FastSlamConfig(particles=4, seed=0, turn_slip=True), data.robots["r1"].info)
    np.testing.assert_allclose(unannounced, plain)


def robot_sighting_filter(**settings):
    """Two robots at their start poses in one filter of 400 particles; r2's particles spread 0.5 m around its true
    pose, r1's exactly at its own. Returns (filter, r1's detection of r2 at its true pose, scan noise)."""
    data = simulate("arena", robots=2, seed=0, duration=1.0)
    infos = [log.info for log in data.robots.values()]
    slam = FastSlam(FastSlamConfig(particles=400, association="shared", seed=0, **settings), infos)
    rng = np.random.default_rng(5)
    r1, r2 = slam.robots["r1"], slam.robots["r2"]
    truth1, truth2 = infos[0].start_pose, infos[1].start_pose
    slam.pose[:, r2.index] = truth2 + rng.normal(0.0, [0.5, 0.5, 0.05], (400, 3))
    noise = np.diag([0.01, 0.001])
    z = r1.sensor.observe(np.asarray(truth1, float), np.asarray(truth2, float)[None, :2])[0]
    r1.pose_time = r2.pose_time = 0.0
    event = ScanEvent("r1", 0, 0.0, np.zeros(0), np.zeros(0), None, noise, ["r2"], np.array([z[0]]), np.array([z[1]]))
    return slam, event, noise, np.asarray(truth2, float)


def test_a_robot_detection_pulls_the_detected_robot_toward_where_it_was_seen():
    """r1 sees r2 (no landmark in the scan): the particles whose r2 explains the detection gain weight, so r2's
    estimate moves to within a fraction of its spread of the truth; with robot detections off nothing moves."""
    from central.fastslam import robot_detections
    slam, event, noise, truth2 = robot_sighting_filter()
    before = np.hypot(*(slam.poses()["r2"][0][:2] - truth2[:2]))
    spread = math.sqrt(np.trace(slam.poses()["r2"][1][:2, :2]))
    robot_detections.weigh(slam, slam.robots["r1"], event, noise)
    after = np.hypot(*(slam.poses()["r2"][0][:2] - truth2[:2]))
    assert slam.counts["robot_detections_used"] == 1
    assert after < 0.35 * spread and after < 0.5 * before
    assert 1.0 < slam.effective_particles() < 400.0  # informative, not a single survivor
    off, event, noise, _ = robot_sighting_filter(robot_detections=False)
    off.on_scan(event)
    assert off.counts["robot_detections_used"] == 0 and np.ptp(off.logw) == 0.0


def test_robot_detection_noise_scale_widens_their_likelihood():
    """With no motion pending and no relative position allowed, the log-weight differences a detection makes
    shrink by the noise scale."""
    from central.fastslam import robot_detections
    spreads = {}
    for scale in (1.0, 4.0):
        slam, event, noise, _ = robot_sighting_filter(robot_detection_noise_scale=scale, robot_detection_position_sd=0.0)
        robot_detections.weigh(slam, slam.robots["r1"], event, noise)
        spreads[scale] = slam.logw - slam.logw.max()
    np.testing.assert_allclose(spreads[4.0], spreads[1.0] / 4.0, rtol=1e-9, atol=1e-9)


def test_robot_detection_position_sd_adds_the_relative_position_through_the_jacobian():
    """Each particle's log-weight gains a Gaussian log-density whose covariance is kR + σ² H Hᵀ, H the detection's
    Jacobian by the detected robot's position (here by finite differences), and a wider σ flattens the weights."""
    from central.fastslam import robot_detections
    sigma, scale = 0.4, 4.0
    slam, event, noise, _ = robot_sighting_filter(robot_detection_position_sd=sigma)
    plain, *_ = robot_sighting_filter(robot_detection_position_sd=0.0)
    before = slam.logw.copy()
    robot_detections.weigh(slam, slam.robots["r1"], event, noise)
    robot_detections.weigh(plain, plain.robots["r1"], event, noise)
    sensor, pose = slam.robots["r1"].sensor, slam.pose[:, slam.robots["r1"].index]
    target = slam.pose[:, slam.robots["r2"].index, :2]
    z = np.array([event.robot_ranges[0], event.robot_bearings[0]])
    for i in (0, 7, 123):
        h = np.empty((2, 2))
        for k in range(2):
            step = np.zeros(2)
            step[k] = 1e-6
            h[:, k] = (sensor.observe(pose[i], (target[i] + step)[None])[0]
                       - sensor.observe(pose[i], (target[i] - step)[None])[0]) / 2e-6
        s = scale * noise + sigma ** 2 * h @ h.T
        nu = sensor.innovation(z, sensor.observe(pose[i], target[i][None])[0])
        expected = -0.5 * nu @ np.linalg.solve(s, nu) - 0.5 * np.log(np.linalg.det(s)) - math.log(2 * math.pi)
        assert slam.logw[i] - before[i] == pytest.approx(expected, abs=1e-5)
    assert np.ptp(slam.logw) < 0.5 * np.ptp(plain.logw)


def test_robot_detection_position_sd_defaults_to_a_decimetre_without_ids_and_none_with_them():
    """None resolves by the association (MR.CLAM: better without barcodes, worse with them); a value set wins."""
    assert FastSlamConfig(association="shared").robot_detection_relative_sd == 0.1
    assert FastSlamConfig(association="known").robot_detection_relative_sd == 0.0
    assert FastSlamConfig(association="known", robot_detection_position_sd=0.3).robot_detection_relative_sd == 0.3


def test_motion_noise_scale_defaults_to_the_announced_covariance_times_the_robots_gain():
    """None resolves to 1 for every association (the quarter fitted on Victoria Park is gone: each robot's gain adapts
    instead, shared association only); a value set wins, and it scales the covariance the particles draw from."""
    assert FastSlamConfig(association="shared").motion_scale == 1.0
    assert FastSlamConfig(association="known").motion_scale == 1.0
    assert FastSlamConfig(association="shared", motion_noise_scale=2.0).motion_scale == 2.0
    assert FastSlamConfig(association="shared").adapts_motion_noise
    assert not FastSlamConfig(association="known").adapts_motion_noise
    data = simulate("arena", robots=1, seed=0, duration=2.0)
    event = next(e for e in data.events() if isinstance(e, OdomEvent))
    for association, scale in (("shared", 0.25), ("known", 0.25), ("known", 1.0)):
        slam = FastSlam(FastSlamConfig(particles=5, association=association, seed=0, motion_noise_scale=scale),
                        [data.robots["r1"].info])
        slam.on_odometry(event)
        np.testing.assert_allclose(slam.robots["r1"].scaled_cov, scale * np.asarray(event.control_cov))


def test_turn_gains_learn_how_much_a_robot_over_counts_its_turns():
    """Odometry that reports 8 % more turn than the robot made: with turn gains the particles that turn by about
    1/1.08 of it survive, and the heading stays closer to the truth than without them; with them off every gain
    stays 1 and no draw is spent on them (the same filter as before they existed)."""
    data = simulate("arena", robots=1, seed=3, duration=60.0)
    log = data.robots["r1"]

    def run(**settings) -> tuple[FastSlam, float]:
        slam = FastSlam(FastSlamConfig(particles=200, association="known", seed=1, **settings), [log.info])
        for event in data.events():
            if isinstance(event, OdomEvent):
                event = dataclasses.replace(event, control=np.asarray(event.control) * [1.0, 1.08])
                slam.on_odometry(event)
            elif isinstance(event, ScanEvent):
                slam.on_scan(event)
        pose, _ = slam.poses()["r1"]
        return slam, abs(wrap_angle(pose[2] - log.truth_pose[-1, 2]))

    learned, heading_error = run(turn_gain_std=0.05, turn_gain_walk=0.002)
    gain = float(learned.weights() @ learned.turn_gain[:, 0])
    assert gain == pytest.approx(1.0 / 1.08, abs=0.03)
    plain, plain_error = run()
    assert np.all(plain.turn_gain == 1.0)
    assert heading_error < plain_error
    from central.fastslam import motion

    def draws_for_gains(**settings) -> bool:  # does taking buffered motion move the random stream?
        slam = FastSlam(FastSlamConfig(particles=20, association="known", seed=0, **settings), [log.info])
        slam.on_odometry(next(e for e in data.events() if isinstance(e, OdomEvent)))
        state = slam.rng.bit_generator.state
        assert motion.take_pending(slam, slam.robots["r1"]) is not None
        return slam.rng.bit_generator.state != state

    assert not draws_for_gains() and draws_for_gains(turn_gain_walk=0.002)


def test_each_robots_turn_scale_follows_how_much_its_odometry_over_counts_its_turns():
    """Shared association, ``turn_scale_adapt``: a fleet whose odometry says 1 / 0.9 of every turn learns a turn scale
    near 0.9 from pairs of its detections (robots/odometry_noise.py) and turns its particles by it; off (the default),
    the scale stays 1; an Ackermann robot's never adapts (its turn comes from the steering through the wheelbase)."""
    from central.fastslam import noise_gain

    data = simulate("arena", robots=2, seed=2, duration=120.0)
    for log in data.robots.values():
        log.odom_control = log.odom_control * (1.0, 1.0 / 0.9)
    infos = [log.info for log in data.robots.values()]
    slam = FastSlam(FastSlamConfig(particles=20, association="shared", seed=0, turn_scale_adapt=True), infos)
    feed(slam, data)
    scales = slam.extra_metrics()["turn_scale"]
    assert all(0.86 < scale < 0.94 for scale in scales.values()), scales
    fixed = FastSlam(FastSlamConfig(particles=20, association="shared", seed=0), infos)  # off by default
    feed(fixed, data)
    assert set(fixed.extra_metrics()["turn_scale"].values()) == {1.0}
    assert noise_gain.start(slam, "ackermann").turn_scale_bounds is None


@pytest.mark.parametrize("looser", [1.0, 16.0])
def test_each_robots_odometry_noise_gain_follows_what_its_detections_show(looser):
    """Shared association: a fleet whose odometry announces ``looser`` times its real covariance draws a gain of it
    that falls towards 1 / ``looser`` (robots/odometry_noise.py: 0.16-0.2 after 120 s at 16 times), and stays near
    1 when the announcement is right; with the adaptation off every robot draws the announced covariance."""
    data = simulate("arena", robots=2, seed=2, duration=120.0)
    for log in data.robots.values():
        log.odom_cov = log.odom_cov * looser
    infos = [log.info for log in data.robots.values()]
    slam = FastSlam(FastSlamConfig(particles=20, association="shared", seed=0), infos)
    feed(slam, data)
    gains = slam.extra_metrics()["noise_gain"]
    assert slam.counts["noise_gain_pairs"] > 20
    for gain in gains.values():
        assert (0.5 < gain <= 1.0) if looser == 1.0 else (1.0 / looser < gain < 0.35), gains
    fixed = FastSlam(FastSlamConfig(particles=20, association="shared", seed=0, motion_noise_adapt=False), infos)
    feed(fixed, data)
    assert "noise_gain" not in fixed.extra_metrics()
    assert all(robot.scaled_cov is None or np.allclose(robot.scaled_cov, robot.checked_cov) for robot in fixed.robots.values())
