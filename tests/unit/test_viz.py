"""The Rerun scene (pure: messages -> archetypes at entity paths) and recordings read back with Rerun's own reader."""

from __future__ import annotations

import json
from collections import Counter

import numpy as np
import pytest
from rerun.chunk import RrdReader
from scipy.stats import chi2

from robots.simulator import simulate
from schemas.contract import RunOptions
from schemas.messages import (
    Estimate, GroundTruth, MapEstimate, MclPose, PoseHypothesis, RobotEstimate, RobotInfo, SensorSpec, ServiceStats,
)
from services.cli import main as cli_main
from services.evaluation.metrics import Trajectory
from services.offline import run_estimator
from services.viz.config import VizConfig
from services.viz.recording import save_offline_run
from services.viz.scene import (
    PALETTE, PathBuilder, Record, Scene, Throttle, covariance_ellipses, robot_colour, source_colour, thin_by_time,
    time_arguments,
)


def rows_by_entity(path) -> Counter:
    """Rows of every non-static chunk per entity path, and of the static ones under ``static:PATH``."""
    rows: Counter = Counter()
    for chunk in RrdReader(str(path)).stream():
        rows[("static:" if chunk.is_static else "") + chunk.entity_path] += chunk.num_rows
    return rows


def column_lengths(path, entity: str, column: str) -> list[int]:
    """Lengths of ``column`` in each row logged at ``entity``."""
    lengths = []
    for chunk in RrdReader(str(path)).stream():
        if chunk.entity_path == entity:
            lengths += [len(cell) for cell in chunk.to_record_batch().column(column).to_pylist()]
    return lengths


def test_each_robot_has_a_fixed_colour_and_each_source_a_shade_of_it():
    assert robot_colour("r1") == PALETTE[0] and robot_colour("r3") == PALETTE[2]
    assert robot_colour("scout") == robot_colour("scout")
    shades = {source_colour("r2", s) for s in ("truth", "central", "dslam", "mcl")}
    assert len(shades) == 4
    assert source_colour("r2", "central") == PALETTE[1]
    assert all(c >= p for c, p in zip(source_colour("r2", "truth"), PALETTE[1]))  # truth is lighter


def test_covariance_ellipses_lie_on_the_confidence_contour():
    rng = np.random.default_rng(4)
    means = rng.normal(size=(5, 2))
    factors = rng.normal(size=(5, 2, 2))
    covs = factors @ np.swapaxes(factors, 1, 2) + 0.01 * np.eye(2)
    polygons = covariance_ellipses(means, covs, 0.95, 32)
    assert polygons.shape == (5, 33, 2)
    np.testing.assert_allclose(polygons[:, 0], polygons[:, -1])  # closed
    offsets = polygons - means[:, None]
    mahalanobis = np.einsum("lvi,lij,lvj->lv", offsets, np.linalg.inv(covs), offsets)
    np.testing.assert_allclose(mahalanobis, chi2.ppf(0.95, 2), rtol=1e-6)


def test_a_path_is_logged_in_throttled_segments_that_join_up():
    builder = PathBuilder("p", (1, 2, 3), 1.0, period_s=1.0, segment_points=5, min_step=0.01)
    points = [(float(k), 0.0) for k in range(12)]
    records = []
    for k, xy in enumerate(points):
        records += builder.add(xy, stamp=float(k), wall=None, now=0.1 * k)  # 12 points within 1.1 s
    records += builder.flush(now=1.15, force=True)
    paths = [r.path for r in records]
    assert paths[:2] == ["p/0", "p/0"]  # first re-log at once, then the full segment; nothing else in between
    assert paths[-1] == "p/2" and paths.count("p/1") == 1
    strips = {}
    for record in records:
        strips[record.path] = record.archetype.strips.as_arrow_array().to_pylist()[0]
    joined = strips["p/0"] + strips["p/1"][1:] + strips["p/2"][1:]
    assert [tuple(p) for p in joined] == points
    assert builder.add((11.001, 0.0), 12.0, None, 5.0) == []  # closer than min_step: skipped


def test_throttle_logs_the_latest_item_once_its_time_comes():
    throttle = Throttle(0.5)
    made = []

    def item(k):
        return lambda: made.append(k) or [Record(f"x/{k}", None)]

    assert [r.path for r in throttle.offer("map", 0.0, item(0))] == ["x/0"]
    assert throttle.offer("map", 0.1, item(1)) == [] and throttle.offer("map", 0.2, item(2)) == []
    assert throttle.flush(0.3) == []
    assert [r.path for r in throttle.flush(0.6)] == ["x/2"]
    assert made == [0, 2]  # the item superseded while held back is never built
    assert throttle.flush(5.0, force=True) == []


