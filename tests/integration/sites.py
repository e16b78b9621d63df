"""A fleet over three sites in network namespaces, each with its own router, joined by slow and lossy links.

Used by tests/integration/test_multi_site.py (short) and benchmarks/multi_site.py (the issue's 30 s cut, many runs):

- host ``depot``: a router, central FastSLAM (with checkpoints, ``--state-dir``) and the test's receiver
  (tests/integration/observer.py, recovering what it missed like every service);
- hosts ``site1`` and ``site2``: a router connected to the depot's (``fleetslam router --connect``) and a
  simulated robot, a client of its site's router;
- each site's link delays by ``delay_ms`` ± ``jitter_ms`` and loses ``loss_pct`` % of the packets in both
  directions: with ``tc netem`` on the site's cable (its veth) where the kernel has it; else (this machine's kernel:
  "Specified qdisc kind is unknown") through a relay in the depot (tests/integration/linkrelay.py: the site's
  router connects to it, it connects on to the depot's router), which holds every chunk ``delay_ms`` ±
  ``jitter_ms`` and, for a loss under TCP, stalls the stream for a retransmission timeout (200 ms) on
  ``loss_pct`` % of the chunks; the figures say which (``link_shaping``: ``netem``, ``relay`` or ``none``);
- an untouched copy of the fleet beside it, under its own key prefix (as in the crash test): the same two robots
  (same world, seed and duration, so the same data) and the same central, all in the depot on its router, which
  no fault touches.

Faults, in order: site1's cable is unplugged for ``cut_s`` (longer than the 10 s lease: both routers drop the
link); half-way through the cut central is killed (SIGKILL) and started again at once from its checkpoints; after
the cable's return site2's router is killed and started again. The robots then run to the end of their
``duration_s`` by themselves. The figures: when site1's robot was heard at the depot again after the cable came
back, when site2's after its router restarted, when central was back after its kill, the bytes each site's link
carried per second, every message each robot sent against what reached the depot's receiver and central, and
whether central's final estimate (the full one its state query answers) is the untouched copy's, bit for bit.
"""

from __future__ import annotations

import argparse
import json
import re
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydantic import BaseModel

from tests.helpers import REPO, wait_until
from tests.integration.netns import NetnsLab, _ip
from tests.integration.observer import read_rows

PORT = 7447
RELAY_PORTS = {"site1": 7448, "site2": 7449}  # in the depot: each site's router connects to its own relay
STREAMS = ("odom", "scan")
ROBOTS = {"site1": "r1", "site2": "r2"}
PREFIX, UNTOUCHED_PREFIX = "sites", "sitesu"
STALL_MS = 200.0  # a retransmission timeout: what a lost segment costs a TCP stream (Linux's minimum RTO)
# services wait this long for a robot that announced itself and for a silent stream (as in the crash test: on a
# loaded machine a robot's process now and then stalls longer than the 0.1 s default, and two runs of the same data
# would then handle the robots' events in another order)
ORDERING = ("--join-wait-s", "4", "--reorder-window-s", "2")
CENTRAL = ("central", "--association", "shared", "--estimate-rate-hz", "4", *ORDERING)
FAULTS = ("cut", "central", "router")


def partition_wait_s(cut_s: float) -> float:
    """How long central's events wait for a robot that is cut off (``--partition-wait-s``: the cut and 30 s for the
    link to come back and the robot's caches to be recovered), so that they are still handled in stamp order and the
    estimate ends as the untouched copy's (without it central goes on without the cut robot after
    ``--reorder-window-s`` and handles its messages out of order when they come back)."""
    return cut_s + 30.0


@dataclass
class SiteRun:
    """What a run measured."""

    figures: dict = field(default_factory=dict)
    sent: dict[str, dict[str, int]] = field(default_factory=dict)
    received: dict[str, dict[str, list[int]]] = field(default_factory=dict)
    central: dict | None = None  # central's last stats once it took in every message (None: it did not)
    untouched_central: dict | None = None  # the same for the untouched copy's central
    estimates: dict[str, bytes | None] = field(default_factory=dict)  # "faulted" / "untouched": the state reply


