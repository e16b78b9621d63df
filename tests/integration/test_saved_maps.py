"""Services started from a saved map, over a real router: the central FastSLAM service publishes the loaded map
before any robot has scanned, saves it on SIGTERM, and refuses a bad map file in one line."""

from __future__ import annotations

import signal

import numpy as np
import pytest

from schemas.keys import Keys
from schemas.mapfile import load_map, save_map
from schemas.messages import Estimate
from tests.helpers import Collector, wait_until
from tests.unit.test_mapfile import sample_view

pytestmark = pytest.mark.integration


def test_central_publishes_the_loaded_map_before_any_robot_and_saves_it_on_sigterm(router, processes, zsession,
                                                                                   prefix, tmp_path):
    view = sample_view(6, seed=2)
    save_map(tmp_path / "in.json", view, {"estimator": "fastslam"})
    out = tmp_path / "out" / "map.json"
    estimates = Collector(zsession, Keys(prefix).central_estimate)
    central = processes.start("central", "central", "--association", "known", "--particles", "20",
                              "--estimate-rate-hz", "5", "--map", str(tmp_path / "in.json"), "--map-out", str(out),
                              "--map-out-period-s", "0")
    wait_until(lambda: estimates.count() > 0, 60, what="the central service's first estimate")
    first = estimates.decoded(Estimate)[0]
    assert first.robots == []  # no robot yet: the map alone
    order = np.argsort(first.landmark_ids)
    assert first.landmark_ids[order].tolist() == view.ids.tolist()
    assert np.allclose(first.landmarks[order], view.means) and np.allclose(first.landmark_covs[order], view.covs)
    assert not out.exists()  # map_out_period_s 0: written on exit only
    processes.stop(central, signal.SIGTERM, timeout=20)
    assert central.returncode == 0, processes.log("central")
    saved = load_map(out).view()
    order = np.argsort(saved.ids)
    assert saved.ids[order].tolist() == view.ids.tolist() and np.allclose(saved.means[order], view.means)


def test_services_refuse_a_bad_map_in_one_line(router, processes, tmp_path):
    (tmp_path / "bad.json").write_text('{"format": "fleetslam-map", "version": 1, "landmarks": [')
    for name in ("central", "dslam"):
        process = processes.start(name, name, "--map", str(tmp_path / "bad.json"))
        assert process.wait(timeout=60) == 2
        text = processes.log(name)
        assert "not a JSON document, truncated or corrupt" in text and "Traceback" not in text, text
