"""Bounded queries on a live fleet: do heavy queries or a flood of them block ``fleetslam assoc`` or ``fleetslam mcl``?

Per seed, two runs with fresh processes on a real router: a router, ``fleetslam mcl`` (map ``truth``,
``--all-robots``: it tracks both robots), ``fleetslam assoc`` and two simulated robots (office world, the seed's
draws) with every service setting at its default. After a warm-up, the *flood* run sends, a few seconds apart:

- ``assoc_jcbb_200``: one dense JCBB query, 200 measurements × 200 landmarks, every pair gated (35.8 s unbounded);
- ``assoc_ihgr_2000x5000``: one dense IHGR query, 2000 × 5000 (about 363 s and 7.5 GB unbounded);
- ``mcl_3000x50000``: one LocalizeRequest of 3,000 observations and 50,000 particles (about 184 s unbounded);
- ``mcl_largest_admitted``: the largest localization the defaults admit (200 observations × 5,000 particles);
- ``assoc_flood`` and ``mcl_flood``: ``--flood`` (500) ordinary queries at once to each service;

and right after each heavy query an ordinary one (``ordinary_after_s``: how long it took to be answered). The *quiet*
run sends nothing over the same wall time. Per query: the answer (ok, or the refusal's reason) and its seconds;
per flood: answers by kind and the slowest answer. The queries come from a process of their own (the asking client,
as on another machine), which encodes their payloads before the phase: the process timing scans and poses sends and
receives none of them. The services' largest resident memory over the phase above what they held before it.

MCL's stream latency is scan → MclPose: a robot's scan arriving here, MCL's pose for that scan arriving here. Most of
it is MCL's stamp-order wait for the other robot's stream (up to ``--reorder-window-s``), set by how far apart the two
robots' clocks started: it differs from run to run (`hold_ms` medians 1.5–95 ms over 24 runs), not within a run. So each run
is measured against itself: ``--baseline-s`` without queries right before the phase, cut into windows of the pause +
0.5 s, whose slowest p99 is the run's yardstick (``baseline.worst_window_scan_to_pose_ms_p99``). Per probe, the p99
of its window (from the probe to the end of the pause after it) and how far it is above the yardstick
(``{probe}_over_baseline_ms``); per run, its phase's slowest window above the yardstick
(``{run}_phase_worst_window_over_baseline_ms``): the quiet run's says how far above its yardstick a window of an
untouched run goes by chance. MCL's own stats (``latency_ms_p99``: arrival to handled, its last 2000 stream items,
without the stamp-order wait) at the end of the phase. The machine's load average at the end of each run says how far
the figures can be trusted (the machine is shared). Over the seeds: median and worst of each figure.

Targets (issue 16): no query blocks a service for more than 1 s (``ordinary_after_s`` < 1 s, MCL's stream latency
p99 unchanged), each of 500 concurrent queries answered (a result or ``busy``) within 1 s.

    .venv/bin/python benchmarks/query_flood.py [--seeds 0,1,2] [--flood 500] [--out reports/query_flood.json]
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

import numpy as np
import zenoh

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.support.association_problems import dense_request  # noqa: E402
from robots.models import RangeBearingSensor  # noqa: E402
from robots.worlds import make_world  # noqa: E402
from schemas.association import AssociationRequest  # noqa: E402
from schemas.codec import DecodeError, decode, encode  # noqa: E402
from schemas.keys import Keys  # noqa: E402
from schemas.mcl import LocalizeRequest  # noqa: E402
from schemas.messages import MclPose, Scan, ServiceStats  # noqa: E402
from tests.helpers import Processes, client_session, free_port, wait_for_port, wait_until  # noqa: E402
from report import emit, over_seeds  # noqa: E402

PREFIX = "qflood"
ROBOTS = ("r1", "r2")


def ordinary_assoc(seed: int) -> AssociationRequest:
    """A scan as D-SLAM asks about: 10 measurements, 30 landmarks around the robot."""
    rng = np.random.default_rng([seed, 1])
    landmarks = rng.uniform(-8.0, 8.0, (30, 2))
    seen = RangeBearingSensor().observe(np.zeros(3), landmarks[:10]) + rng.normal(0, [0.05, 0.01], (10, 2))
    seen[:, 0] = np.abs(seen[:, 0])
    seen[:, 1] = np.arctan2(np.sin(seen[:, 1]), np.cos(seen[:, 1]))
    return AssociationRequest(measurements=seen, noise=np.diag([0.05**2, 0.01**2]), landmarks=landmarks,
                              landmark_covs=np.tile(np.eye(2) * 0.01, (30, 1, 1)), pose=np.zeros(3),
                              pose_cov=np.diag([0.01, 0.01, 0.001]))


def scan_request(observations: int, particles: int | None, seed: int) -> LocalizeRequest:
    """A LocalizeRequest of ``observations`` random detections with the office sensor."""
    sensor = make_world("office", 0).sensor
    rng = np.random.default_rng([seed, observations])
    return LocalizeRequest(request_id=seed, ranges=rng.uniform(0.5, sensor.max_range, observations),
                           bearings=rng.uniform(-sensor.fov / 2, sensor.fov / 2, observations), sensor=sensor,
                           particles=particles, seed=seed)


class Asked:
    """One query sent without waiting; its first reply (ok, or the refusal's reason) and the seconds it took."""

    def __init__(self, session: zenoh.Session, key: str, payload: bytes, timeout: float = 30.0):
        self.done = threading.Event()
        self.kind: str | None = None
        self.seconds: float | None = None
        self.replies = 0
        self.sent = time.monotonic()
        session.get(key, zenoh.handlers.Callback(self._on_reply, self.done.set), payload=payload, timeout=timeout)

    def _on_reply(self, reply: zenoh.Reply) -> None:
        self.replies += 1
        if self.kind is None:
            self.seconds = time.monotonic() - self.sent
            if reply.ok is not None:
                self.kind = "ok"
            elif reply.replier_id is None:
                self.kind = "no_answer"
            else:
                self.kind = reply.err.payload.to_bytes().decode(errors="replace").partition(":")[0]

    def wait(self, timeout: float = 40.0) -> dict:
        self.done.wait(timeout)
        return {"answer": self.kind or "no_answer", "seconds": None if self.seconds is None else round(self.seconds, 3),
                "replies": self.replies}


class Watch:
    """Scan and MclPose arrivals (for the scan → pose latency), MCL's stats, and the services' resident memory."""

    def __init__(self, session: zenoh.Session, keys: Keys, pids: dict[str, int]):
        self.lock = threading.Lock()
        self.scans: dict[tuple[str, float], float] = {}
        self.poses: list[tuple[str, float, float]] = []  # (robot, stamp, arrival)
        self.stats: list[tuple[float, ServiceStats]] = []
        self.rss: dict[str, list[tuple[float, float]]] = {name: [] for name in pids}
        self.pids = pids
        self.stopping = threading.Event()
        self.entities = [session.declare_subscriber(keys.all_robot_stream("scan"), self._on_scan),
                         session.declare_subscriber(f"{keys.prefix}/mcl/*/pose", self._on_pose),
                         session.declare_subscriber(keys.stats("mcl"), self._on_stats)]
        self.sampler = threading.Thread(target=self._sample_rss, daemon=True)
        self.sampler.start()

    def _on_scan(self, sample) -> None:
        now = time.monotonic()
        try:
            scan = decode(sample.payload.to_bytes(), Scan)
        except DecodeError:
            return
        with self.lock:
            self.scans[(scan.robot_id, scan.stamp)] = now

    def _on_pose(self, sample) -> None:
        now = time.monotonic()
        pose = decode(sample.payload.to_bytes(), MclPose)
        with self.lock:
            self.poses.append((pose.robot_id, pose.stamp, now))

    def _on_stats(self, sample) -> None:
        now = time.monotonic()
        with self.lock:
            self.stats.append((now, decode(sample.payload.to_bytes(), ServiceStats)))

    def _sample_rss(self) -> None:
        while not self.stopping.wait(0.2):
            for name, pid in self.pids.items():
                try:
                    text = Path(f"/proc/{pid}/status").read_text()
                except OSError:
                    continue
                kb = next(int(line.split()[1]) for line in text.splitlines() if line.startswith("VmRSS:"))
                with self.lock:
                    self.rss[name].append((time.monotonic(), kb / 1024))

    def latency(self, start: float, end: float) -> dict:
        """Scan → MclPose latency (ms) of the scans that arrived in [start, end]."""
        with self.lock:
            values = [(arrival - self.scans[(rid, stamp)]) * 1e3 for rid, stamp, arrival in self.poses
                      if (rid, stamp) in self.scans and start <= self.scans[(rid, stamp)] <= end]
        if not values:
            return {"scan_to_pose_ms_p99": None, "scan_to_pose_ms_median": None, "poses": 0}
        return {"scan_to_pose_ms_p99": round(float(np.percentile(values, 99)), 2),
                "scan_to_pose_ms_median": round(float(np.median(values)), 2), "poses": len(values)}

    def worst_window(self, start: float, end: float, length: float) -> float | None:
        """The largest scan → pose p99 (ms) of the consecutive windows of ``length`` seconds in [start, end]: how
        slow a few seconds of this run got, to set a probe's window against."""
        worst = None
        while start + length <= end:
            p99 = self.latency(start, start + length)["scan_to_pose_ms_p99"]
            if p99 is not None:
                worst = p99 if worst is None else max(worst, p99)
            start += length
        return worst

    def stats_at(self, t: float) -> ServiceStats | None:
        with self.lock:
            before = [stats for arrival, stats in self.stats if arrival <= t]
        return before[-1] if before else None

    def rss_growth(self, start: float, end: float) -> dict:
        """Per service: the largest RSS in [start, end] above the last sample before ``start`` (MB)."""
        out = {}
        with self.lock:
            for name, samples in self.rss.items():
                before = [mb for t, mb in samples if t < start]
                during = [mb for t, mb in samples if start <= t <= end]
                if before and during:
                    out[name] = round(max(during) - before[-1], 1)
        return out

    def close(self) -> None:
        self.stopping.set()
        for entity in self.entities:
            entity.undeclare()


def probe_payloads(seed: int, count: int) -> dict[str, tuple[str, bytes | list[bytes], bytes | None]]:
    """Per probe, in order: (method, or ``mcl``; the heavy payload or the flood's payloads; the ordinary payload sent
    right after a heavy one, None for a flood)."""
    assoc, scan = encode(ordinary_assoc(seed)), encode(scan_request(10, None, seed))
    return {
        "assoc_jcbb_200": ("jcbb", encode(dense_request(200, 200, seed)), assoc),
        "assoc_ihgr_2000x5000": ("ihgr", encode(dense_request(2000, 5000, seed)), assoc),
        "mcl_3000x50000": ("mcl", encode(scan_request(3000, 50_000, seed)), scan),
        "mcl_largest_admitted": ("mcl", encode(scan_request(200, 5_000, seed)), scan),
        "assoc_flood": ("auto", [encode(ordinary_assoc(seed * 1000 + k)) for k in range(count)], None),
        "mcl_flood": ("mcl", [encode(scan_request(10, None, seed * 1000 + k)) for k in range(count)], None),
    }


def heavy_then_ordinary(session: zenoh.Session, key: str, heavy: bytes, ordinary_key: str, ordinary: bytes) -> dict:
    """One heavy query, and an ordinary one sent right after it: both answers."""
    big = Asked(session, key, heavy)
    time.sleep(0.05)  # the heavy one is in (decoded, sized, with a worker) before the ordinary one comes
    small = Asked(session, ordinary_key, ordinary)
    result = big.wait()
    after = small.wait()
    return {**result, "ordinary_after_s": after["seconds"], "ordinary_after": after["answer"]}


def flood(session: zenoh.Session, key: str, payloads: list[bytes]) -> dict:
    """Every payload at once; answers by kind, the slowest answer, how many were answered within 1 s."""
    asked = [Asked(session, key, payload) for payload in payloads]
    answers = [a.wait() for a in asked]
    seconds = [a["seconds"] for a in answers if a["seconds"] is not None]
    return {"queries": len(payloads), "answers": dict(Counter(a["answer"] for a in answers)),
            "max_answer_s": round(max(seconds), 3) if seconds else None,
            "answered_within_1s": sum(1 for a in answers if a["seconds"] is not None and a["seconds"] <= 1.0),
            "more_than_one_reply": sum(1 for a in answers if a["replies"] > 1)}


def asker(endpoint: str, prefix: str, seed: int, count: int, conn) -> None:
    """The asking client, a process of its own as a client on another machine would be: it encodes the probes'
    payloads, sends their names in order (it is ready), then runs each probe it is sent by name and sends back its
    answers (None: stop)."""
    keys = Keys(prefix)
    payloads = probe_payloads(seed, count)
    with client_session(endpoint) as session:
        conn.send(list(payloads))
        while (name := conn.recv()) is not None:
            service, heavy, ordinary = payloads[name]
            key = keys.mcl_localize if service == "mcl" else keys.assoc(service)
            ordinary_key = keys.mcl_localize if service == "mcl" else keys.assoc("auto")
            if ordinary is None:
                conn.send(flood(session, key, heavy))
            else:
                conn.send(heavy_then_ordinary(session, key, heavy, ordinary_key, ordinary))


class AskingClient:
    """:func:`asker` in a child process: the queries, and their hundreds of replies, cost this process (which times
    the scans and poses) nothing, as they would cost the observer nothing on a real network."""

    def __init__(self, endpoint: str, seed: int, count: int):
        context = multiprocessing.get_context("spawn")
        self.conn, theirs = context.Pipe()
        self.process = context.Process(target=asker, args=(endpoint, PREFIX, seed, count, theirs), daemon=True)
        self.process.start()
        if not self.conn.poll(120):
            raise RuntimeError("the asking client did not start")
        self.probes: list[str] = self.conn.recv()  # in probe_payloads' order

    def ask(self, probe: str) -> dict:
        self.conn.send(probe)
        if not self.conn.poll(300):
            raise RuntimeError(f"the asking client did not answer probe {probe}")
        return self.conn.recv()

    def close(self) -> None:
        try:
            self.conn.send(None)
        except OSError:
            pass
        self.process.join(10)
        if self.process.is_alive():
            self.process.kill()


def run(seed: int, loud: bool, args: argparse.Namespace) -> dict:
    """One run: services and robots, a warm-up, the query phase (queries when ``loud``), the figures."""
    with tempfile.TemporaryDirectory(prefix="query_flood_") as folder:
        port = free_port()
        endpoint = f"tcp/127.0.0.1:{port}"
        env = {k: v for k, v in os.environ.items() if not k.startswith("FLEETSLAM_")}
        processes = Processes(Path(folder), {**env, "PYTHONUNBUFFERED": "1", "FLEETSLAM_ZENOH_CONNECT": endpoint,
                                             "FLEETSLAM_PREFIX": PREFIX, "FLEETSLAM_CONNECT_TIMEOUT_S": "10"})
        session = None
        watch = None
        client = None
        try:
            processes.start("router", "router", "--listen", endpoint)
            wait_for_port(port)
            session = client_session(endpoint)
            keys = Keys(PREFIX)
            mcl = processes.start("mcl", "mcl", "--source", "truth", "--all-robots", "--stats-period-s", "0.5")
            assoc = processes.start("assoc", "assoc")
            watch = Watch(session, keys, {"mcl": mcl.pid, "assoc": assoc.pid})
            wait_until(lambda: watch.stats_at(time.monotonic()) is not None, 90, what="MCL's stats")
            wait_until(lambda: Asked(session, keys.assoc("nn"), encode(ordinary_assoc(seed)), 1.0).wait()["answer"] == "ok",
                       90, interval=0.5, what="the association service's first answer")
            duration = args.warm_up_s + args.baseline_s + args.phase_s + 10.0
            for k, rid in enumerate(ROBOTS):
                processes.start(rid, "robot", "--id", rid, "--world", "office", "--seed", str(seed * 10 + k),
                                "--speedup", str(args.speedup), "--duration", str(duration * args.speedup),
                                "--start-delay", "0.5")
            client = AskingClient(endpoint, seed, args.flood)  # in both runs: the same processes, one of them idle
            wait_until(lambda: len(watch.poses) > 20, 60, what="MCL's poses of the robots")
            time.sleep(args.warm_up_s)
            baseline = time.monotonic()
            time.sleep(args.baseline_s)
            start = time.monotonic()
            queries, windows = {}, {}
            for name in client.probes if loud else ():
                began = time.monotonic()
                queries[name] = client.ask(name)
                time.sleep(args.pause_s)
                windows[name] = watch.latency(began, time.monotonic())
            left = start + args.phase_s - time.monotonic()
            if left > 0:
                time.sleep(left)
            end = time.monotonic()
            time.sleep(1.0)  # the last poses of the phase come in
            stats = watch.stats_at(end + 0.6)
            window = args.pause_s + 0.5
            return {"seed": seed, "run": "flood" if loud else "quiet", "phase_s": round(end - start, 1),
                    "baseline": {**watch.latency(baseline, start), "worst_window_scan_to_pose_ms_p99":
                                 watch.worst_window(baseline, start, window)},
                    "load_average": [round(v, 2) for v in os.getloadavg()],
                    "queries": queries, **watch.latency(start, end), "latency_by_probe": windows,
                    "worst_window_scan_to_pose_ms_p99": watch.worst_window(start, end, window),
                    "stats_latency_ms_p99": None if stats is None else round(stats.latency_ms_p99, 2),
                    "stats_hold_ms": {} if stats is None else {k: round(v, 2) for k, v in stats.extra.items()
                                                               if k.startswith("hold_ms")},
                    "rejected": {} if stats is None else dict(stats.rejected),
                    "query_extra": {} if stats is None else {k: round(v, 2) for k, v in stats.extra.items()
                                                             if k.startswith("query_")},
                    "rss_growth_mb": watch.rss_growth(start, end)}
        finally:
            if client is not None:
                client.close()
            if watch is not None:
                watch.close()
            if session is not None:
                session.close()
            processes.stop_all()


def seed_figures(quiet: dict, loud: dict) -> dict:
    """The figures of one seed that the targets speak of, flat, for :func:`over_seeds`."""
    q = loud["queries"]
    out = {f"{name}_ordinary_after_s": q[name]["ordinary_after_s"] for name in q if "ordinary_after_s" in q[name]}
    out.update({f"{name}_answer_s": q[name]["seconds"] for name in q if "seconds" in q[name]})
    for name in ("assoc_flood", "mcl_flood"):
        out[f"{name}_max_answer_s"] = q[name]["max_answer_s"]
        out[f"{name}_not_within_1s"] = q[name]["queries"] - q[name]["answered_within_1s"]
    out["quiet_load_average_1m"], out["flood_load_average_1m"] = quiet["load_average"][0], loud["load_average"][0]
    for figure in ("scan_to_pose_ms_p99", "scan_to_pose_ms_median", "stats_latency_ms_p99",
                   "worst_window_scan_to_pose_ms_p99"):
        out[f"quiet_{figure}"] = quiet[figure]
        out[f"flood_{figure}"] = loud[figure]
    for name, mb in loud["rss_growth_mb"].items():
        out[f"flood_rss_growth_mb_{name}"] = mb
    for name, result in (("quiet", quiet), ("flood", loud)):
        yardstick = result["baseline"]["worst_window_scan_to_pose_ms_p99"]
        out[f"{name}_baseline_scan_to_pose_ms_p99"] = result["baseline"]["scan_to_pose_ms_p99"]
        out[f"{name}_baseline_worst_window_scan_to_pose_ms_p99"] = yardstick
        out[f"{name}_phase_worst_window_over_baseline_ms"] = over(result["worst_window_scan_to_pose_ms_p99"], yardstick)
    for name, window in loud["latency_by_probe"].items():
        out[f"{name}_scan_to_pose_ms_p99"] = window["scan_to_pose_ms_p99"]
        out[f"{name}_over_baseline_ms"] = over(window["scan_to_pose_ms_p99"],
                                               loud["baseline"]["worst_window_scan_to_pose_ms_p99"])
    return out


def over(value: float | None, yardstick: float | None) -> float | None:
    """How many ms ``value`` is above ``yardstick`` (negative: below); None when either is missing."""
    return None if value is None or yardstick is None else round(value - yardstick, 2)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--flood", type=int, default=500, help="queries at once to each service")
    parser.add_argument("--speedup", type=float, default=2.0, help="robots' speed-up (MCL tracks 2 × 20 msg/s × this)")
    parser.add_argument("--warm-up-s", type=float, default=6.0, help="wall seconds of tracking before the queries")
    parser.add_argument("--baseline-s", type=float, default=10.0,
                        help="wall seconds without queries before the query phase, in both runs: each run's own yardstick")
    parser.add_argument("--phase-s", type=float, default=30.0, help="wall seconds of the query phase (both runs)")
    parser.add_argument("--pause-s", type=float, default=2.0, help="wall seconds between two probes")
    parser.add_argument("--out", help="also write the JSON here")
    args = parser.parse_args()
    runs, figures = [], []
    for seed in (int(s) for s in args.seeds.split(",")):
        quiet = run(seed, False, args)
        loud = run(seed, True, args)
        runs += [quiet, loud]
        figures.append(seed_figures(quiet, loud))
        print(f"seed {seed}: {figures[-1]}", file=sys.stderr, flush=True)
    keys = sorted({key for row in figures for key in row})
    report = {"benchmark": "query_flood", "robots": len(ROBOTS), "world": "office", "speedup": args.speedup,
              "flood": args.flood, "cpus": os.cpu_count(),
              "targets": {"ordinary_after_s": "< 1 s after any heavy query", "flood": "each answered (ok or busy) "
                          "within 1 s", "stream latency p99": "unchanged: each probe's window above its run's yardstick "
                          "({probe}_over_baseline_ms) no more than an untouched run's phase goes above its own "
                          "(quiet_phase_worst_window_over_baseline_ms)"},
              "over_seeds": over_seeds(figures, keys), "seeds": figures, "runs": runs}
    emit(report, args.out)


if __name__ == "__main__":
    main()
