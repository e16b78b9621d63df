"""The map file (schemas.mapfile): round trip, atomic writes, and every refusal with a one-line reason."""

from __future__ import annotations

import json

import numpy as np
import pytest

from schemas.contract import MapView
from schemas.mapfile import FORMAT, VERSION, MapFileError, load_map, save_map


def sample_view(n: int = 4, with_ids: bool = True, seed: int = 0) -> MapView:
    rng = np.random.default_rng(seed)
    a = rng.normal(0.0, 0.1, (n, 2, 2))
    covs = a @ np.swapaxes(a, 1, 2) + 1e-3 * np.eye(2)
    return MapView(rng.uniform(-10, 10, (n, 2)), covs, np.arange(10, 10 + n) if with_ids else None)


def test_round_trip_keeps_every_number_ids_hits_and_source(tmp_path):
    view = sample_view()
    path = tmp_path / "map.json"
    written = save_map(path, view, {"estimator": "fastslam", "association": "known"}, hits=np.array([3, 4, 5, 6]))
    loaded = load_map(path)
    back = loaded.view()
    assert np.array_equal(back.means, view.means)  # JSON keeps every digit of a float
    assert np.allclose(back.covs, view.covs, rtol=0, atol=1e-15)
    assert back.ids.tolist() == [10, 11, 12, 13]
    assert loaded.hits().tolist() == [3, 4, 5, 6]
    assert loaded.source == {"estimator": "fastslam", "association": "known"}
    assert loaded.created == written.created and loaded.created.tzinfo is not None
    raw = json.loads(path.read_text())
    assert raw["format"] == FORMAT and raw["version"] == VERSION and raw["frame"] == "world"


def test_maps_without_ids_or_hits_and_empty_maps_load(tmp_path):
    save_map(tmp_path / "a.json", sample_view(with_ids=False))
    loaded = load_map(tmp_path / "a.json")
    assert loaded.view().ids is None and loaded.hits() is None and len(loaded.landmarks) == 4
    save_map(tmp_path / "b.json", MapView.empty())
    assert load_map(tmp_path / "b.json").view().means.shape == (0, 2)


def test_save_is_atomic_and_leaves_no_temporary_file(tmp_path, monkeypatch):
    path = tmp_path / "map.json"
    save_map(path, sample_view(2))
    before = path.read_text()

    def broken_fsync(_fd):
        raise OSError(5, "Input/output error")

    monkeypatch.setattr("schemas.mapfile.os.fsync", broken_fsync)
    with pytest.raises(MapFileError, match="cannot write the map"):
        save_map(path, sample_view(5, seed=1))
    assert path.read_text() == before  # the old map is whole
    assert [p.name for p in tmp_path.iterdir()] == ["map.json"]


def test_save_refuses_nan_and_bad_covariances(tmp_path):
    view = sample_view(2)
    view.means[1, 0] = np.nan
    with pytest.raises(MapFileError, match="landmarks.1.mean"):
        save_map(tmp_path / "m.json", view)
    view = sample_view(2)
    view.covs[0] = np.diag([1.0, -1.0])
    with pytest.raises(MapFileError, match="positive definite"):
        save_map(tmp_path / "m.json", view)
    assert not (tmp_path / "m.json").exists()


def write(tmp_path, text: str):
    path = tmp_path / "map.json"
    path.write_text(text)
    return path


def good_document() -> dict:
    return {"format": FORMAT, "version": VERSION, "frame": "world", "created": "2025-01-01T00:00:00+00:00",
            "source": {}, "landmarks": [{"id": 1, "mean": [1.0, 2.0], "cov": [[0.1, 0.0], [0.0, 0.1]], "hits": 3},
                                        {"id": 2, "mean": [3.0, 4.0], "cov": [[0.2, 0.01], [0.01, 0.1]], "hits": 5}]}


def changed(**edits) -> str:
    document = good_document()
    document.update(edits)
    return json.dumps(document)


def with_landmark(**fields) -> str:
    document = good_document()
    document["landmarks"][1].update(fields)
    return json.dumps(document)


@pytest.mark.parametrize("text, reason", [
    ("{\"format\": \"fleetslam-map\", \"version\": 1, \"landm", "not a JSON document, truncated or corrupt"),
    ("\x00\x01garbage", "not a JSON document"),
    ("", "not a JSON document"),
    ("[1, 2]", "not a fleetslam-map file"),
    (changed(format="other-map"), "not a fleetslam-map file (format 'other-map')"),
    (changed(version=2), "version 2 is not supported"),
    (changed(version="1"), "version '1' is not supported"),
    (with_landmark(mean=[1.0, 2.0, 3.0]), "landmarks.1.mean"),
    (with_landmark(mean=[1.0]), "landmarks.1.mean"),
    (with_landmark(cov=[[0.1, 0.0]]), "landmarks.1.cov"),
    (with_landmark(cov=[[0.1, 0.0, 0.0], [0.0, 0.1, 0.0]]), "landmarks.1.cov"),
    (with_landmark(cov=[[0.1, 0.05], [0.0, 0.1]]), "cov is not symmetric"),
    (with_landmark(cov=[[0.1, 0.0], [0.0, -0.1]]), "cov is not positive definite"),
    (with_landmark(mean=[1.0, "x"]), "landmarks.1.mean"),
    (with_landmark(hits=-1), "landmarks.1.hits"),
    (with_landmark(id=1), "landmark ids repeat"),
    (with_landmark(id=None), "either every landmark has an id or none has"),
    (with_landmark(colour="red"), "landmarks.1.colour"),
    (changed(created="yesterday"), "created"),
    (changed(landmarks=None), "landmarks"),
])
def test_refusals_are_one_line_with_the_reason(tmp_path, text, reason):
    path = write(tmp_path, text)
    with pytest.raises(MapFileError) as error:
        load_map(path)
    message = str(error.value)
    assert reason in message and str(path) in message
    assert "\n" not in message


@pytest.mark.parametrize("token", ["NaN", "Infinity", "-Infinity"])
def test_nan_and_infinity_are_refused(tmp_path, token):
    text = changed().replace("[3.0, 4.0]", f"[3.0, {token}]")
    assert token in text
    with pytest.raises(MapFileError, match=f"holds {token}"):
        load_map(write(tmp_path, text))


def test_truncated_file_is_refused_whatever_the_cut(tmp_path):
    save_map(tmp_path / "full.json", sample_view(3))
    text = (tmp_path / "full.json").read_text()
    for cut in range(1, len(text.rstrip()) - 1, 37):
        with pytest.raises(MapFileError, match="not a JSON document"):
            load_map(write(tmp_path, text[:cut]))


def test_missing_file_is_a_one_line_error(tmp_path):
    with pytest.raises(MapFileError, match="cannot read"):
        load_map(tmp_path / "nothing.json")