def test_time_arguments_take_the_data_clock_and_the_wall_clock():
    assert time_arguments(Record("a", None, stamp=12.5)) == [("stamp", {"duration": 12.5})]
    assert time_arguments(Record("a", None, stamp=1.25e9, wall=1.7e9)) == [
        ("stamp", {"timestamp": 1.25e9}), ("wall", {"timestamp": 1.7e9})]
    assert time_arguments(Record("a", None, static=True)) == []


def _sensor() -> SensorSpec:
    return SensorSpec(max_range=8.0, fov=np.pi, noise_cov=np.diag([0.01, 0.001]))


def test_scene_turns_fleet_messages_into_entities():
    scene = Scene(VizConfig(map_hz=1.0))
    scene.robot_info(RobotInfo(robot_id="r2", stamp=0.0, motion_model="unicycle", sensor=_sensor(),
                               odom_rate_hz=10, scan_rate_hz=10))
    assert scene.arrow_length("r2") == pytest.approx(0.8)
    truth = scene.ground_truth(GroundTruth(robot_id="r2", seq=0, stamp=1.0, pose=np.array([1.0, 2.0, 0.5])), 100.0, 0.0)
    assert [r.path for r in truth] == ["world/robots/r2/truth/pose"]  # one point: no path yet
    arrow = truth[0].archetype
    np.testing.assert_allclose(arrow.vectors.as_arrow_array().to_pylist()[0], 0.8 * np.array([np.cos(0.5), np.sin(0.5)]),
                               rtol=1e-6)
    covs = np.stack([np.eye(2) * 0.01] * 3)
    estimate = Estimate(seq=0, stamp=2.0, robots=[
        RobotEstimate(robot_id=rid, stamp=2.0, pose=np.array([k, 0.0, 0.0]), cov=np.eye(3) * 0.01)
        for k, rid in enumerate(("r1", "r2"))], landmarks=np.arange(6.0).reshape(3, 2), landmark_covs=covs,
        landmark_ids=np.array([6, 7, 8]), particles=10, effective_particles=5.0)
    paths = [r.path for r in scene.estimate(estimate, 101.0, 0.1)]
    assert paths == ["world/robots/r1/central/pose", "world/robots/r2/central/pose", "world/map/central/landmarks",
                     "world/map/central/ellipses"]
    assert scene.estimate(estimate.model_copy(update={"seq": 1}), 101.5, 0.5)[-1].path.endswith("central/pose")
    held = scene.flush(1.2)
    assert [r.path for r in held] == ["world/map/central/landmarks", "world/map/central/ellipses"]

    dslam = MapEstimate(seq=0, stamp=2.0, landmarks=np.arange(6.0).reshape(3, 2), landmark_ids=np.array([6, 7, 8]),
                        covariance_ids=np.array([8, 99]), covariances=np.stack([np.eye(2)] * 2))
    records = {r.path: r for r in scene.map_estimate(dslam, 102.0, 2.0)}
    ellipses = records["world/map/dslam/ellipses"].archetype.strips.as_arrow_array().to_pylist()
    assert len(ellipses) == 1  # id 99 is not in the map
    np.testing.assert_allclose(np.mean(ellipses[0][:-1], axis=0), [4.0, 5.0], atol=1e-9)


def test_mcl_hypotheses_are_weighted_and_stats_become_two_series():
    scene = Scene()
    hypotheses = [PoseHypothesis(mean=np.array([1.0, 1.0, 0.0]), cov=np.eye(3), weight=0.8, particles=80),
                  PoseHypothesis(mean=np.array([-1.0, -1.0, np.pi]), cov=np.eye(3), weight=0.2, particles=20)]
    message = MclPose(robot_id="r4", seq=0, stamp=3.0, best_pose=np.array([1.0, 1.0, 0.0]), best_cov=np.eye(3),
                      hypotheses=hypotheses)
    records = {r.path: r for r in scene.mcl_pose(message, None, 0.0)}
    arrows = records["world/robots/r4/mcl/hypotheses"].archetype
    alpha = [c & 0xFF for c in arrows.colors.as_arrow_array().to_pylist()]
    assert alpha[0] > alpha[1]
    assert arrows.labels.as_arrow_array().to_pylist() == ["0.80", "0.20"]

    stats = ServiceStats(service="central", instance="central-1", stamp=1e9, uptime_s=1.0, latency_ms_median=2.0,
                         latency_ms_p99=9.0)
    first = scene.service_stats(stats, 1.7e9)
    assert [(r.path, r.static) for r in first] == [("stats/central/central-1/latency_ms", True),
                                                   ("stats/central/central-1/latency_ms", False)]
    assert first[1].archetype.scalars.as_arrow_array().to_pylist() == [2.0, 9.0]
    assert first[1].stamp == 3.0  # the data clock seen so far
    assert len(scene.service_stats(stats, 1.7e9 + 1)) == 1


