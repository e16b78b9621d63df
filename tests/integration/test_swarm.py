"""``fleetslam swarm``: many simulated robots in one process, each on its own keys with its own liveliness token;
every message it says it sent arrives, the tokens go when it stops, and the central service fuses a swarm."""

from __future__ import annotations

import json
import threading
from collections import Counter, defaultdict

import pytest
import zenoh

from schemas.codec import decode
from schemas.keys import Keys
from schemas.messages import Estimate, Odometry, Scan, ServiceStats
from tests.helpers import Collector, wait_until

pytestmark = pytest.mark.integration

MODELS = {"odom": Odometry, "scan": Scan}


class Tokens:
    """The liveliness tokens under a key expression: the keys ever declared and the keys that are gone."""

    def __init__(self, session: zenoh.Session, key: str):
        self._lock = threading.Lock()
        self.declared: set[str] = set()
        self.gone: set[str] = set()
        self._subscriber = session.liveliness().declare_subscriber(key, self._on_sample, history=True)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        with self._lock:
            (self.gone if sample.kind == zenoh.SampleKind.DELETE else self.declared).add(str(sample.key_expr))

    def alive(self) -> set[str]:
        with self._lock:
            return self.declared - self.gone


def swarm_args(robots: int, duration: float, speedup: float, counts_file, *extra: str) -> tuple[str, ...]:
    return ("swarm", "--robots", str(robots), "--duration", str(duration), "--speedup", str(speedup),
            "--start-delay", "1", "--linger-s", "0.5", "--json-out", str(counts_file), *extra)


def test_every_robot_of_a_swarm_has_its_token_and_every_message_arrives(router, processes, zsession, prefix, tmp_path):
    robots = [f"s{k}" for k in range(1, 21)]
    keys = Keys(prefix)
    tokens = Tokens(zsession, f"{prefix}/robots/*/alive")
    streams = Collector(zsession, f"{prefix}/robots/*/*")
    swarm = processes.start("swarm", *swarm_args(20, 5.0, 5.0, tmp_path / "sent.json", "--progress-period-s", "0.1"))
    wait_until(lambda: tokens.alive() == {keys.alive(rid) for rid in robots}, 30, what="every robot's token")
    assert swarm.wait(timeout=60) == 0, processes.log("swarm")
    assert "swarm at " in processes.log("swarm"), "no progress line: " + processes.log("swarm")[-2000:]
    sent = json.loads((tmp_path / "sent.json").read_text())
    assert sent["robots"] == 20 and sent["stopped_by"] is None
    assert set(sent["per_robot"]) == set(robots)
    expected = {(rid, stream): counts[stream] for rid, counts in sent["per_robot"].items() for stream in MODELS}
    assert all(count == 51 if stream == "scan" else count == 50 for (_, stream), count in expected.items()), expected

    def received() -> Counter:
        return Counter((key.split("/")[-2], key.split("/")[-1]) for key, _ in streams.snapshot()
                       if key.split("/")[-1] in MODELS)

    wait_until(lambda: received() == Counter(expected), 20, what="every message the swarm says it sent")
    seqs: dict[tuple[str, str], list[int]] = defaultdict(list)
    for key, payload in streams.snapshot():
        rid, stream = key.split("/")[-2:]
        if stream in MODELS:
            seqs[(rid, stream)].append(decode(payload, MODELS[stream]).seq)
    assert all(values == list(range(expected[name])) for name, values in seqs.items())
    assert sum(1 for key, _ in streams.snapshot() if key.endswith("/info")) >= 20
    wait_until(lambda: not tokens.alive(), 10, what="every token gone after the swarm stopped")
    assert tokens.gone == {keys.alive(rid) for rid in robots}


def test_central_fuses_a_swarm_without_landmark_ids(router, processes, zsession, prefix, tmp_path):
    robots = {f"s{k}" for k in range(1, 11)}
    keys = Keys(prefix)
    estimates = Collector(zsession, keys.central_estimate)
    stats = Collector(zsession, keys.stats("central"))
    processes.start("central", "central", "--association", "shared", "--particles", "20", "--estimate-rate-hz", "4")
    wait_until(lambda: stats.count() > 0, 60, what="the central service's first stats")
    swarm = processes.start("swarm", *swarm_args(10, 4.0, 2.0, tmp_path / "sent.json"))
    assert swarm.wait(timeout=60) == 0, processes.log("swarm")
    sent = json.loads((tmp_path / "sent.json").read_text())["sent"]

    def processed_all() -> bool:
        last = stats.decoded(ServiceStats)[-1]
        return last.extra.get("processed", 0) >= sent["odom"] + sent["scan"] and last.extra.get("buffered", 1) == 0

    wait_until(processed_all, 30, what="central to process every odometry and scan of the swarm")
    last = stats.decoded(ServiceStats)[-1]
    assert last.extra["processed"] == sent["odom"] + sent["scan"]
    assert last.extra["missing"] == 0 and not last.rejected, last
    wait_until(lambda: any({r.robot_id for r in e.robots} == robots for e in estimates.decoded(Estimate)), 20,
               what="every robot of the swarm in the central estimate")
