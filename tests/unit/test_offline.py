"""``fleetslam run`` and the dead-reckoning baseline: exact dead reckoning, JSON fields, pluggable extra metrics."""

import json
import math
import os
import signal
import subprocess
import sys

import numpy as np
import pytest

from robots.loaders import data_root
from robots.models import motion_model
from robots.simulator import simulate
from schemas.config import RunSettings
from services import estimators as registry
from services.cli import main as cli_main
from schemas.contract import MapView, RunOptions
from services.estimators import make_estimator, resolve_association
from services.baselines.dead_reckoning import DeadReckoning
from services.offline import run, run_estimator
from tests.helpers import wait_until

ROOT = data_root()
needs_data = pytest.mark.skipif(ROOT is None, reason="real data sets not found (set FLEETSLAM_DATA or add ../shared/data)")


def _step_by_step(log):
    """Reference: the EKF prediction applied one control at a time."""
    model = motion_model(log.info.motion_model, log.info.wheelbase, log.info.encoder_offset)
    pose, cov = np.array(log.info.start_pose, float), np.array(log.info.start_pose_cov, float)
    for k in range(log.odom_stamp.size):
        f_pose, f_control = model.jacobians(pose, log.odom_control[k], log.odom_dt[k])
        pose = model.step(pose, log.odom_control[k], log.odom_dt[k])
        cov = f_pose @ cov @ f_pose.T + f_control @ log.odom_cov @ f_control.T
    return pose, cov


@pytest.mark.parametrize("kind", ["unicycle", "ackermann"])
def test_dead_reckoning_in_batches_equals_the_step_by_step_prediction(kind):
    data = simulate("arena", robots=1, seed=3, duration=8.0)
    log = data.robots["r1"]
    if kind == "ackermann":
        log.info = log.info.model_copy(update={"motion_model": "ackermann", "wheelbase": 2.83, "encoder_offset": 0.76})
        log.odom_control = np.column_stack([log.odom_control[:, 0], 0.3 * np.sin(log.odom_stamp)])
    estimator = DeadReckoning()
    estimator.add_robot(log.info)
    for k, event in enumerate(e for e in data.events() if e.__class__.__name__ == "OdomEvent"):
        estimator.on_odometry(event)
        if k % 7 == 3:
            estimator.poses()  # flush at irregular points
    pose, cov = estimator.poses()["r1"]
    want_pose, want_cov = _step_by_step(log)
    np.testing.assert_allclose(pose, want_pose, atol=1e-9)
    np.testing.assert_allclose(cov, want_cov, atol=1e-12, rtol=1e-7)


def test_dead_reckoning_maps_landmarks_by_true_id_from_its_poses():
    data = simulate("arena", robots=1, seed=0, duration=5.0)
    estimator = make_estimator(RunOptions(estimator="odometry"), [data.robots["r1"].info])
    for event in data.events():
        (estimator.on_scan if hasattr(event, "ranges") else estimator.on_odometry)(event)
    view = estimator.landmark_map()
    assert view.means.shape[0] == view.ids.size > 0
    truth = dict(zip(data.landmark_ids.tolist(), data.landmarks))
    errors = np.linalg.norm(view.means - np.array([truth[i] for i in view.ids.tolist()]), axis=1)
    assert np.median(errors) < 0.5
    blind = make_estimator(RunOptions(estimator="odometry", association="nn"), [data.robots["r1"].info])
    for event in data.events():
        (blind.on_scan if hasattr(event, "ranges") else blind.on_odometry)(event)
    assert blind.landmark_map().means.shape == (0, 2)


def test_run_estimator_samples_each_robot_at_its_odometry_stamps():
    data = simulate("arena", robots=2, seed=1, duration=6.0)
    result = run_estimator(data, RunOptions(), sample_period_s=0.5)
    for rid, trajectory in result.trajectories.items():
        assert np.all(np.diff(trajectory.stamps) > 0)
        assert 12 <= len(trajectory) <= 14
        assert set(trajectory.stamps[1:].round(6)) <= set(data.robots[rid].odom_stamp.round(6))
    assert result.events == {"odometry": 120, "scan": 122}
    assert result.data_s == pytest.approx(6.0)