def test_thin_by_time_keeps_one_pose_per_period_and_the_last():
    stamps = np.array([0.0, 0.05, 0.1, 0.21, 0.25, 0.39, 0.41, 0.45])
    assert thin_by_time(stamps, 0.2).tolist() == [0, 3, 6, 7]
    assert thin_by_time(np.zeros(0), 0.2).size == 0


def test_an_offline_run_reads_back_with_its_entities_and_row_counts(tmp_path):
    data = simulate("arena", robots=2, seed=1, duration=4.0)
    result = run_estimator(data, RunOptions(estimator="fastslam", association="known", particles=20, seed=1),
                           sample_period_s=0.2)
    truth = {rid: Trajectory(log.truth_stamp, log.truth_pose) for rid, log in data.robots.items()}
    path = tmp_path / "run.rrd"
    save_offline_run(str(path), data, result, truth, "fastslam", 0.2)
    assert result.extra["rerun"]["path"] == str(path)

    rows = rows_by_entity(path)
    assert rows["static:/world/truth/landmarks"] == 1 and rows["static:/world"] == 1
    assert column_lengths(path, "/world/truth/landmarks", "Points2D:positions") == [len(data.landmarks)]
    for rid in ("r1", "r2"):
        assert rows[f"/world/robots/{rid}/truth/pose"] == len(thin_by_time(data.robots[rid].truth_stamp, 0.2))
        assert rows[f"/world/robots/{rid}/fastslam/pose"] == len(thin_by_time(result.trajectories[rid].stamps, 0.2))
        assert rows[f"/world/robots/{rid}/truth/path/0"] >= 2
        assert rows[f"/world/robots/{rid}/fastslam/path/0"] >= 2
    assert rows["/world/map/fastslam/landmarks"] == 1 and rows["/world/map/fastslam/ellipses"] == 1
    assert column_lengths(path, "/world/map/fastslam/ellipses", "LineStrips2D:strips") == [len(result.map_means)]
    logged = sum(n for entity, n in rows.items() if "__properties" not in entity)
    assert logged == result.extra["rerun"]["records"]


def test_fleetslam_run_rerun_writes_a_recording_and_says_so(tmp_path, capsys):
    path, results = tmp_path / "out.rrd", tmp_path / "results.json"
    code = cli_main(["run", "--dataset", "sim:arena", "--duration", "2", "--estimator", "odometry", "--sim-robots", "1",
                     "--rerun", str(path), "--json", str(results), "--out", str(tmp_path / "report"), "--no-progress"])
    assert code == 0
    assert json.loads(results.read_text())["rerun"]["path"] == str(path)
    assert rows_by_entity(path)["/world/robots/r1/odometry/pose"] > 5
    assert cli_main(["run", "--dataset", "sim:arena", "--rerun", str(tmp_path / "x.mcap")]) == 2
    assert "--rerun" in capsys.readouterr().err


def test_without_rerun_the_viz_commands_say_which_extra_to_install(monkeypatch, tmp_path, capfd):
    """rerun-sdk is the optional viz extra: without it each Rerun entry point ends with one line naming it."""
    import services.viz
    from services.cli import main as cli_main

    monkeypatch.setattr(services.viz, "find_spec", lambda name: None)
    assert services.viz.rerun_missing().startswith("rerun-sdk is not installed: pip install 'fleetslam[viz]'")
    assert cli_main(["viz", "--save", str(tmp_path / "x.rrd")]) == 2
    assert cli_main(["run", "--dataset", "sim:arena", "--duration", "1", "--rerun", str(tmp_path / "x.rrd"),
                     "--out", str(tmp_path / "report"), "--no-progress"]) == 2
    assert cli_main(["demo", "--viz", "--out", str(tmp_path / "demo")]) == 2
    output = capfd.readouterr()
    errors = [line for line in (output.out + output.err).splitlines() if "ERROR" in line]
    assert len(errors) == 3 and all("fleetslam[viz]" in line for line in errors), errors
    assert "Traceback" not in output.out + output.err
    assert not (tmp_path / "report").exists() and not (tmp_path / "demo").exists()