def _netem(lab: NetnsLab, host: str, delay_ms: float, jitter_ms: float, loss_pct: float) -> str | None:
    """Delay and loss on both ends of ``host``'s cable; None, or why it could not be done (a kernel without the
    netem queueing discipline, as this machine's: "Specified qdisc kind is unknown")."""
    shape = ["netem", "delay", f"{delay_ms}ms", f"{jitter_ms}ms", "loss", f"{loss_pct}%"]
    try:
        _ip("netns", "exec", lab.switch, "tc", "qdisc", "add", "dev", lab.ports[host], "root", *shape)
        _ip("netns", "exec", lab.ns(host), "tc", "qdisc", "add", "dev", "eth0", "root", *shape)
    except RuntimeError as error:
        return str(error).rsplit(": ", 1)[-1]
    return None


def _cable_bytes(lab: NetnsLab, host: str) -> int:
    """Bytes the cable of ``host`` carried both ways so far (its switch port's counters)."""
    counts = []
    for direction in ("rx_bytes", "tx_bytes"):
        out = subprocess.run(["ip", "netns", "exec", lab.switch, "cat",
                              f"/sys/class/net/{lab.ports[host]}/statistics/{direction}"],
                             capture_output=True, text=True, check=True)
        counts.append(int(out.stdout))
    return sum(counts)


def _samples_since(rows: list[dict], robot: str, since: float) -> int:
    return sum(1 for r in rows if r["kind"] == "sample" and r["robot"] == robot and r["t"] > since)


def _gone_since(rows: list[dict], robot: str, since: float) -> bool:
    return any(r["kind"] == "gone" and r.get("robot") == robot and r["t"] > since for r in rows)


def _first_sample_after(rows: list[dict], robot: str, since: float) -> float | None:
    return next((r["t"] for r in rows if r["kind"] == "sample" and r["robot"] == robot and r["t"] > since), None)


def _central_stats(rows: list[dict]) -> list[dict]:
    return [dict(r["stats"], t=r["t"]) for r in rows if r["kind"] == "stats" and r["key"].endswith("/central/stats")]


def _caught_up(rows: list[dict], total: int, or_missing: bool = False) -> dict | None:
    """Central's last stats when it has handled ``total`` messages and holds none back (with ``or_missing``, also
    when the ones it has not handled are those it counts as lost for good: it will not handle them); else None."""
    stats = _central_stats(rows)
    last = stats[-1] if stats else None
    handled = 0 if last is None else last["extra"].get("processed", 0) + or_missing * last["extra"].get("missing", 0)
    return last if last and handled >= total and last["extra"].get("buffered", 1) == 0 else None


def compare_estimates(faulted: bytes | None, untouched: bytes | None) -> dict:
    """Central's full estimate (a state query's reply) against the untouched copy's: ``equal`` when every field but
    the estimate's number is the same to the last bit (robots' poses, covariances and stamps, every landmark's
    mean, covariance and id, the particle figures); with how far apart they are when not."""
    if faulted is None or untouched is None:
        return {"equal": False, "why": "no estimate from " + ("central" if faulted is None else "the untouched copy")}
    from schemas.codec import decode
    from schemas.messages import Estimate

    a, b = decode(faulted, Estimate), decode(untouched, Estimate)
    differ = sorted(_differences(a, b, "", skip={"seq"}))
    out = {"equal": not differ, "landmarks": [int(a.landmarks.shape[0]), int(b.landmarks.shape[0])]}
    if differ:
        out["fields_differing"] = differ[:12]
        poses_a, poses_b = ({r.robot_id: r.pose for r in e.robots} for e in (a, b))
        out["pose_diff_m"] = {rid: round(float(np.hypot(*(poses_a[rid][:2] - poses_b[rid][:2]))), 6)
                              for rid in sorted(set(poses_a) & set(poses_b))}
        if a.landmarks.shape == b.landmarks.shape:
            out["landmark_diff_m_max"] = round(float(np.abs(a.landmarks - b.landmarks).max(initial=0.0)), 6)
    return out


