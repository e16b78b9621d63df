"""``fleetslam viz`` over a real router: a short simulated fleet and the central service, recorded to an .rrd file
that Rerun's own reader opens."""

from __future__ import annotations

import pytest
from rerun.chunk import RrdReader

from schemas.codec import decode
from schemas.keys import Keys
from schemas.messages import ServiceStats
from tests.helpers import Collector, wait_until

pytestmark = pytest.mark.integration

ROBOTS = ("r1", "r2")


def test_viz_records_every_robots_truth_and_the_central_estimate(router, processes, zsession, prefix, tmp_path):
    keys = Keys(prefix)
    stats = Collector(zsession, keys.all_stats)

    def service_ready(name: str) -> bool:
        return any(key.split("/")[-2] == name for key, _ in stats.snapshot())

    processes.start("central", "central", "--association", "known", "--particles", "20", "--estimate-rate-hz", "5")
    wait_until(lambda: service_ready("central"), 60, what="the central service's first stats")
    recording = tmp_path / "fleet.rrd"
    viz = processes.start("viz", "viz", "--save", str(recording), "--duration", "10")
    wait_until(lambda: service_ready("viz"), 15, what="the viz's first stats")
    robots = [processes.start(rid, "robot", "--id", rid, "--world", "arena", "--seed", "2", "--rate", "10",
                              "--duration", "4", "--speedup", "8", "--start-delay", "0.5") for rid in ROBOTS]
    for process in robots:
        assert process.wait(timeout=30) == 0
    assert viz.wait(timeout=30) == 0, processes.log("viz")
    assert "records logged" in processes.log("viz")

    rows: dict[str, int] = {}
    static: set[str] = set()
    for chunk in RrdReader(str(recording)).stream():
        rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
        if chunk.is_static:
            static.add(chunk.entity_path)
    for rid in ROBOTS:
        assert rows.get(f"/world/robots/{rid}/truth/pose", 0) >= 20, rows  # 40 truth messages per robot
        assert rows.get(f"/world/robots/{rid}/truth/path/0", 0) >= 1, rows
    assert any(rows.get(f"/world/robots/{rid}/central/pose", 0) >= 1 for rid in ROBOTS), rows
    assert rows.get("/world/map/central/landmarks", 0) >= 1, rows
    assert "/world/truth/landmarks" in static
    assert any(path.startswith("/stats/central/") for path in rows), rows
    viz_stats = [decode(p, ServiceStats) for k, p in stats.snapshot() if k == keys.stats("viz")]
    assert not viz_stats[-1].rejected, viz_stats[-1].rejected
