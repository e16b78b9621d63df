"""Bounded queries over a real router: ``fleetslam assoc`` and ``fleetslam mcl``'s localize answer every query once
(a result, or a refusal by reason), refuse at once what is too large or arrives when the queue is full, cut a solve at
its deadline, and MCL keeps tracking its robots while a heavy query is solved."""

from __future__ import annotations

import time

import numpy as np
import pytest
import zenoh

from robots.worlds import make_world
from schemas.association import AssociationReply
from schemas.codec import decode, encode
from schemas.keys import Keys
from schemas.mcl import LocalizeReply, LocalizeRequest
from schemas.messages import ServiceStats
from services.association.client import query_associate
from tests.helpers import Asked, Collector, wait_until
from tests.unit.test_query_limits import dense_request

pytestmark = pytest.mark.integration


def latest_stats(collector: Collector, check) -> ServiceStats:
    return wait_until(lambda: next((s for s in reversed(collector.decoded(ServiceStats)) if check(s)), None), 15,
                      what="stats showing the queries")


def test_a_flood_of_association_queries_is_answered_with_results_or_busy_and_counted(processes, zsession, prefix):
    keys = Keys(prefix)
    stats = Collector(zsession, keys.stats("assoc"))
    processes.start("assoc", "assoc", "--query-workers", "1", "--query-queue", "2", "--light-query-cells", "0",
                    "--stats-period-s", "0.3")  # one lane: every query competes for the one worker
    wait_until(lambda: stats.count() > 0, 60, what="the assoc service's stats")
    heavy = encode(dense_request(200, 200))  # an LP of 40,000 pairs, a fifth of a second: the queue stays full
    flood = [Asked(zsession, keys.assoc("ihgr"), heavy) for _ in range(40)]
    outcomes = [asked.one() for asked in flood]
    solved = [decode(payload, AssociationReply) for ok, payload, _ in outcomes if ok]
    busy = [late for ok, payload, late in outcomes if not ok and payload.startswith(b"busy: ")]
    assert len(solved) + len(busy) == 40, [payload[:40] for ok, payload, _ in outcomes if not ok]
    assert 1 <= len(solved) <= 10 and busy and max(busy) < 1.0
    assert all(reply.method == "ihgr" and not reply.truncated for reply in solved)
    assert max(late for *_, late in outcomes) < 5.0
    last = latest_stats(stats, lambda s: s.messages_in.get("ihgr", 0) == 40 and s.extra.get("query_replies") == len(solved)
                        and sum(s.rejected.values()) == len(busy))
    assert last.rejected == {"busy": len(busy)}
    assert last.extra["query_pending"] == 0 and last.extra["query_solve_ms_p99"] < 1000
    stats.undeclare()


def test_association_refuses_oversize_at_once_cuts_at_the_deadline_and_answers_a_wildcard_once(processes, zsession,
                                                                                              prefix):
    keys = Keys(prefix)
    stats = Collector(zsession, keys.stats("assoc"))
    processes.start("assoc", "assoc", "--query-workers", "1", "--query-deadline-s", "1.5", "--stats-period-s", "0.3",
                    "--max-jcbb-nodes", str(10**8))
    wait_until(lambda: stats.count() > 0, 60, what="the assoc service's stats")
    # holds the only worker 1.5 s: a node budget no search spends in that time, so the deadline is what cuts it
    slow = Asked(zsession, keys.assoc("jcbb"),
                 encode(dense_request(150, 150).model_copy(update={"jcbb_max_nodes": 10**8})))
    oversize = Asked(zsession, keys.assoc("exact"), encode(dense_request(800, 400)))  # (800 + 400)² cells
    small = encode(dense_request(5, 5))
    light = Asked(zsession, keys.assoc("auto"), small)  # as D-SLAM asks: the light lane, while the worker is held
    ok, payload, late = oversize.one()
    assert not ok and payload.startswith(b"too_large: ") and b"max_query_cells 1000000" in payload and late < 0.5
    ok, payload, late = light.one()
    assert ok and late < 1.0 and not slow.ended.is_set()
    ok, payload, late = slow.one()
    assert ok and decode(payload, AssociationReply).truncated and 1.4 < late < 3.0

    for key in (f"{prefix}/assoc/**", f"{prefix}/assoc/*", f"{prefix}/*/*"):
        ok, payload, _ = Asked(zsession, key, small).one()
        assert ok and decode(payload, AssociationReply).method in ("exact", "jcbb")  # auto's choice
    ok, payload, _ = Asked(zsession, keys.assoc("nn"), small).one()  # a concrete key: its own method, as before
    assert ok and decode(payload, AssociationReply).method == "nn"
    last = latest_stats(stats, lambda s: s.extra.get("query_replies") == 1.0 and s.extra.get("light_replies") == 5.0)
    assert last.rejected == {"too_large": 1} and sum(last.messages_in.values()) == 7
    stats.undeclare()