def _differences(a, b, path: str, skip: set[str] = frozenset()) -> list[str]:
    """The paths at which two decoded messages differ (arrays: dtype, shape or any bit of a value)."""
    if isinstance(a, BaseModel) and type(a) is type(b):
        return [d for name in type(a).model_fields if name not in skip
                for d in _differences(getattr(a, name), getattr(b, name), f"{path}.{name}".lstrip("."))]
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        if len(a) != len(b):
            return [f"{path} (length {len(a)} != {len(b)})"]
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in _differences(x, y, f"{path}[{i}]")]
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        same = (isinstance(a, np.ndarray) and isinstance(b, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape
                and a.tobytes() == b.tobytes())
        return [] if same else [path]
    return [] if a == b else [path]


def robot_argv(rid: str, seed: int, rate_hz: float, duration_s: float) -> list[str]:
    return ["robot", "--id", rid, "--fleet", ",".join(ROBOTS.values()), "--world", "arena", "--seed", str(seed),
            "--rate", str(rate_hz), "--duration", str(duration_s), "--start-delay", "2", "--no-publish-truth"]


def run_sites(lab: NetnsLab, workdir: Path, cut_s: float = 12.0, delay_ms: float = 40.0, jitter_ms: float = 10.0,
              loss_pct: float = 1.0, rate_hz: float = 10.0, settle_s: float = 5.0, seed: int = 0,
              shaping: str = "auto", faults: tuple[str, ...] = FAULTS, untouched: bool = True,
              duration_s: float | None = None) -> SiteRun:
    """Start the three sites (and the untouched copy), apply ``faults`` (see the module doc), let the robots run to
    the end of ``duration_s`` (robot seconds; by default the cut plus 33 s, enough for the faults and ``settle_s``
    after them); return what was measured. ``shaping``: ``auto`` (netem where the kernel has it, else the relay),
    ``netem``, ``relay`` or ``none``. ``seed`` seeds the robots, central and the relays."""
    duration_s = cut_s + 33.0 if duration_s is None else duration_s
    base = {"PATH": "/usr/bin:/bin:/usr/sbin:/sbin", "PYTHONUNBUFFERED": "1", "FLEETSLAM_CONNECT_TIMEOUT_S": "30",
            "FLEETSLAM_ZENOH_CONNECT": f"tcp/127.0.0.1:{PORT}"}
    env = {**base, "FLEETSLAM_PREFIX": PREFIX}
    env_untouched = {**base, "FLEETSLAM_PREFIX": UNTOUCHED_PREFIX}
    python = [sys.executable, "-m", "services.cli"]
    hosts = {name: lab.add_host(name) for name in ("depot", "site1", "site2")}
    run = SiteRun()

    def start(host: str, name: str, *argv: str, environment: dict | None = None) -> subprocess.Popen:
        return lab.start(host, [*python, *argv], environment or env, workdir / f"{name}.log", REPO)

    why_not_netem = None
    if shaping in ("auto", "netem"):
        why_not_netem = _netem(lab, "site1", delay_ms, jitter_ms, loss_pct)
        why_not_netem = why_not_netem or _netem(lab, "site2", delay_ms, jitter_ms, loss_pct)
        if why_not_netem and shaping == "netem":
            raise RuntimeError(f"tc netem: {why_not_netem}")
    used = "none" if shaping == "none" else "relay" if shaping == "relay" or why_not_netem else "netem"
    run.figures["link_shaping"] = used
    run.figures["links"] = {
        "netem": f"tc netem on each site's cable: delay {delay_ms:g} ± {jitter_ms:g} ms, loss {loss_pct:g} %",
        "relay": f"a relay in the depot per site: each chunk held {delay_ms:g} ± {jitter_ms:g} ms each way, "
                 f"{loss_pct:g} % of them stall the stream {STALL_MS:g} ms (a loss under TCP, retransmitted after a "
                 f"timeout)" + (f"; tc netem unavailable: {why_not_netem}" if why_not_netem else ""),
        "none": "not shaped",
    }[used]
    relays: dict[str, subprocess.Popen] = {}
    if used == "relay":
        for index, site in enumerate(ROBOTS, start=1):
            relays[site] = lab.start("depot", [sys.executable, "-m", "tests.integration.linkrelay",
                                               "--listen", f"0.0.0.0:{RELAY_PORTS[site]}", "--to", f"127.0.0.1:{PORT}",
                                               "--delay-ms", str(delay_ms), "--jitter-ms", str(jitter_ms),
                                               "--stall-probability", str(loss_pct / 100), "--stall-ms", str(STALL_MS),
                                               "--seed", str(seed * 100 + index)], base, workdir / f"relay-{site}.log",
                                     REPO)

    def router(host: str) -> subprocess.Popen:
        mesh = [] if host == "depot" else ["--connect", f"tcp/{hosts['depot']}:{RELAY_PORTS[host] if relays else PORT}"]
        return start(host, f"router-{host}", "router", "--listen", f"tcp/0.0.0.0:{PORT}", *mesh)

    routers = {host: router(host) for host in hosts}  # each client waits for its router (connect timeout 30 s)
    observed, observed_untouched = workdir / "observed.jsonl", workdir / "observed-untouched.jsonl"
    copies = [(env, observed, "observer")] + ([(env_untouched, observed_untouched, "observer-untouched")]
                                               if untouched else [])
    for environment, out, name in copies:
        lab.start("depot", [sys.executable, "-m", "tests.integration.observer", "--out", str(out)],
                  {**environment, "FLEETSLAM_SUBSCRIBER_RECOVERY": "true"}, workdir / f"{name}.log", REPO)
    state_dir = workdir / "state" / "central"
    wait_s = partition_wait_s(cut_s)
    run.figures["central_partition_wait_s"] = wait_s
    central_args = (*CENTRAL, "--seed", str(seed), "--partition-wait-s", str(wait_s))
    central_argv = (*central_args, "--state-dir", str(state_dir))
    central = start("depot", "central", *central_argv)
    if untouched:
        start("depot", "central-untouched", *central_args, environment=env_untouched)
    for out, what in ((observed, "central"), (observed_untouched, "the untouched copy's central"))[:1 + untouched]:
        wait_until(lambda: _central_stats(read_rows(out)), 120, 0.1, f"the first stats of {what} (before any robot)")
    robot_processes = {(rid, False): start(site, rid, *robot_argv(rid, seed, rate_hz, duration_s))
                       for site, rid in ROBOTS.items()}  # (robot, of the untouched copy) -> its process
    if untouched:
        robot_processes.update({(rid, True): start("depot", f"{rid}-untouched",
                                                   *robot_argv(rid, seed, rate_hz, duration_s),
                                                   environment=env_untouched) for rid in ROBOTS.values()})

    def heard(rid: str, since: float) -> bool:
        return _first_sample_after(read_rows(observed), rid, since) is not None

    wait_until(lambda: all(heard(rid, 0.0) for rid in ROBOTS.values()), 180, 0.1, "both sites' robots at the depot")
    t0, bytes0 = time.time(), {site: _cable_bytes(lab, site) for site in ROBOTS}
    wait_until(lambda: all(_samples_since(read_rows(observed), rid, t0) >= 5 * 2 * rate_hz for rid in ROBOTS.values()),
               30, 0.1, "5 s of both robots' streams at the depot (the window the cables' bytes are counted over)")
    run.figures["cable_bytes_per_s"] = {site: round((_cable_bytes(lab, site) - bytes0[site]) / (time.time() - t0))
                                        for site in ROBOTS}
    t_kill_central = None
    if "cut" in faults:
        t_cut = time.time()
        lab.cut("site1")
        if "central" in faults:  # half-way through the cut: central killed and started again at once
            wait_until(lambda: time.time() >= t_cut + cut_s / 2, cut_s, 0.05, "the middle of the cut")
            t_kill_central = time.time()
            central.send_signal(signal.SIGKILL)
            central.wait(timeout=10)
            central = start("depot", "central-restarted", *central_argv)
            run.figures["central_killed_after_cut_s"] = round(t_kill_central - t_cut, 2)
        wait_until(lambda: time.time() - t_cut >= cut_s and _gone_since(read_rows(observed), "r1", t_cut), cut_s + 30,
                   0.1, f"the depot to drop site1's robot (lease) and the cut to last {cut_s:g} s")
        t_back = time.time()
        lab.restore("site1")
        wait_until(lambda: heard("r1", t_back), 30, 0.05, "site1's robot at the depot after its cable is back")
        run.figures["cut_s"] = round(t_back - t_cut, 2)
        run.figures["site1_heard_again_s"] = round(_first_sample_after(read_rows(observed), "r1", t_back) - t_back, 2)
        if relays:  # of which the site's router took this long to open its link to the depot again
            opened = [float(t) for t in re.findall(r"^CONNECTION \d+ from \S+ at ([\d.]+)$",
                                                   (workdir / "relay-site1.log").read_text(), re.M)]
            run.figures["site1_link_back_s"] = next((round(t - t_back, 2) for t in opened if t > t_back), None)
    if "router" in faults:
        t_kill = time.time()
        routers["site2"].send_signal(signal.SIGKILL)
        routers["site2"].wait(timeout=10)
        routers["site2"] = router("site2")
        wait_until(lambda: heard("r2", t_kill + 0.5), 40, 0.05, "site2's robot after its router restarted")
        run.figures["site2_heard_again_s"] = round(_first_sample_after(read_rows(observed), "r2", t_kill + 0.5)
                                                   - t_kill, 2)
    t_faults_over = time.time()
    wait_until(lambda: all(_samples_since(read_rows(observed), rid, t_faults_over) >= settle_s * 2 * rate_hz
                           for rid in ROBOTS.values()), settle_s + 30, 0.1,
               f"{settle_s:g} s more of both robots' streams after the faults (robots' --duration too short?)")
    if t_kill_central is not None:
        back = next((s["t"] for s in _central_stats(read_rows(observed))
                     if s["t"] > t_kill_central and s["uptime_s"] < s["t"] - t_kill_central), None)
        run.figures["central_back_s"] = None if back is None else round(back - t_kill_central, 2)
        restarted_log = (workdir / "central-restarted.log").read_text()
        run.figures["central_resumed_from_checkpoint"] = "resumed from" in restarted_log
    for (rid, of_untouched), process in robot_processes.items():  # they end by themselves, at their --duration's end
        process.wait(timeout=duration_s + 120)
        log = (workdir / f"{rid}{'-untouched' if of_untouched else ''}.log").read_text()
        done = re.search(r"done: odom (\d+), scan (\d+)", log)
        counts = dict(zip(STREAMS, map(int, done.groups()))) if done else {}
        (run.figures.setdefault("untouched_sent", {}) if of_untouched else run.sent)[rid] = counts

    def received() -> dict[str, dict[str, list[int]]]:
        rows = read_rows(observed)
        return {rid: {s: [r["seq"] for r in rows if r["kind"] == "sample" and r["robot"] == rid and r["stream"] == s]
                      for s in STREAMS} for rid in ROBOTS.values()}

    def everything_arrived() -> bool:
        got = received()
        return all(len(got[rid][s]) >= n for rid, counts in run.sent.items() for s, n in counts.items())

    total = sum(sum(c.values()) for c in run.sent.values())
    checks = [(everything_arrived, "every message at the depot's receiver"),
              (lambda: _caught_up(read_rows(observed), total, True), "central to handle every message")]
    if untouched:
        checks.append((lambda: _caught_up(read_rows(observed_untouched), total, True),
                       "the untouched copy's central to handle every message"))
    for predicate, what in checks:
        try:
            wait_until(predicate, 60, 0.2, what)
        except AssertionError:
            pass  # the caller judges what arrived
    run.received, run.central = received(), _caught_up(read_rows(observed), total)
    last = (_central_stats(read_rows(observed)) or [{}])[-1].get("extra", {})
    run.figures["central_processed"], run.figures["central_missing"] = last.get("processed"), last.get("missing")
    if untouched:
        run.untouched_central = _caught_up(read_rows(observed_untouched), total)
        states = _query_states(lab, workdir, [PREFIX, UNTOUCHED_PREFIX], base)
        run.estimates = {"faulted": states[PREFIX], "untouched": states[UNTOUCHED_PREFIX]}
        run.figures["central_vs_untouched"] = compare_estimates(run.estimates["faulted"], run.estimates["untouched"])
        run.figures["central_equal_untouched"] = run.figures["central_vs_untouched"]["equal"]
        run.figures["untouched_sent_the_same"] = run.figures["untouched_sent"] == run.sent
    lost = {rid: {s: n - len(set(run.received[rid][s])) for s, n in counts.items()} for rid, counts in run.sent.items()}
    run.figures["lost"] = sum(sum(c.values()) for c in lost.values())
    run.figures["sent"] = total
    if relays:
        run.figures["relay"] = {site: _stop_relay(process, workdir / f"relay-{site}.log")
                                for site, process in relays.items()}
    return run


def _query_states(lab: NetnsLab, workdir: Path, prefixes: list[str], env: dict) -> dict[str, bytes | None]:
    """Central's full estimate under each of ``prefixes`` (its state query's reply, raw), asked from the depot."""
    outs = {prefix: workdir / f"state-{prefix}.bin" for prefix in prefixes}
    argv = [sys.executable, "-m", "tests.integration.sites"]
    for prefix, out in outs.items():
        argv += ["--query-state", f"{prefix}={out}"]
    _finish(lab.start("depot", argv, env, workdir / "query-state.log", REPO), 90.0)
    return {prefix: out.read_bytes() if out.exists() else None for prefix, out in outs.items()}


def _finish(process: subprocess.Popen, timeout_s: float) -> None:
    """Wait for ``process`` to end; killed after ``timeout_s``."""
    try:
        process.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()


def _stop_relay(process: subprocess.Popen, log: Path) -> dict | None:
    """Stop a relay; what it relayed (its ``LINKRELAY`` line: chunks, stalls, delays per direction)."""
    process.send_signal(signal.SIGTERM)
    _finish(process, 10.0)
    lines = [line for line in log.read_text().splitlines() if line.startswith("LINKRELAY ")]
    if not lines:
        return None
    stats = json.loads(lines[-1].split(" ", 1)[1])
    return {"connections": stats["connections"],
            **{name: {k: stats[name][k] for k in ("chunks", "stalls", "delay_ms_mean", "delay_ms_min", "delay_ms_max")}
               for name in ("up", "down")}}


def query_states_main(wanted: list[tuple[str, Path]], timeout_s: float = 60.0) -> int:
    """Ask ``{prefix}/central/state`` of each (prefix, file) until a reply comes (central may be restarting); write
    its payload to the file."""
    from schemas.config import FleetSettings
    from schemas.keys import Keys
    from schemas.transport import session_scope

    pause = threading.Event()  # never set: waits on it pace the queries
    deadline = time.monotonic() + timeout_s
    with session_scope(FleetSettings()) as session:
        for prefix, out in wanted:
            while not out.exists() and time.monotonic() < deadline:
                for reply in session.get(Keys(prefix).central_state, timeout=10.0):
                    if reply.ok is not None:
                        out.write_bytes(reply.ok.payload.to_bytes())
                        break
                else:
                    pause.wait(0.5)  # pacing: no central answered (restarting), ask again
            if not out.exists():
                print(f"no reply on {Keys(prefix).central_state} in {timeout_s:g} s", file=sys.stderr)
    return 0 if all(out.exists() for _, out in wanted) else 1


def main() -> int:
    parser = argparse.ArgumentParser(description="helpers of the multi-site test, run inside its namespaces")
    parser.add_argument("--query-state", action="append", required=True, metavar="PREFIX=FILE",
                        help="write the full estimate of central under PREFIX to FILE (repeatable)")
    args = parser.parse_args()
    return query_states_main([(prefix, Path(out)) for prefix, _, out in
                              (text.partition("=") for text in args.query_state)])


if __name__ == "__main__":
    sys.exit(main())