class _Constant:
    """A fake estimator that never moves and reports its own figures."""

    def __init__(self, infos):
        self.infos = {i.robot_id: i for i in infos}
        self.scans = 0

    def add_robot(self, info):
        self.infos[info.robot_id] = info

    def on_odometry(self, event):
        pass

    def on_scan(self, event):
        self.scans += 1

    def poses(self):
        return {rid: (np.array(i.start_pose), np.eye(3)) for rid, i in self.infos.items()}

    def landmark_map(self):
        return MapView(np.zeros((0, 2)), np.zeros((0, 2, 2)))

    def extra_metrics(self):
        return {"association_accuracy": 0.5, "scans_seen": self.scans}


def make_constant(options, infos):
    return _Constant(infos)


def test_run_writes_the_json_fields_and_merges_extra_metrics(tmp_path, monkeypatch):
    monkeypatch.setitem(registry.ESTIMATORS, "odometry", make_constant)
    settings = RunSettings(dataset="sim:arena", estimator="odometry", duration=5.0, sim_robots=2,
                           json_out=str(tmp_path / "out.json"), out=None, progress=False)
    output = run(settings)
    written = json.loads((tmp_path / "out.json").read_text())
    assert written == output
    for key in ("wall_s", "data_s", "ate_rmse_m", "map_rmse_m", "landmarks", "gps_rmse_m", "settings"):
        assert key in written
    assert written["association_accuracy"] == 0.5 and written["scans_seen"] == written["events"]["scan"]
    assert set(written["ate_rmse_m"]) == {"r1", "r2"} and min(written["ate_rmse_m"].values()) > 0.1
    assert written["landmarks"] == {"estimated": 0, "matched": 0, "missed": 15, "spurious": 0}
    assert written["settings"]["estimator"] == "odometry"


def test_fleetslam_run_command_writes_json_and_a_report_folder(tmp_path):
    out, report = tmp_path / "run.json", tmp_path / "report"
    code = cli_main(["run", "--dataset", "sim:arena", "--duration", "4", "--robots", "r1,r3", "--json", str(out),
                     "--out", str(report), "--no-progress"])
    assert code == 0
    result = json.loads(out.read_text())
    assert result["robots"] == ["r1", "r3"] and result["estimator"] == "odometry"
    assert 0.0 < result["ate_rmse_m"]["r1"] < 1.0
    assert result["landmarks"]["matched"] > 0 and result["map_rmse_m"] < 1.0
    metrics = json.loads((report / "metrics.json").read_text())
    assert metrics["summary"]["odometry"]["ate_rmse_m"] == result["ate_rmse_m"]
    for name in ("truth_r1.tum", "odometry_r3.tum", "map_odometry.png", "errors.png"):
        assert (report / name).stat().st_size > 0
    line = (report / "odometry_r1.tum").read_text().splitlines()[1].split()
    assert len(line) == 8 and float(line[6]) ** 2 + float(line[7]) ** 2 == pytest.approx(1.0, abs=1e-5)


def test_unknown_estimator_and_robot_are_clear_errors():
    with pytest.raises(ValueError, match="unknown estimator 'nope'; choose from odometry, ekf, fastslam, dslam, mcl"):
        run_estimator(simulate("arena", robots=2, duration=1.0), RunOptions(estimator="nope"))
    with pytest.raises(ValueError, match="not in"):
        run_estimator(simulate("arena", robots=2, duration=1.0), RunOptions(), robots=["r9"])


@needs_data
def test_car_park_dead_reckoning_scores_against_gps_at_the_antenna(tmp_path):
    output = run(RunSettings(dataset="car-park:acfr_car_park", duration=30.0, out=str(tmp_path / "report"), progress=False))
    assert output["gps_rmse_m"] is not None and output["gps_rmse_m"] < 1.0
    assert output["landmarks"]["missed"] == 15 and output["heading_rmse_rad"] == {}
    assert math.isfinite(output["ate_rmse_m"]["r1"])


def test_set_parses_estimator_settings_and_reaches_the_estimator(tmp_path):
    from services.offline import parse_estimator_settings

    assert parse_estimator_settings("max_obs_range=40, proposal=fastslam2,resample=true") == {
        "max_obs_range": 40, "proposal": "fastslam2", "resample": True}
    assert parse_estimator_settings(None) == {}
    with pytest.raises(ValueError, match="NAME=VALUE"):
        parse_estimator_settings("max_obs_range")
    out = tmp_path / "out.json"
    assert cli_main(["run", "--dataset", "sim:arena", "--estimator", "fastslam", "--robots", "r1", "--duration", "5",
                     "--particles", "10", "--set", "max_obs_range=2.0", "--json", str(out), "--out", str(tmp_path / "a"),
                     "--no-progress"]) == 0
    near = json.loads(out.read_text())
    assert near["settings"]["estimator_settings"] == "max_obs_range=2.0"
    assert cli_main(["run", "--dataset", "sim:arena", "--estimator", "fastslam", "--robots", "r1", "--duration", "5",
                     "--particles", "10", "--json", str(out), "--out", str(tmp_path / "b"), "--no-progress"]) == 0
    assert near["landmarks"]["estimated"] < json.loads(out.read_text())["landmarks"]["estimated"]


