"""Three sites in network namespaces, each with its own router, meshed to the depot's over links with 40 ± 10 ms
delay and 1 % loss (tests/integration/sites.py: ``tc netem`` where the kernel has it, else a relay that delays and
stalls the stream as a loss under TCP does): site1's cable is cut for 12 s (longer than the lease), central is
killed (SIGKILL) half-way through the cut and started again at once from its checkpoints, site2's router is killed
and restarted. Nothing is lost: the depot's receiver holds every message each robot sent, each seq once and in
order, and central took every one in with none missing; the cut site's robot is heard again within seconds of its
cable's return, without a restart; and central ends where an untouched copy of the fleet (same robots, same data,
same central, no fault) ends, bit for bit."""

from __future__ import annotations

import json

import pytest

from tests.integration.sites import run_sites

pytestmark = pytest.mark.integration


def test_sites_meshed_over_lossy_links_lose_nothing_across_a_cut_a_central_kill_and_a_router_restart(netns_lab,
                                                                                                     tmp_path):
    run = run_sites(netns_lab, tmp_path, cut_s=12.0)
    print("MULTI-SITE FIGURES " + json.dumps(run.figures))
    assert run.figures["link_shaping"] in ("netem", "relay"), run.figures["links"]
    assert run.sent and all(counts.get("odom", 0) > 100 for counts in run.sent.values()), run.sent
    for rid, counts in run.sent.items():
        for stream, n in counts.items():
            assert run.received[rid][stream] == list(range(n)), f"{rid}/{stream}: not every seq once and in order"
    assert run.figures["lost"] == 0
    assert run.figures["central_missing"] == 0, f"central lost messages for good: {run.figures}"
    assert run.central is not None, "central did not take in every message"
    assert run.central["extra"].get("missing") == 0, run.central["extra"]
    assert not {"duplicate", "out_of_order", "time_backwards"} & set(run.central["rejected"]), run.central["rejected"]
    assert run.figures["site1_heard_again_s"] < 10.0, run.figures
    assert run.figures["central_resumed_from_checkpoint"], "central restarted afresh, not from its checkpoint"
    assert run.figures["untouched_sent_the_same"], (run.sent, run.figures["untouched_sent"])
    assert run.untouched_central is not None, "the untouched central did not take in every message"
    assert run.figures["central_equal_untouched"], run.figures["central_vs_untouched"]
