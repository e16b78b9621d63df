"""A fleet over three sites in network namespaces, each with its own router, joined by slow and lossy links.

Used by tests/integration/test_multi_site.py (short) and benchmarks/multi_site.py (the issue's 30 s cut, many runs):

- host ``depot``: a router, central FastSLAM and the test's receiver (tests/integration/observer.py, recovering
  what it missed like every service);
- hosts ``site1`` and ``site2``: a router connected to the depot's (``fleetslam router --connect``) and a
  simulated robot, a client of its site's router;
- each site's cable (its veth) delays by ``delay_ms`` ± ``jitter_ms`` and loses ``loss_pct`` % of the packets in
  both directions (``tc netem``).

Faults, in order: site1's cable is unplugged for ``cut_s`` (longer than the 10 s lease: both routers drop the
link), then site2's router is killed (SIGKILL) and started again. The figures: when site1's robot was heard at the
depot again after the cable came back, when site2's after its router restarted, the bytes each site's cable
carried per second, and at the end every message each robot sent against what reached the depot's receiver and
central.
"""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from tests.helpers import REPO, wait_until
from tests.integration.netns import NetnsLab, _ip
from tests.integration.observer import read_rows

PORT = 7447
STREAMS = ("odom", "scan")


@dataclass
class SiteRun:
    """What a run measured."""

    figures: dict = field(default_factory=dict)
    sent: dict[str, dict[str, int]] = field(default_factory=dict)
    received: dict[str, dict[str, list[int]]] = field(default_factory=dict)
    central: dict | None = None


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