def test_a_service_that_does_not_answer_in_time_is_a_timeout_not_a_refusal(zsession, prefix):
    """Zenoh's own Timeout error (no replier sent it) is TimeoutError for the client, so D-SLAM counts it as
    unreachable and not as a refusal of reason ``Timeout``."""
    keys = Keys(prefix)
    held: list[zenoh.Query] = []
    silent = zsession.declare_queryable(keys.assoc("nn"), held.append)
    with pytest.raises(TimeoutError):
        query_associate(zsession, keys, "nn", dense_request(2, 2), timeout=0.3)
    assert held
    held.clear()
    silent.undeclare()


def write_office_map(tmp_path) -> str:
    path = tmp_path / "office.npy"
    np.save(path, make_world("office", 0).landmarks)
    return str(path)


def scan_request(observations: int, particles: int | None = None, noise=None, request_id: int = 0) -> LocalizeRequest:
    sensor = make_world("office", 0).sensor
    if noise is not None:
        sensor = sensor.model_copy(update={"noise_cov": noise})
    rng = np.random.default_rng(request_id)
    return LocalizeRequest(request_id=request_id, ranges=rng.uniform(0.5, sensor.max_range, observations),
                           bearings=rng.uniform(-sensor.fov / 2, sensor.fov / 2, observations), sensor=sensor,
                           particles=particles)


def test_localize_refuses_bad_and_oversize_requests_at_once_and_a_flood_is_answered(processes, zsession, prefix,
                                                                                   tmp_path):
    keys = Keys(prefix)
    stats = Collector(zsession, keys.stats("mcl"))
    processes.start("mcl", "mcl", "--source", f"file:{write_office_map(tmp_path)}", "--query-queue", "2",
                    "--stats-period-s", "0.3")
    wait_until(lambda: stats.count() > 0, 60, what="the mcl service's stats")

    ok, payload, _ = Asked(zsession, keys.mcl_localize, encode(scan_request(8, noise=np.zeros((2, 2))))).one()
    assert not ok and payload.startswith(b"invalid: ") and b"positive definite" in payload
    ok, payload, late = Asked(zsession, keys.mcl_localize, encode(scan_request(3000, 50_000))).one()
    assert not ok and payload.startswith(b"too_large: ") and b"max_localize_particles 5000" in payload and late < 0.5
    ok, payload, _ = Asked(zsession, keys.mcl_localize, encode(scan_request(8, request_id=3))).one()
    assert ok and decode(payload, LocalizeReply).request_id == 3

    flood = [Asked(zsession, keys.mcl_localize, encode(scan_request(10, request_id=k))) for k in range(30)]
    outcomes = [asked.one() for asked in flood]
    solved = [decode(payload, LocalizeReply) for ok, payload, _ in outcomes if ok]
    busy = [late for ok, payload, late in outcomes if not ok and payload.startswith(b"busy: ")]
    assert len(solved) + len(busy) == 30 and solved and busy and max(busy) < 1.0
    last = latest_stats(stats, lambda s: s.messages_in.get("localize", 0) == 33
                        and s.extra.get("query_replies") == 1 + len(solved) and sum(s.rejected.values()) == 2 + len(busy))
    assert last.rejected == {"invalid": 1, "too_large": 1, "busy": len(busy)}
    assert "handler_error" not in last.rejected
    log = processes.log("mcl")
    assert "Traceback" not in log and "LinAlgError" not in log
    stats.undeclare()


def test_mcl_keeps_tracking_a_robot_while_a_heavy_localize_query_runs(processes, zsession, prefix):
    keys = Keys(prefix)
    stats = Collector(zsession, keys.stats("mcl"))
    arrivals: list[float] = []
    poses = zsession.declare_subscriber(keys.mcl_pose("r4"), lambda sample: arrivals.append(time.monotonic()))
    processes.start("mcl", "mcl", "--source", "truth", "--max-localize-cells", "200000000", "--max-localize-particles",
                    "50000", "--query-deadline-s", "3")
    wait_until(lambda: stats.count() > 0, 60, what="the mcl service's stats")
    processes.start("r4", "robot", "--id", "r4", "--world", "office", "--unknown-start", "--seed", "3",
                    "--speedup", "4", "--duration", "40", "--start-delay", "0.5")
    wait_until(lambda: len(arrivals) > 20, 30, what="r4's poses from MCL")

    heavy = Asked(zsession, keys.mcl_localize, encode(scan_request(3000, 50_000)))  # about 3 minutes unbounded
    ok, payload, late = heavy.one()
    assert not ok and payload.startswith(b"deadline: "), payload
    assert 2.9 < late < 5.0
    during = [t for t in arrivals if heavy.sent <= t <= heavy.sent + late]
    gaps = np.diff([heavy.sent, *during, heavy.sent + late])
    assert len(during) > 10 and gaps.max() < 1.0, (len(during), gaps.max())
    ok, payload, late = Asked(zsession, keys.mcl_localize, encode(LocalizeRequest(robot_id="r4"))).one()
    assert ok and decode(payload, LocalizeReply).source == "track" and late < 1.0
    last = latest_stats(stats, lambda s: s.rejected.get("deadline") == 1)
    assert "handler_error" not in last.rejected
    poses.undeclare()
    stats.undeclare()
