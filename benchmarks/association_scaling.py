"""Time per association against problem size, in-process and through a router (prints JSON).

Each problem is a dense scan: N landmarks scattered 1.5-8 m ahead of the robot
(about 0.35 m apart at N = 200), the robot pose uncertain (σ 0.1 m, 1.5°), 90 %
of the landmarks detected with noise plus clutter up to M = N measurements, so
the gate graph has real conflicts. For each size and method it times
:func:`associate` in-process (gating + costs + solve, the whole call) over
``--problems`` random problems; then it starts a router and one
``fleetslam assoc`` and times the round trip of a query (encode, router,
service decode + solve + encode, reply, decode) for each size with the exact
method and for M = N = 50 with every method.

    python benchmarks/association_scaling.py --out reports/association_scaling.json
"""

from __future__ import annotations

import argparse
import math
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from robots.models import RangeBearingSensor  # noqa: E402
from schemas.association import AssociationRequest  # noqa: E402
from schemas.codec import encode  # noqa: E402
from schemas.config import FleetSettings  # noqa: E402
from schemas.keys import Keys  # noqa: E402
from schemas.transport import open_session  # noqa: E402
from services.association.client import AssociationClient, query_associate  # noqa: E402
from services.association.core import associate  # noqa: E402
from report import emit

R = np.diag([0.03**2, math.radians(0.5) ** 2])


def dense_problem(size: int, rng: np.random.Generator) -> AssociationRequest:
    """M = N = ``size``: landmarks in a wedge ahead, 90 % detected, clutter fills up to M."""
    radius = rng.uniform(1.5, 8.0, size)
    angle = rng.uniform(-1.2, 1.2, size)
    landmarks = np.stack([radius * np.cos(angle), radius * np.sin(angle)], -1)
    pose_cov = np.diag([0.1**2, 0.1**2, math.radians(1.5) ** 2])
    true_pose = rng.multivariate_normal(np.zeros(3), pose_cov)
    sensor = RangeBearingSensor()
    seen = rng.random(size) < 0.9
    z = sensor.observe(true_pose, landmarks[seen]) + rng.normal(size=(int(seen.sum()), 2)) * np.sqrt(np.diag(R))
    clutter = np.stack([rng.uniform(1.5, 8.0, size - z.shape[0]), rng.uniform(-1.2, 1.2, size - z.shape[0])], -1)
    z = np.vstack([z, clutter])[rng.permutation(size)]
    z[:, 1] = np.arctan2(np.sin(z[:, 1]), np.cos(z[:, 1]))
    return AssociationRequest(
        measurements=z, noise=R, landmarks=landmarks, landmark_covs=np.tile(np.eye(2) * 0.02**2, (size, 1, 1)),
        pose=np.zeros(3), pose_cov=pose_cov, clutter_density=0.1 * size / (6.5 * 2.4), new_feature_density=1e-3,
        detection_probability=0.9,
    )


def summary(ms: list[float]) -> dict:
    values = np.asarray(ms)
    return {"median_ms": round(float(np.median(values)), 4), "p90_ms": round(float(np.percentile(values, 90)), 4),
            "mean_ms": round(float(values.mean()), 4), "n": int(values.size)}


