"""Monte Carlo localization (Sehestedt and Schneider, "Monte Carlo Localization in Highly Symmetric Environments"):
KLD bound, resampling, clustering, likelihood, resetting."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robots.gaussian import systematic_resample
from robots.models import RangeBearingSensor, wrap_angle
from robots.simulator import simulate
from schemas.contract import OdomEvent
from schemas.messages import RobotInfo, SensorSpec
from services.mcl.clustering import cluster_particles
from services.mcl.config import MclConfig
from services.mcl.core import VARIANTS, MonteCarloLocalizer
from services.mcl.kld import bin_keys, kld_prefix_size, kld_sample_size, normal_quantile, support
from services.mcl.likelihood import LandmarkMap, ScanModel, scan_log_likelihood
from services.mcl.resampling import two_stage_resample
from services.mcl.resetting import poses_from_scan

R = np.diag([0.05**2, math.radians(1.0) ** 2])


def sensor(max_range=6.0, fov=2 * math.pi, p_detect=1.0) -> SensorSpec:
    return SensorSpec(max_range=max_range, fov=fov, noise_cov=R, detection_probability=p_detect)


def info(spec: SensorSpec | None = None) -> RobotInfo:
    return RobotInfo(robot_id="r1", stamp=0.0, motion_model="unicycle", sensor=spec or sensor(), odom_rate_hz=10.0,
                     scan_rate_hz=10.0)


def scan_model(spec: SensorSpec, config: MclConfig) -> ScanModel:
    return ScanModel.from_spec(spec, config.noise_scale, config.clutter_weight, config.miss_floor,
                               config.view_margin_range, config.view_margin_bearing, config.match_sigmas)


# ---------------------------------------------------------------- KLD bound


def test_kld_bound_uses_the_normal_quantile_not_delta():
    assert normal_quantile(0.01) == pytest.approx(2.3263478740408408, abs=1e-12)
    assert normal_quantile(0.05) == pytest.approx(1.6448536269514722, abs=1e-12)
    z = 2.3263478740408408
    for k, epsilon in ((2, 0.05), (10, 0.05), (50, 0.1), (400, 0.02)):
        a = 2.0 / (9.0 * (k - 1))
        expected = math.ceil((k - 1) / (2 * epsilon) * (1 - a + math.sqrt(a) * z) ** 3)
        assert kld_sample_size(k, epsilon, 0.01) == expected
        wrong = math.ceil((k - 1) / (2 * epsilon) * (1 - a + math.sqrt(a) * 0.01) ** 3)  # δ in place of z_(1-δ)
        assert kld_sample_size(k, epsilon, 0.01) > wrong


def test_kld_bound_grows_with_bins_and_shrinks_with_epsilon():
    sizes = kld_sample_size(np.arange(1, 200), 0.05, 0.01)
    assert sizes[0] == 0 and np.all(np.diff(sizes) > 0)
    assert kld_sample_size(100, 0.1, 0.01) < kld_sample_size(100, 0.05, 0.01)
    assert kld_sample_size(100, 0.05, 0.05) < kld_sample_size(100, 0.05, 0.01)


def test_kld_prefix_stops_at_the_first_n_that_meets_the_bound():
    assert kld_prefix_size(np.zeros(5000, np.int64), 0.05, 0.01, 50, 5000) == 50  # one bin: the minimum
    keys = np.arange(5000)  # every sample in a new bin: never enough, stop at the maximum
    assert kld_prefix_size(keys, 0.05, 0.01, 50, 5000) == 5000
    keys = np.repeat(np.arange(20), 250)[np.random.default_rng(0).permutation(5000)]  # 20 bins
    n = kld_prefix_size(keys, 0.05, 0.01, 10, 5000)
    k = np.unique(keys[:n]).size
    assert n >= kld_sample_size(k, 0.05, 0.01) and n - 1 < kld_sample_size(np.unique(keys[: n - 1]).size, 0.05, 0.01)


def test_bin_keys_separate_cells_and_wrap_heading():
    poses = np.array([[0.1, 0.1, 0.0], [0.2, 0.3, 0.05], [0.6, 0.1, 0.0], [0.1, 0.1, math.pi - 1e-9]])
    keys = bin_keys(poses, 0.5, math.radians(10))
    assert keys[0] == keys[1] and len(set(keys.tolist())) == 3
    assert support(poses, 0.5, math.radians(10)) == 3


# ---------------------------------------------------------------- resampling


def test_systematic_resampling_counts_follow_the_weights():
    weights = np.array([0.5, 0.25, 0.125, 0.125])
    index = systematic_resample(weights, 1000, np.random.default_rng(1))
    counts = np.bincount(index, minlength=4)
    assert np.all(np.abs(counts - 1000 * weights) <= 1)


def test_two_stage_resampling_keeps_every_significant_cluster():
    rng = np.random.default_rng(2)
    labels = np.repeat([0, 1, 2, 3], 250)
    weights = np.concatenate([np.full(250, 0.90), np.full(250, 0.09), np.full(250, 0.01), np.full(250, 1e-6)]) / 250
    weights /= weights.sum()
    plain = np.bincount(labels[systematic_resample(weights, 1000, rng)], minlength=4)
    assert plain[2] <= 11 and plain[3] == 0  # ordinary resampling keeps about 1 % of the third hypothesis
    index, new_weights = two_stage_resample(weights, labels, np.array([0, 1, 2]), 1000, rng, memory=0.0)
    counts = np.bincount(labels[index], minlength=4)
    assert counts[3] == 0 and np.all(np.abs(counts[:3] - 1000 / 3) <= 1)  # an equal share each; none for the dropped one
    assert np.bincount(labels[index], new_weights, 3) == pytest.approx([1 / 3] * 3)  # eq. 7: every cluster weighs the same
    _, carried = two_stage_resample(weights, labels, np.array([0, 1, 2]), 999, rng, memory=1.0)
    shares = [carried[k * 333:(k + 1) * 333].sum() for k in range(3)]
    assert shares == pytest.approx([0.90 / 1.0, 0.09, 0.01], rel=1e-3)  # the Bayesian weights survive


# ---------------------------------------------------------------- clustering


def test_grid_clustering_separates_rotated_hypotheses_and_merges_one_cloud():
    rng = np.random.default_rng(3)
    centres = np.array([[0.0, 1.0, math.pi / 2], [-1.0, 0.0, math.pi], [0.0, -1.0, -math.pi / 2], [1.0, 0.0, 0.0]])
    poses = np.repeat(centres, 100, axis=0) + rng.normal(0.0, [0.1, 0.1, 0.05], size=(400, 3))
    poses[:, 2] = wrap_angle(poses[:, 2])
    weights = np.full(400, 1 / 400)
    clusters = cluster_particles(poses, weights, np.ones(400), 2.0, math.pi / 4, 2.0, math.pi / 4, 1e-4)
    assert len(clusters) == 4 and np.allclose(clusters.weight, 0.25)
    assert sorted(clusters.count.tolist()) == [100] * 4
    cloud = np.array([1.0, 1.0, 0.0]) + rng.normal(0.0, [0.6, 0.6, 0.15], size=(400, 3))  # straddles cell borders
    single = cluster_particles(cloud, weights, np.ones(400), 2.0, math.pi / 4, 2.0, math.pi / 4, 1e-4)
    assert len(single) == 1 and np.allclose(single.mean[0], [1.0, 1.0, 0.0], atol=0.1)
    assert np.sqrt(single.cov[0, 0, 0]) == pytest.approx(0.6, rel=0.15)


# ---------------------------------------------------------------- likelihood


def test_likelihood_matches_the_exact_innovation_and_prefers_the_truth():
    rng = np.random.default_rng(4)
    landmarks = rng.uniform(-5.0, 5.0, size=(30, 2))
    config = MclConfig(miss_floor=1.0)
    spec = sensor()
    model = scan_model(spec, config)
    lmap = LandmarkMap(landmarks, model, config.lookup_cell, 4)
    truth = np.array([0.3, -0.2, 0.4])
    z = RangeBearingSensor().observe(truth, landmarks)
    seen = z[:, 0] <= 5.5
    z = z[seen] + rng.normal(0.0, [0.05, math.radians(1.0)], size=(int(seen.sum()), 2))
    poses = truth + np.array([[0, 0, 0], [0.03, -0.02, 0.01], [0.1, 0.05, -0.02], [1.0, 0.0, 0.0]])
    loglik, quality = scan_log_likelihood(poses, z, lmap, model)
    nu = RangeBearingSensor.innovation(z[None], RangeBearingSensor().observe(poses[:, None], landmarks[seen][None]))
    m2 = np.einsum("pni,ij,pnj->pn", nu, np.linalg.inv(model.noise_cov), nu)
    density = (1 - model.clutter_weight) * np.exp(model.log_gauss_norm - 0.5 * m2) + math.exp(model.log_floor)
    exact = np.log(density).sum(1)
    assert loglik[:3] == pytest.approx(exact[:3], abs=0.05 * len(z))
    assert loglik[0] > loglik[2] > loglik[3] and np.all((quality > 0) & (quality <= 1))
    assert loglik[3] >= len(z) * model.log_floor  # the clutter floor bounds the damage of every observation


def test_one_false_detection_costs_the_floor_and_a_missed_landmark_costs_p_miss():
    landmarks = np.array([[2.0, 0.0], [0.0, 2.0], [-2.0, 0.5]])
    config = MclConfig()
    model = scan_model(sensor(), config)
    lmap = LandmarkMap(landmarks, model, config.lookup_cell, 2)
    pose = np.zeros((1, 3))
    z = RangeBearingSensor().observe(pose[0], landmarks)
    full, _ = scan_log_likelihood(pose, z, lmap, model)
    clutter, _ = scan_log_likelihood(pose, np.vstack([z, [[4.0, 2.5]]]), lmap, model)
    assert clutter[0] - full[0] == pytest.approx(model.log_floor, abs=1e-6)
    missing, _ = scan_log_likelihood(pose, z[:2], lmap, model)
    assert missing[0] - full[0] == pytest.approx(math.log(model.miss_probability) - model.log_peak, abs=1e-3)


# ---------------------------------------------------------------- sensor resetting


def test_poses_drawn_from_a_scan_include_the_true_pose():
    rng = np.random.default_rng(5)
    landmarks = rng.uniform(0.0, 20.0, size=(60, 2))
    config = MclConfig()
    model = scan_model(sensor(fov=math.pi), config)
    lmap = LandmarkMap(landmarks, model, config.lookup_cell, 2)
    truth = np.array([10.0, 10.0, 1.0])
    z = RangeBearingSensor().observe(truth, landmarks)
    z = z[(z[:, 0] < 6.0) & (np.abs(z[:, 1]) < math.pi / 2)]
    def close(poses):
        near = np.hypot(*(poses[:, :2] - truth[:2]).T) < 0.2
        return int((near & (np.abs(wrap_angle(poses[:, 2] - truth[2])) < 0.05)).sum())

    plain = poses_from_scan(z, lmap, model, 2000, 3.0, 0.05, 0.02, 2.0, rng, draws=1)
    poses = poses_from_scan(z, lmap, model, 2000, 3.0, 0.05, 0.02, 2.0, rng, draws=8)
    assert close(poses) >= 10 and close(poses) > 2 * close(plain)  # the one-point check enriches the right poses
    loglik, _ = scan_log_likelihood(poses, z, lmap, model)
    best = poses[np.argmax(loglik)]
    assert np.hypot(*(best[:2] - truth[:2])) < 0.2


# ---------------------------------------------------------------- the filter


def random_scene(seed):
    """(landmarks (40, 2), true pose, the scan from it out to 6 m) of a random world."""
    landmarks = np.random.default_rng(seed).uniform(-8.0, 8.0, size=(40, 2))
    truth = np.array([0.0, 0.0, 0.3])
    z = RangeBearingSensor().observe(truth, landmarks)
    return landmarks, truth, z[z[:, 0] < 6.0]


def test_every_variant_runs_and_unknown_variant_is_refused():
    landmarks, truth, z = random_scene(6)
    for variant in VARIANTS:
        mcl = MonteCarloLocalizer(landmarks, info(), MclConfig(variant=variant, particles=300, max_particles=2000))
        for _ in range(4):
            mcl.predict(np.zeros(2), 0.1, np.diag([1e-4, 1e-4]))
            report = mcl.update(z)
        assert report.particles_after == mcl.count > 0 and mcl.weights.sum() == pytest.approx(1.0)
        assert np.hypot(*(mcl.best()[0][:2] - truth[:2])) < 0.3, variant
    with pytest.raises(ValueError):
        MonteCarloLocalizer(landmarks, info(), MclConfig.model_construct(variant="nope"))


def test_known_start_pose_tracks_without_global_initialisation():
    landmarks = np.array([[2.0, 0.0], [0.0, 2.0], [-2.0, 0.5], [1.0, -3.0]])
    start = info().model_copy(update={"start_pose": np.array([0.5, 0.5, 0.2]), "start_pose_cov": np.diag([1e-3] * 3)})
    mcl = MonteCarloLocalizer(landmarks, start, MclConfig(variant="csrl", particles=200))
    assert mcl.initialized and mcl.restarts == 0
    mcl.update(RangeBearingSensor().observe(np.array([0.5, 0.5, 0.2]), landmarks))
    assert np.allclose(mcl.best()[0], [0.5, 0.5, 0.2], atol=0.05) and mcl.restarts == 0


def test_map_files_load_as_landmark_arrays(tmp_path):
    from services.mcl.service import load_map_file

    landmarks = np.array([[1.0, 2.0], [3.5, -4.0]])
    np.save(tmp_path / "map.npy", landmarks)
    np.savetxt(tmp_path / "map.txt", landmarks)
    assert np.array_equal(load_map_file(str(tmp_path / "map.npy")), landmarks)
    assert np.allclose(load_map_file(str(tmp_path / "map.txt")), landmarks)
    np.savetxt(tmp_path / "bad.txt", np.ones((3, 3)))
    with pytest.raises(ValueError):
        load_map_file(str(tmp_path / "bad.txt"))
    np.save(tmp_path / "nan.npy", np.array([[np.nan, 1.0]]))
    with pytest.raises(ValueError):
        load_map_file(str(tmp_path / "nan.npy"))


def _per_control_reference(particles, controls, dt, cov, config, rng):
    """The prediction before odometry was buffered: one noisy control and one diffusion per particle and control."""
    from robots.models import unicycle_step

    for control in controls:
        noisy = control + rng.standard_normal((len(particles), 2)) @ (np.linalg.cholesky(cov) * config.motion_noise_scale).T
        particles = unicycle_step(particles, noisy, dt)
        particles[:, :2] += rng.normal(0.0, config.diffusion_xy * math.sqrt(dt), size=(len(particles), 2))
        particles[:, 2] = wrap_angle(particles[:, 2] + rng.normal(0.0, config.diffusion_theta * math.sqrt(dt),
                                                                   size=len(particles)))
    return particles


@pytest.mark.parametrize("compiled", [True, False])
@pytest.mark.parametrize("diffusion", [False, True])
def test_buffered_odometry_moves_the_particles_as_one_draw_per_control_does(compiled, diffusion):
    """Twenty controls on a turning arc, applied as one draw from their integrated motion when the particles are
    next looked at: the same mean and covariance as drawing at every control. The diffusion is added once for the
    time buffered, like FastSLAM's pose noise: its variances are the per-control ones', its correlations with the
    later motion are left out."""
    start = np.array([1.0, -2.0, 0.7])
    noise = {} if diffusion else {"diffusion_xy": 0.0, "diffusion_theta": 0.0}
    config = MclConfig(particles=20000, max_particles=20000, compiled=compiled, max_batch_s=10.0, **noise)
    mcl = MonteCarloLocalizer(np.array([[5.0, 0.0]]), info().model_copy(
        update={"start_pose": start, "start_pose_cov": np.diag([1e-12] * 3)}), config, np.random.default_rng(3))
    controls = np.column_stack([np.linspace(0.5, 1.0, 20), np.linspace(-0.8, 0.8, 20)])
    cov = np.diag([0.05**2, 0.1**2])
    for control in controls:
        mcl.predict(control, 0.05, cov)
    assert len(mcl._pending) == 20  # nothing moved yet ...
    batched = mcl.particles.copy()  # ... until the particles are read
    assert not mcl._pending
    reference = _per_control_reference(np.tile(start, (20000, 1)), controls, 0.05, cov, config,
                                       np.random.default_rng(4))
    assert np.hypot(*(batched.mean(0)[:2] - start[:2])) > 0.5  # it did move
    assert np.allclose(batched.mean(0), reference.mean(0), atol=2e-3)
    got, want = np.cov(batched.T), np.cov(reference.T)
    if diffusion:
        got, want = np.diag(got), np.diag(want)
    assert np.allclose(got, want, rtol=0.06, atol=1e-6)


def test_odometry_is_applied_at_least_every_max_batch_s_and_a_new_set_drops_what_moved_the_old():
    start = info().model_copy(update={"start_pose": np.zeros(3), "start_pose_cov": np.diag([1e-6] * 3)})
    mcl = MonteCarloLocalizer(np.array([[5.0, 0.0]]), start, MclConfig(particles=100, max_batch_s=0.25))
    for _ in range(5):
        mcl.predict(np.array([1.0, 0.0]), 0.1, np.diag([1e-6, 1e-6]))
    assert len(mcl._pending) == 2 and mcl._particles[:, 0].mean() == pytest.approx(0.3, abs=0.05)
    mcl.particles = np.zeros((50, 3))
    assert not mcl._pending and mcl.count == 50 and np.all(mcl.particles == 0.0)


# ---------------------------------------------------------------- the fleet


def test_fleet_waits_for_a_map_then_localizes_restarts_and_answers_one_shot_queries():
    from schemas.contract import OdomEvent, ScanEvent
    from services.mcl.fleet import MclFleet

    landmarks, truth, z = random_scene(7)
    scan = ScanEvent("r1", 0, 0.1, z[:, 0], z[:, 1], None, R)
    fleet = MclFleet(MclConfig(variant="csrl", particles=300))
    fleet.add_robot(info())
    assert "r1" in fleet and fleet.robots["r1"].mcl is None and fleet.on_scan(scan) is None
    assert fleet.poses()["r1"][1][0, 0] >= 1e6 and fleet.hypotheses("r1") == []
    with pytest.raises(ValueError):
        fleet.localize_once(z, sensor(), 500, seed=1)
    fleet.set_map(landmarks)  # the robot waiting for a map gets its filter
    for k in range(5):
        fleet.on_odometry(OdomEvent("r1", k, 0.1 * k, 0.1, np.zeros(2), np.diag([1e-4, 1e-4])))
        report = fleet.on_scan(scan)
    state = fleet.robots["r1"]
    assert report is not None and state.scans == 5 and state.localized == report.localized
    assert np.hypot(*(fleet.poses()["r1"][0][:2] - truth[:2])) < 0.3 and fleet.hypotheses("r1")
    fleet.add_robot(state.info)  # a new run of the robot: localized from scratch
    fresh = fleet.robots["r1"]
    assert fresh.scans == 0 and fresh.mcl is not state.mcl and fresh.mcl.count == 0
    once = fleet.localize_once(z, sensor(), 500, seed=1)
    assert np.hypot(*(once.best()[0][:2] - truth[:2])) < 0.3 and fleet.robots["r1"].mcl.count == 0
    tracked = MclFleet(MclConfig(particles=100), landmarks)  # a known start pose is tracked from it
    tracked.add_robot(info().model_copy(update={"start_pose": truth, "start_pose_cov": np.diag([1e-3] * 3)}))
    assert tracked.robots["r1"].mcl.initialized
    fleet.remove_robot("r1")
    assert "r1" not in fleet and fleet.landmark_map().means.shape == (0, 2)


def test_signatures_localize_in_a_symmetric_world_within_a_few_scans():
    """Detections with landmark ids are weighed against their own landmark: a robot in a symmetric world (where
    the unsigned likelihood holds several hypotheses) is localized, at the true pose, within a few scans."""
    data = simulate("grid196", robots=1, seed=4, duration=20.0)
    log = data.robots["r1"]
    info = log.info.model_copy(update={"start_pose": None, "start_pose_cov": None})
    results = {}
    for signatures in (True, False):
        config = MclConfig(particles=500, seed=0, use_signatures=signatures)
        mcl = MonteCarloLocalizer(data.landmarks, info, config, np.random.default_rng(0), data.landmark_ids)
        scans = 0
        for event in data.events():
            if isinstance(event, OdomEvent):
                mcl.predict(event.control, event.dt, event.control_cov)
                continue
            if not len(event.ranges):
                continue
            report = mcl.update(event.observations, event.landmark_ids)
            scans += 1
            if report.localized or scans >= 10:
                break
        best = mcl.best()[0]
        truth = log.truth_at(np.array([event.stamp]))[0]
        results[signatures] = (mcl.localized, float(np.hypot(*(best[:2] - truth[:2]))), scans)
    localized, error, scans = results[True]
    assert localized and error < 0.3 and scans <= 6, results
    assert not (results[False][0] and results[False][1] < 0.3 and results[False][2] <= scans), results


def test_a_hypothesis_collapsed_on_one_landmark_circle_is_not_localized_and_a_contradicting_detection_restarts():
    """With signatures, a global localization's dominant hypothesis must explain two landmarks apart by id before
    it is localized; a tight cloud on the wrong arc of one landmark's circle (what resampling leaves after a robot
    saw one landmark for long) is localized without the check, and with it is dropped at the first detection of
    another landmark, the localization starting again from that scan."""
    landmarks = np.array([[0.0, 0.0], [4.0, 0.0], [0.0, 5.0]])
    ids = np.array([10, 11, 12])
    truth = np.array([2.0, -2.0, math.pi / 2])
    wrong = np.array([-2.0, -2.0, 0.0])  # also 2.83 m from landmark 10, facing it from the other side
    spec = sensor()
    see = RangeBearingSensor()
    z_truth = see.observe(truth, landmarks)
    z_wrong_one = see.observe(wrong, landmarks[:1])
    localized = {}
    for baseline in (0.0, 0.3):
        mcl = MonteCarloLocalizer(landmarks, info(spec), MclConfig(particles=300, seed=0, localized_baseline_m=baseline),
                                  np.random.default_rng(0), ids)
        mcl.update(z_wrong_one, ids[:1])  # global localization from a scan of one landmark: its circle
        mcl.particles = wrong + np.random.default_rng(1).normal(0.0, [0.02, 0.02, 0.005], (300, 3))
        mcl.weights = np.full(300, 1.0 / 300)
        for _ in range(4):  # landmark 10 alone, seen as from the wrong pose: the wrong cloud explains it
            mcl.update(z_wrong_one, ids[:1])
        localized[baseline] = mcl.localized
        if baseline:
            assert mcl.contradictions == 0
            restarts = mcl.restarts
            mcl.update(np.vstack([z_wrong_one, see.observe(truth, landmarks[1:2])]), ids[:2])  # 11 contradicts
            assert mcl.contradictions == 1 and mcl.restarts == restarts + 1 and not mcl.localized
            for _ in range(5):
                mcl.update(z_truth, ids)
            assert mcl.localized
            assert np.hypot(*(mcl.best()[0][:2] - truth[:2])) < 0.2
    assert localized == {0.0: True, 0.3: False}


@pytest.mark.parametrize("source, signed, least", [("dslam", False, 6), ("central", True, 3), ("central", False, 6)])
def test_the_service_localizes_against_a_map_only_once_it_can_tell_poses_apart(source, signed, least):
    """Live as offline (``services.placement``): 3 landmarks with ids, 6 without (D-SLAM numbers its own)."""
    from types import SimpleNamespace

    from schemas.config import MclSettings
    from services.mcl.service import MclService

    service = MclService(MclSettings(source=source, map_period_s=0.0))
    taken = []
    for count in range(1, 9):
        landmarks = np.column_stack([np.arange(count, dtype=float), np.zeros(count)])
        ids = list(range(count)) if signed else None
        service._on_map(SimpleNamespace(landmarks=landmarks, landmark_ids=ids, robots=[]))
        taken.append(service.fleet.landmarks is not None and service.fleet.landmarks.shape[0] == count)
    assert taken == [count >= least for count in range(1, 9)]
    assert service.extra["maps_too_small"] == least - 1


def test_the_map_is_prepared_once_for_the_robots_and_queries_that_share_it():
    """Every robot of a fleet with one sensor and every localization query weigh against one prepared map; a new map,
    another sensor or another landmark set gets its own; the cache holds a few and comes back empty from a pickle."""
    import pickle

    from services.mcl.fleet import MclFleet
    from services.mcl.likelihood import MapCache

    rng = np.random.default_rng(9)
    landmarks = rng.uniform(0.0, 20.0, (40, 2))
    fleet = MclFleet(MclConfig(particles=50), landmarks, use_start_pose=False)
    for rid in ("r1", "r2"):
        fleet.add_robot(info().model_copy(update={"robot_id": rid}))
    maps = {rid: state.mcl.map for rid, state in fleet.robots.items()}
    assert maps["r1"] is maps["r2"]
    z = RangeBearingSensor().observe(np.array([10.0, 10.0, 0.0]), landmarks)[:6]
    assert fleet.localize_once(z, sensor(), 100, seed=1).map is maps["r1"]
    assert fleet.localize_once(z, sensor(max_range=4.0), 100, seed=1).map is not maps["r1"]
    fleet.set_map(landmarks + 1.0)
    assert fleet.robots["r1"].mcl.map is fleet.robots["r2"].mcl.map is not maps["r1"]
    np.testing.assert_array_equal(fleet.robots["r1"].mcl.map.landmarks, landmarks + 1.0)
    cache = MapCache(size=2)
    model = scan_model(sensor(), MclConfig())
    built = [cache.get(landmarks + k, model, 1.0, 4) for k in range(3)]
    assert cache.get(landmarks + 2, model, 1.0, 4) is built[2] and cache.get(landmarks, model, 1.0, 4) is not built[0]
    restored = pickle.loads(pickle.dumps(fleet))
    assert len(fleet.maps) == 3 and len(restored.maps) == 0  # r1 and r2's two maps, the 4 m query's
    np.testing.assert_array_equal(restored.robots["r1"].mcl.map.landmarks, landmarks + 1.0)
    assert len(cache) == 2
    old = pickle.loads(pickle.dumps(fleet))
    del old.__dict__["maps"]  # a checkpoint written before the cache existed
    assert isinstance(pickle.loads(pickle.dumps(old)).maps, MapCache)
