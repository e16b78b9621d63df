"""Three sites in network namespaces, each with its own router, meshed to the depot's over links with 40 ± 10 ms
delay and 1 % loss (tests/integration/sites.py): site1's cable is cut for 12 s (longer than the lease), site2's
router is killed and restarted. Nothing is lost: the depot's receiver holds every message each robot sent, each
seq once and in order, and central took every one in with none missing; the cut site's robot is heard again
within seconds of its cable's return, without a restart."""

from __future__ import annotations

import json

import pytest

from tests.integration.sites import run_sites

pytestmark = pytest.mark.integration


def test_sites_meshed_over_lossy_links_lose_nothing_across_a_cut_and_a_router_restart(netns_lab, tmp_path):
    run = run_sites(netns_lab, tmp_path, cut_s=12.0)
    print("MULTI-SITE FIGURES " + json.dumps(run.figures))
    assert run.sent and all(counts.get("odom", 0) > 100 for counts in run.sent.values()), run.sent
    for rid, counts in run.sent.items():
        for stream, n in counts.items():
            assert run.received[rid][stream] == list(range(n)), f"{rid}/{stream}: not every seq once and in order"
    assert run.figures["lost"] == 0
    assert run.central is not None, "central did not take in every message"
    assert run.central["extra"].get("missing") == 0, run.central["extra"]
    assert not {"duplicate", "out_of_order", "time_backwards"} & set(run.central["rejected"]), run.central["rejected"]
    assert run.figures["site1_heard_again_s"] < 10.0, run.figures