def in_process(sizes: list[int], methods: list[str], problems: int, jcbb_max: int, seed: int) -> dict:
    out: dict = {}
    for size in sizes:
        rng = np.random.default_rng([seed, size])
        requests = [dense_problem(size, rng) for _ in range(problems)]
        row: dict = {}
        for method in methods:
            if method in ("jcbb", "auto") and size > jcbb_max:
                row[method] = {"skipped": f"JCBB's search is exponential; sizes above {jcbb_max} not timed"}
                continue
            associate(requests[0], method)  # warm up (imports, caches)
            times, extra = [], {"gated_pairs": [], "components": [], "lp_solves": [], "truncated": 0}
            for request in requests:
                started = time.perf_counter()
                reply = associate(request, method)
                times.append((time.perf_counter() - started) * 1e3)
                extra["gated_pairs"].append(reply.gated_pairs)
                if reply.components is not None:
                    extra["components"].append(reply.components)
                extra["lp_solves"].append(reply.lp_solves)
                extra["truncated"] += reply.truncated
            row[method] = {**summary(times), "gated_pairs_mean": float(np.mean(extra["gated_pairs"])),
                           "components_mean": float(np.mean(extra["components"])) if extra["components"] else None,
                           "lp_solves_mean": float(np.mean(extra["lp_solves"])), "jcbb_truncated": extra["truncated"]}
        out[str(size)] = row
        print(f"in-process M=N={size}: " + ", ".join(f"{m} {v.get('median_ms', '-')} ms" for m, v in row.items()), file=sys.stderr)
    return out


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_port(port: int, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while True:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
            return
        except OSError:
            if time.monotonic() > deadline:
                raise SystemExit("router did not start")
            time.sleep(0.05)


def through_router(sizes: list[int], methods: list[str], queries: int, method_queries: int, instances: int, seed: int) -> dict:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    prefix = f"bench{port}"
    env = {**os.environ, "FLEETSLAM_ZENOH_CONNECT": endpoint, "FLEETSLAM_PREFIX": prefix, "FLEETSLAM_LOG_LEVEL": "WARNING"}
    cli = [sys.executable, "-m", "services.cli"]
    started = [subprocess.Popen([*cli, "router", "--listen", endpoint], env=env, cwd=REPO, stderr=subprocess.DEVNULL)]
    try:
        wait_port(port)
        started += [subprocess.Popen([*cli, "assoc"], env=env, cwd=REPO, stderr=subprocess.DEVNULL) for _ in range(instances)]
        session = open_session(FleetSettings(zenoh_connect=endpoint))
        keys = Keys(prefix)
        client = AssociationClient(session, keys, timeout=5.0)
        deadline = time.monotonic() + 20
        while len(client.instances) < instances:
            if time.monotonic() > deadline:
                raise SystemExit("association service did not start")
            time.sleep(0.05)
        out: dict = {"instances": instances, "sizes": {}, "methods_50": {}}

        def time_queries(method: str, payload: bytes, count: int) -> dict:
            query_associate(session, keys, method, payload, timeout=5.0)
            times = []
            for _ in range(count):
                t0 = time.perf_counter()
                query_associate(session, keys, method, payload, timeout=5.0)
                times.append((time.perf_counter() - t0) * 1e3)
            return summary(times)

        for size in sizes:
            payload = encode(dense_problem(size, np.random.default_rng([seed, size, 1])))
            out["sizes"][str(size)] = {"method": "exact", "payload_bytes": len(payload), **time_queries("exact", payload, queries)}
            print(f"round trip M=N={size} exact: {out['sizes'][str(size)]['median_ms']} ms", file=sys.stderr)
        payload = encode(dense_problem(50, np.random.default_rng([seed, 50, 1])))
        for method in methods:
            out["methods_50"][method] = time_queries(method, payload, method_queries)
        if instances > 1:  # round robin over the instances from this one client
            times = []
            for _ in range(queries):
                t0 = time.perf_counter()
                client.associate("exact", payload)
                times.append((time.perf_counter() - t0) * 1e3)
            out["round_robin_50_exact"] = summary(times)
        client.close()
        session.close()
        return out
    finally:
        for process in reversed(started):
            process.terminate()
        for process in reversed(started):
            try:
                process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                process.kill()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="5,10,20,50,100,200", help="M = N values")
    parser.add_argument("--methods", default="nn,greedy,ihgr,exact,jcbb,auto")
    parser.add_argument("--problems", type=int, default=30, help="random problems per size (in-process)")
    parser.add_argument("--queries", type=int, default=300, help="queries per round-trip measurement")
    parser.add_argument("--method-queries", type=int, default=50, help="queries per method at M = N = 50")
    parser.add_argument("--jcbb-max", type=int, default=50, help="largest size JCBB is timed at")
    parser.add_argument("--instances", type=int, default=1, help="association service instances")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-router", action="store_true", help="skip the round trip through a router")
    parser.add_argument("--out", help="also write the JSON here")
    args = parser.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    methods = args.methods.split(",")
    result = {
        "benchmark": "association_scaling",
        "problem": "M = N; landmarks 1.5-8 m ahead in a ±1.2 rad wedge; 90 % detected; clutter up to M; "
                   "pose σ 0.1 m / 1.5°; noise σ 0.03 m / 0.5°; landmark form with pose covariance",
        "in_process": in_process(sizes, methods, args.problems, args.jcbb_max, args.seed),
    }
    if not args.no_router:
        result["round_trip"] = through_router(sizes, methods, args.queries, args.method_queries, args.instances, args.seed)
    emit(result, args.out)


if __name__ == "__main__":
    main()
