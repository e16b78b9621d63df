"""Maps that outlive a run: estimators started from a saved map, ``fleetslam run --map/--map-out``, and a second
session whose robots, without start poses, are placed in the first session's map and extend it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from central.fastslam.config import FastSlamConfig
from central.fastslam.core import FastSlam
from robots.loaders import load_dataset
from schemas.config import RunSettings
from schemas.contract import MapView, RunOptions
from schemas.mapfile import MapFileError, load_map, save_map
from services.cli import main as cli_main
from services.dslam.config import DslamConfig
from services.dslam.core import DSlam
from services.evaluation.metrics import interpolate_poses, map_error
from services.maps import options_with_map, seed_estimator
from services.offline import run, run_estimator
from tests.unit.test_mapfile import sample_view


def test_fastslam_starts_from_a_map_stored_once_and_numbers_new_landmarks_after_it():
    view = sample_view(40)
    slam = FastSlam(FastSlamConfig(particles=20, association="shared", seed=0))
    assert seed_estimator(slam, view, None, "shared") == 40
    assert slam.map.blocks_in_use() == 2  # 40 slots in blocks of 32, shared by all 20 particles
    shown = slam.landmark_map()  # shared association shows confirmed landmarks only: these are
    rows = lambda means: means[np.lexsort(means.T[::-1])]  # noqa: E731 - rows in one order, to compare as sets
    assert shown.ids is None and np.allclose(rows(shown.means), rows(view.means))
    assert slam.next_landmark_id == 50
    known = FastSlam(FastSlamConfig(particles=5, association="known", seed=0))
    seed_estimator(known, view, np.arange(40), "known")
    out = known.landmark_map()
    by_id = dict(zip(out.ids.tolist(), range(40)))
    rows = [by_id[i] for i in view.ids.tolist()]
    assert np.allclose(out.means[rows], view.means) and np.allclose(out.covs[rows], view.covs)
    assert (known.map.hits[list(known.known_slots.values())] >= known.config.confirm_hits).all()
    with pytest.raises(ValueError, match="already in the map"):
        known.load_landmarks(view.ids[:1], view.means[:1], view.covs[:1])


def test_known_association_refuses_a_map_without_ids():
    slam = FastSlam(FastSlamConfig(particles=5, association="known"))
    with pytest.raises(MapFileError, match="no landmark ids"):
        seed_estimator(slam, sample_view(3, with_ids=False), None, "known")
    assert slam.landmark_map().means.shape == (0, 2)


def test_dslam_takes_the_saved_landmarks_as_prior_information():
    view = sample_view(70)  # more than one chunk of the phase-I update
    dslam = DSlam(DslamConfig(association="known"))
    seed_estimator(dslam, view, None, "known")
    out = dslam.landmark_map()
    assert out.ids.tolist() == view.ids.tolist()
    assert np.allclose(out.means, view.means, atol=1e-6)
    assert np.allclose(out.covs, view.covs, rtol=1e-4, atol=1e-9)  # information = inverse covariance, no links


def run_settings(tmp_path, **fields) -> RunSettings:
    base = dict(dataset="sim:arena", estimator="fastslam", association="known", particles=10, duration=5.0,
                sim_robots=1, out=None, progress=False, seed=0)
    return RunSettings(**{**base, **fields})


def test_run_map_out_is_written_atomically_and_a_failed_write_keeps_the_old_map(tmp_path, monkeypatch):
    path = tmp_path / "maps" / "session.json"
    output = run(run_settings(tmp_path, map_out=str(path)))
    saved = load_map(path)
    assert output["map_out"] == {"path": str(path), "landmarks": len(saved.landmarks)}
    assert len(saved.landmarks) == output["landmarks"]["estimated"] > 0
    assert saved.source["estimator"] == "fastslam" and saved.source["robots"] == ["r1"]
    assert [p.name for p in path.parent.iterdir()] == ["session.json"]
    before = path.read_bytes()

    def broken_fsync(_fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr("schemas.mapfile.os.fsync", broken_fsync)
    output = run(run_settings(tmp_path, map_out=str(path), duration=3.0))
    assert "No space left on device" in output["map_out_error"]
    assert output["ate_rmse_m"]["r1"] is not None  # the run's figures are kept
    assert path.read_bytes() == before and [p.name for p in path.parent.iterdir()] == ["session.json"]


def test_run_refuses_a_bad_map_in_one_line(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text('{"format": "fleetslam-map", "version": 7, "landmarks": []}')
    code = cli_main(["run", "--dataset", "sim:arena", "--estimator", "fastslam", "--duration", "2", "--map", str(bad),
                     "--no-progress", "--out", str(tmp_path / "r")])
    err = capsys.readouterr().err
    assert code == 2 and "version 7 is not supported" in err and "Traceback" not in err
    idless = tmp_path / "idless.json"
    save_map(idless, sample_view(3, with_ids=False))
    code = cli_main(["run", "--dataset", "sim:arena", "--estimator", "fastslam", "--association", "known",
                     "--duration", "2", "--map", str(idless), "--no-progress", "--out", str(tmp_path / "r")])
    err = capsys.readouterr().err
    assert code == 2 and "no landmark ids" in err and "Traceback" not in err


def test_second_session_without_start_poses_is_placed_in_the_first_map_and_extends_it(tmp_path):
    """Session 1: r1 with its start pose maps part of the arena and saves. Session 2: r2 and r3, no start poses,
    start from the file: MCL places them in session 1's frame (no new anchor), the map grows, old landmarks stay."""
    data = load_dataset("sim:arena", robots=3, seed=3, duration=40.0, rate=10.0)
    options = RunOptions("fastslam", "known", particles=30, seed=1)
    first = run_estimator(data, options, robots=["r1"], start_poses="known")
    path = tmp_path / "session1.json"
    save_map(path, MapView(first.map_means, first.map_covs, first.map_ids), {"session": 1})
    saved = load_map(path)
    assert len(saved.landmarks) < len(data.landmarks)  # something is left to map

    second = run_estimator(data, options_with_map(options, saved), robots=["r2", "r3"], start_poses="none")
    placements = second.extra["placement"]
    assert {rid: placements[rid]["how"] for rid in ("r2", "r3")} == {"r2": "mcl", "r3": "mcl"}
    assert len(second.map_ids) > len(saved.landmarks)
    before = dict(zip(saved.view().ids.tolist(), saved.view().means))
    after = dict(zip(second.map_ids.tolist(), second.map_means))
    moved = [float(np.linalg.norm(after[i] - mean)) for i, mean in before.items()]
    assert max(moved) < 0.15, moved
    for rid in ("r2", "r3"):  # in the truth's frame, since session 1's frame is r1's true start pose
        path_ = second.trajectories[rid]
        truth = interpolate_poses(data.robots[rid].truth_stamp, data.robots[rid].truth_pose, path_.stamps, 1.0)
        late = path_.stamps > path_.stamps[-1] - 10.0
        error = np.linalg.norm(path_.poses[late, :2] - truth[late, :2], axis=1)
        assert np.mean(error) < 0.3, (rid, float(np.mean(error)))
    assert map_error(second.map_means, data.landmarks, 1.0)["rmse_m"] < 0.15


def test_mcl_estimator_localizes_against_a_saved_map(tmp_path):
    """``fleetslam run --estimator mcl --map FILE``: the saved map replaces the data set's true one."""
    data = load_dataset("sim:arena", robots=1, seed=3, duration=20.0, rate=10.0)
    shifted = MapView(data.landmarks + np.array([100.0, 0.0]), np.tile(np.eye(2) * 1e-4, (len(data.landmarks), 1, 1)),
                      np.asarray(data.landmark_ids))
    save_map(tmp_path / "far.json", shifted)
    output = run(run_settings(tmp_path, dataset="sim:arena", estimator="mcl", duration=20.0, seed=3,
                              map=str(tmp_path / "far.json"), json_out=str(tmp_path / "o.json")))
    pose = json.loads((tmp_path / "o.json").read_text())
    assert output["estimator"] == "mcl" and pose["settings"]["map"] == str(tmp_path / "far.json")
    assert output["fleet_aligned"]["transform"][0] == pytest.approx(-100.0, abs=1.0)  # localized in the file's frame