def run_sites(lab: NetnsLab, workdir: Path, cut_s: float = 12.0, delay_ms: float = 40.0, jitter_ms: float = 10.0,
              loss_pct: float = 1.0, rate_hz: float = 10.0, settle_s: float = 5.0) -> SiteRun:
    """Start the three sites, apply the faults, stop the robots; return what was measured (see the module doc)."""
    env = {"PATH": "/usr/bin:/bin:/usr/sbin:/sbin", "PYTHONUNBUFFERED": "1", "FLEETSLAM_PREFIX": "sites",
           "FLEETSLAM_ZENOH_CONNECT": f"tcp/127.0.0.1:{PORT}", "FLEETSLAM_CONNECT_TIMEOUT_S": "30"}
    python = [sys.executable, "-m", "services.cli"]
    hosts = {name: lab.add_host(name) for name in ("depot", "site1", "site2")}
    shaped = [_netem(lab, site, delay_ms, jitter_ms, loss_pct) for site in ("site1", "site2")]

    def start(host: str, name: str, *argv: str) -> subprocess.Popen:
        return lab.start(host, [*python, *argv], env, workdir / f"{name}.log", REPO)

    def router(host: str) -> subprocess.Popen:
        mesh = [] if host == "depot" else ["--connect", f"tcp/{hosts['depot']}:{PORT}"]
        return start(host, f"router-{host}", "router", "--listen", f"tcp/0.0.0.0:{PORT}", *mesh)

    routers = {host: router(host) for host in hosts}  # each client waits for its router (connect timeout 30 s)
    observed = workdir / "observed.jsonl"
    lab.start("depot", [sys.executable, "-m", "tests.integration.observer", "--out", str(observed)],
              {**env, "FLEETSLAM_SUBSCRIBER_RECOVERY": "true"}, workdir / "observer.log", REPO)
    start("depot", "central", "central", "--association", "shared")
    robots = {"site1": "r1", "site2": "r2"}
    robot_processes = {site: start(site, rid, "robot", "--id", rid, "--fleet", "r1,r2", "--rate", str(rate_hz),
                                   "--duration", "3600", "--start-delay", "2", "--no-publish-truth")
                       for site, rid in robots.items()}
    run = SiteRun()
    run.figures["links"] = (f"netem delay {delay_ms} ± {jitter_ms} ms, loss {loss_pct} %" if not any(shaped)
                            else f"not shaped: tc netem unavailable ({shaped[0] or shaped[1]})")

    def heard(rid: str, since: float) -> bool:
        return _first_sample_after(read_rows(observed), rid, since) is not None

    wait_until(lambda: all(heard(rid, 0.0) for rid in robots.values()), 180, 0.1, "both sites' robots at the depot")
    t0, bytes0 = time.time(), {site: _cable_bytes(lab, site) for site in robots}
    wait_until(lambda: all(_samples_since(read_rows(observed), rid, t0) >= 5 * 2 * rate_hz for rid in robots.values()),
               30, 0.1, "5 s of both robots' streams at the depot (the window the cables' bytes are counted over)")
    run.figures["cable_bytes_per_s"] = {site: round((_cable_bytes(lab, site) - bytes0[site]) / (time.time() - t0))
                                        for site in robots}
    t_cut = time.time()
    lab.cut("site1")
    wait_until(lambda: time.time() - t_cut >= cut_s and _gone_since(read_rows(observed), "r1", t_cut), cut_s + 30,
               0.1, f"the depot to drop site1's robot (lease) and the cut to last {cut_s:g} s")
    t_back = time.time()
    lab.restore("site1")
    wait_until(lambda: heard("r1", t_back), 30, 0.05, "site1's robot at the depot after its cable is back")
    run.figures["cut_s"] = round(t_back - t_cut, 2)
    run.figures["site1_heard_again_s"] = round(_first_sample_after(read_rows(observed), "r1", t_back) - t_back, 2)
    t_kill = time.time()
    routers["site2"].send_signal(signal.SIGKILL)
    routers["site2"].wait(timeout=10)
    routers["site2"] = router("site2")
    wait_until(lambda: heard("r2", t_kill + 0.5), 40, 0.05, "site2's robot after its router restarted")
    run.figures["site2_heard_again_s"] = round(_first_sample_after(read_rows(observed), "r2", t_kill + 0.5) - t_kill, 2)
    t_back2 = time.time()
    wait_until(lambda: all(_samples_since(read_rows(observed), rid, t_back2) >= settle_s * 2 * rate_hz
                           for rid in robots.values()), settle_s + 30, 0.1,
               f"{settle_s:g} s more of both robots' streams after the faults")
    for site, process in robot_processes.items():
        process.send_signal(signal.SIGTERM)
        process.wait(timeout=30)
        done = re.search(r"done: odom (\d+), scan (\d+)", (workdir / f"{robots[site]}.log").read_text())
        run.sent[robots[site]] = dict(zip(STREAMS, map(int, done.groups()))) if done else {}

    def received() -> dict[str, dict[str, list[int]]]:
        rows = read_rows(observed)
        return {rid: {s: [r["seq"] for r in rows if r["kind"] == "sample" and r["robot"] == rid and r["stream"] == s]
                      for s in STREAMS} for rid in robots.values()}

    def everything_arrived() -> bool:
        got = received()
        return all(len(got[rid][s]) >= n for rid, counts in run.sent.items() for s, n in counts.items())

    def central_caught_up() -> dict | None:
        stats = [r["stats"] for r in read_rows(observed) if r["kind"] == "stats" and r["key"].endswith("/central/stats")]
        totals = {s: sum(c.get(s, 0) for c in run.sent.values()) for s in STREAMS}
        last = stats[-1] if stats else None
        return last if last and all(last["messages_in"].get(s, 0) >= n for s, n in totals.items()) else None

    for predicate, what in ((everything_arrived, "every message at the depot's receiver"),
                            (central_caught_up, "central to take in every message")):
        try:
            wait_until(predicate, 30, 0.2, what)
        except AssertionError:
            pass  # the caller judges what arrived
    run.received, run.central = received(), central_caught_up()
    lost = {rid: {s: n - len(set(run.received[rid][s])) for s, n in counts.items()} for rid, counts in run.sent.items()}
    run.figures["lost"] = sum(sum(c.values()) for c in lost.values())
    run.figures["sent"] = sum(sum(c.values()) for c in run.sent.values())
    return run
