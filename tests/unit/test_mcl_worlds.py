"""MCL in simulated worlds: hypotheses kept in a symmetric world, recovery from kidnapping, the offline estimator."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.support.mcl_scenarios import kidnapped, symmetric_cross, trace_run
from robots.simulator import simulate
from schemas.contract import RunOptions, SettingsError
from services.estimators import make_estimator
from services.mcl.config import MclConfig
from services.mcl.core import MonteCarloLocalizer


@pytest.fixture(scope="module")
def symmetric_run():
    return simulate(symmetric_cross(), seed=0, duration=15.0, unknown_start=True)


@pytest.mark.parametrize("variant", ["csrl", "cluster_kld_srl"])
def test_clustered_variants_keep_the_symmetric_hypotheses(symmetric_run, variant):
    log = symmetric_run.robots["r1"]
    mcl = MonteCarloLocalizer(symmetric_run.landmarks, log.info, MclConfig(variant=variant, particles=400))
    trace = trace_run(mcl, symmetric_run.events(), lambda t: log.truth_at(np.array([t]))[0])
    held = np.asarray(trace.hypotheses)
    assert held.min() >= 2 and np.mean(held == 4) > 0.9  # all four twins, nearly always
    assert not any(trace.localized)  # never claims one pose where four are equally right
    assert min(np.min(np.hypot(*(m[:, :2] - log.truth_at(np.array([t]))[0][:2]).T))
               for t, m in zip(trace.stamp, trace.means)) < 0.3  # the truth is one of them


def test_kld_sampling_collapses_in_the_symmetric_world(symmetric_run):
    log = symmetric_run.robots["r1"]
    mcl = MonteCarloLocalizer(symmetric_run.landmarks, log.info, MclConfig(variant="kld", particles=400))
    trace = trace_run(mcl, symmetric_run.events(), lambda t: log.truth_at(np.array([t]))[0])
    assert trace.hypotheses[-1] == 1  # without two-stage resampling one twin wins by chance


@pytest.mark.parametrize("variant", ["cluster_kld_srl", "csrl"])
def test_recovery_from_kidnapping(variant):
    dataset = simulate("office", robots=2, seed=1, duration=20.0)
    events, truth = kidnapped(dataset, "r1", "r2", at=8.0)
    config = MclConfig(variant=variant, seed=2, particles=500)
    mcl = MonteCarloLocalizer(dataset.landmarks, dataset.robots["r1"].info, config)
    trace = trace_run(mcl, events, truth)
    assert trace.first_converged(0.5, 0.2) is not None and trace.first_converged(0.5, 0.2) < 2.0
    back = trace.first_converged(0.5, 0.2, after=8.0)
    assert back is not None and back - 8.0 < 4.0
    assert trace.converged(0.5, 0.2)[-1]


def test_offline_estimator_reports_convergence():
    dataset = simulate("office", robots=1, seed=4, duration=6.0)
    log = dataset.robots["r1"]
    options = RunOptions(estimator="mcl", seed=0, settings={"variant": "cluster_kld_srl"}, landmarks=dataset.landmarks,
                         truth={"r1": (log.truth_stamp, log.truth_pose)})
    estimator = make_estimator(options, [log.info])
    for event in dataset.events():
        (estimator.on_odometry if hasattr(event, "control") else estimator.on_scan)(event)
    metrics = estimator.extra_metrics()
    assert metrics["localized"] == {"r1": True} and metrics["hypotheses_max"]["r1"] >= 1
    assert 0.0 <= metrics["converge_s"]["r1"] < 3.0
    pose, _ = estimator.poses()["r1"]
    assert np.hypot(*(pose[:2] - log.truth_pose[-1, :2])) < 0.5
    assert estimator.landmark_map().means.shape == (0, 2)
    with pytest.raises(ValueError, match="map"):
        make_estimator(RunOptions(estimator="mcl"), [log.info])
    with pytest.raises(SettingsError, match="unknown mcl setting varient"):
        make_estimator(RunOptions(estimator="mcl", landmarks=dataset.landmarks, settings={"varient": "kld"}), [log.info])