@pytest.mark.parametrize("estimator", ["odometry", "ekf", "fastslam", "dslam", "mcl"])
def test_unknown_estimator_settings_are_refused_with_the_known_names(estimator, capsys):
    assert cli_main(["run", "--dataset", "sim:arena", "--estimator", estimator, "--robots", "r1", "--duration", "1",
                     "--set", "no_such_setting=1", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0], err
    assert err[0].startswith("fleetslam run: error: unknown ") and "no_such_setting" in err[0] and "(known: " in err[0]


@pytest.mark.parametrize("estimator, expected", [("fastslam", "shared"), ("dslam", "auto"), ("ekf", "jcbb")])
def test_unknown_association_names_each_estimators_recommended_method(estimator, expected):
    """``--association unknown`` reaches every estimator as its own recommended method without ids."""
    data = simulate("arena", robots=1, seed=0, duration=2.0)
    built = make_estimator(RunOptions(estimator=estimator, association="unknown"), [data.robots["r1"].info])
    method = built.method if hasattr(built, "method") else built.config.association
    assert method == expected
    assert resolve_association(estimator, "nn") == "nn"


def test_run_names_its_report_folder_and_clears_an_earlier_report(tmp_path, capsys):
    report = tmp_path / "report"
    report.mkdir()
    (report / "fastslam_r9.tum").write_text("stale")
    (report / "notes.txt").write_text("the user's")
    assert cli_main(["run", "--dataset", "sim:arena", "--robots", "r1", "--duration", "2", "--out", str(report),
                     "--no-progress"]) == 0
    assert f"in{report}/" in "".join(capsys.readouterr().out.split())  # the console wraps long lines
    assert not (report / "fastslam_r9.tum").exists() and (report / "notes.txt").read_text() == "the user's"
    results = json.loads((report / "results.json").read_text())
    assert results["robots"] == ["r1"] and "interrupted" not in results
    assert RunSettings.model_fields["out"].default == "reports/run"  # a run always leaves its results somewhere


def test_an_interrupted_run_scores_and_returns_what_was_computed():
    data = simulate("arena", robots=2, seed=0, duration=20.0)
    asked = []

    def stop_after_a_while() -> bool:
        asked.append(True)
        return len(asked) > 150

    cut = run_estimator(data, RunOptions(estimator="odometry"), should_stop=stop_after_a_while)
    whole = run_estimator(data, RunOptions(estimator="odometry"))
    assert cut.extra["interrupted"] is True and "interrupted" not in whole.extra
    assert 0.0 < cut.data_s < 0.5 * whole.data_s
    assert sum(cut.events.values()) == 150 and set(cut.trajectories) == {"r1", "r2"}


def test_sigterm_during_fleetslam_run_saves_the_results_and_says_interrupted(tmp_path):
    report, log = tmp_path / "report", tmp_path / "run.log"
    with open(log, "w") as sink:
        child = subprocess.Popen([sys.executable, "-m", "services.cli", "run", "--dataset", "sim:arena", "--duration",
                                  "300", "--robots", "r1", "--estimator", "fastslam", "--particles", "3000", "--out",
                                  str(report), "--no-progress"], stdout=sink, stderr=subprocess.STDOUT,
                                 env={k: v for k, v in os.environ.items() if not k.startswith("FLEETSLAM_")})
    try:
        wait_until(lambda: "running fastslam on" in log.read_text() or child.poll() is not None, timeout=120,
                   what="the run to start")
        assert child.poll() is None, log.read_text()
        child.send_signal(signal.SIGTERM)
        child.wait(timeout=120)
    finally:
        if child.poll() is None:
            child.kill()
    output = log.read_text()
    assert child.returncode == 130, output
    assert "SIGTERM: stopping after the current event" in output and "interrupted after" in output
    results = json.loads((report / "results.json").read_text())
    assert results["interrupted"] is True and results["data_s"] < 300.0  # (the data cut: the test above)
