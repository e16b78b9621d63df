"""``fleetslam assoc`` over a real router: many concurrent clients in several processes, load sharing, refusals."""

from __future__ import annotations

import multiprocessing
import threading

import msgpack
import numpy as np
import pytest

from schemas.association import AssociationRequest
from schemas.codec import decode, encode
from schemas.keys import Keys
from schemas.messages import RobotInfo, ServiceStats
from services.association.client import AssociationClient, AssociationRefused, query_associate
from services.association.core import associate
from tests.helpers import Collector, client_session, wait_until

pytestmark = pytest.mark.integration

R = np.diag([0.05**2, np.radians(1.0) ** 2])
METHODS = ("nn", "ihgr", "exact", "jcbb", "auto")


def make_request(seed: int) -> AssociationRequest:
    """A random scan near a robot: some landmarks seen (noisy, shuffled), some measurements new."""
    rng = np.random.default_rng(seed)
    n, m = int(rng.integers(1, 15)), int(rng.integers(0, 15))
    landmarks = rng.uniform(-5.0, 5.0, size=(n, 2))
    pose = np.array([0.0, 0.0, rng.uniform(-np.pi, np.pi)])
    from robots.models import RangeBearingSensor

    seen = RangeBearingSensor().observe(pose, landmarks)[rng.permutation(n)[: min(m, n)]]
    extra = np.stack([rng.uniform(0.5, 7.0, max(0, m - n)), rng.uniform(-np.pi, np.pi, max(0, m - n))], -1)
    z = np.vstack([seen + rng.normal(size=seen.shape) * [0.05, 0.017], extra])
    z[:, 0] = np.abs(z[:, 0])
    z[:, 1] = np.arctan2(np.sin(z[:, 1]), np.cos(z[:, 1]))
    return AssociationRequest(
        request_id=seed, measurements=z, noise=R, landmarks=landmarks,
        landmark_covs=np.tile(np.eye(2) * 0.01, (n, 1, 1)), pose=pose, pose_cov=np.diag([0.01, 0.01, 0.001]),
    )


def client_worker(endpoint: str, prefix: str, seeds: list[int], out) -> None:
    """One client process: ask for every seed with every method, compare with the in-process answer."""
    session = client_session(endpoint)
    keys = Keys(prefix)
    client = AssociationClient(session, keys, timeout=5.0)
    wait_until(lambda: len(client.instances) >= 2, 10, what="both instances' tokens")
    mismatches = answered = 0
    for seed in seeds:
        request = make_request(seed)
        for method in METHODS:
            reply = client.associate(method, request)
            expected = associate(request, method)
            answered += 1
            mismatches += reply.request_id != seed or not np.array_equal(reply.assignment, expected.assignment)
    client.close()
    session.close()
    out.put((answered, mismatches))


def start_two_instances(processes, zsession, prefix):
    for name in ("assoc1", "assoc2"):
        processes.start(name, "assoc")
    client = AssociationClient(zsession, Keys(prefix), timeout=5.0)
    wait_until(lambda: len(client.instances) >= 2, 60, what="two association instances")  # a fresh clone compiles first
    return client


def test_concurrent_clients_in_several_processes_share_two_instances(router, processes, zsession, prefix):
    stats: dict[str, ServiceStats] = {}
    lock = threading.Lock()

    def on_stats(sample):
        message = decode(sample.payload.to_bytes(), ServiceStats)
        with lock:
            stats[message.instance] = message

    subscriber = zsession.declare_subscriber(Keys(prefix).stats("assoc"), on_stats)
    client = start_two_instances(processes, zsession, prefix)
    context = multiprocessing.get_context("spawn")
    results = context.Queue()
    workers = [context.Process(target=client_worker, args=(router.endpoint, prefix, list(range(k * 10, k * 10 + 10)), results))
               for k in range(2)]
    for worker in workers:
        worker.start()
    threads_ok = []

    def thread_client(seed0):  # concurrent requests from threads of this process too, on the public key
        for seed in range(seed0, seed0 + 10):
            request = make_request(seed)
            reply = query_associate(zsession, Keys(prefix), "exact", request, timeout=5.0)
            threads_ok.append(np.array_equal(reply.assignment, associate(request, "exact").assignment))

    threads = [threading.Thread(target=thread_client, args=(1000 + 10 * k,)) for k in range(3)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=60)
    outcomes = [results.get(timeout=90) for _ in workers]
    for worker in workers:
        worker.join(timeout=30)
    assert sum(a for a, _ in outcomes) == 2 * 10 * len(METHODS)
    assert sum(m for _, m in outcomes) == 0
    assert len(threads_ok) == 30 and all(threads_ok)

    def both_served():
        with lock:
            served = [sum(s.messages_in.values()) for s in stats.values()]
        return len(served) == 2 and min(served) >= 2 * 10 * len(METHODS) // 2

    wait_until(both_served, 10, what="stats showing both instances served requests")
    subscriber.undeclare()
    client.close()


def test_malformed_requests_get_errors_and_the_service_keeps_serving(router, processes, zsession, prefix):
    keys = Keys(prefix)
    client = start_two_instances(processes, zsession, prefix)
    good = make_request(1)

    def refusal(payload, method="exact"):
        with pytest.raises(AssociationRefused) as info:
            query_associate(zsession, keys, method, payload, timeout=5.0)
        return info.value.reason

    assert refusal(b"\x00\x01garbage") == "malformed"
    other = RobotInfo(robot_id="r1", stamp=0.0, motion_model="unicycle",
                      sensor={"max_range": 5.0, "fov": 3.0, "noise_cov": R}, odom_rate_hz=10, scan_rate_hz=10)
    assert refusal(encode(other)) == "wrong_schema"
    body = decode(encode(good), AssociationRequest).model_dump()
    body["predicted"] = np.zeros((1, 2))  # both forms at once
    assert refusal(msgpack.packb({"schema": "AssociationRequest", "v": 1, "body": {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in body.items()}})) == "invalid"
    bad_cov = good.model_copy(update={"landmark_covs": -np.tile(np.eye(2), (good.landmarks.shape[0], 1, 1)), "pose_cov": None, "noise": R * 0})
    assert refusal(encode(bad_cov)) == "bad_covariance"
    no_payload = list(zsession.get(keys.assoc("ihgr"), timeout=5.0))
    assert len(no_payload) == 1 and no_payload[0].err is not None
    assert no_payload[0].err.payload.to_bytes().decode().startswith("empty")
    for method in METHODS:  # still serving, on both instances
        for _ in range(2):
            assert np.array_equal(client.associate(method, good).assignment, associate(good, method).assignment)
    collector = Collector(zsession, keys.stats("assoc"))

    def rejections():
        totals: dict[str, int] = {}
        for message in collector.decoded(ServiceStats):
            for reason, count in message.rejected.items():
                totals[reason] = max(totals.get(reason, 0), count)
        return {"malformed", "wrong_schema", "invalid", "bad_covariance", "empty"} <= totals.keys()

    wait_until(rejections, 10, what="the rejections counted in the stats")
    collector.undeclare()
    client.close()
