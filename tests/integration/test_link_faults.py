"""No observation lost across a 15 s link cut and a router restart.

The compose fleet's router and three robots run in their own network
namespaces (their commands and environment from docker-compose.yml, which
keeps the defaults: robots publish through advanced publishers whose caches
hold outage_budget_s of their streams, services subscribe with recovery), with the
central service when it is installed. A receiver built on the services' shell
(tests/integration/observer.py, with recovery on) records every sample. Then:

1. robot r1's cable is unplugged at the switch for 15 s: longer than the
   Zenoh lease (10 s), so the router drops r1 (its liveliness token goes) and
   r1's session loses the router. r1 keeps running; when the cable is back it
   reconnects by itself, and the receiver fetches what it missed from r1's cache;
2. the router is killed (SIGKILL) and started again: every client reconnects,
   every receiver recovers.

At the end every stream of every robot has arrived complete, each seq once, in
order: no gap, no duplicate; and the central service's own counters say it took
in every odometry and scan message with no seq missing and none out of order. The figures (lease detection, reconnect time,
router recovery, messages lost) are printed as JSON (run with ``-s`` to see them).
"""

from __future__ import annotations

import json
import re
import signal
import time

import pytest

from tests.helpers import wait_until
from tests.integration.compose import ComposeFleet, compose_config
from tests.integration.observer import read_rows

pytestmark = pytest.mark.integration

CUT_S = 15.0
STREAMS = ("odom", "scan", "truth")


def _seqs(rows: list[dict], robot: str, stream: str, since: float = 0.0) -> list[int]:
    return [r["seq"] for r in rows if r["kind"] == "sample" and r["robot"] == robot and r["stream"] == stream
            and r["t"] >= since]


def _complete_so_far(rows: list[dict], robot: str, since: float) -> bool:
    """Every stream of ``robot`` is gap-free from seq 0 and has grown since ``since``."""
    for stream in STREAMS:
        seqs = _seqs(rows, robot, stream)
        if not seqs or seqs != list(range(len(seqs))) or not _seqs(rows, robot, stream, since):
            return False
    return True


def _summary(rows: list[dict], robots) -> str:
    """Per robot and stream: messages received, and the first place its seqs stop being 0, 1, 2, ..."""
    parts = []
    for robot in robots:
        for stream in STREAMS:
            seqs = _seqs(rows, robot, stream)
            broken = next((i for i, seq in enumerate(seqs) if seq != i), None)
            parts.append(f"{robot}/{stream}: {len(seqs)}" + ("" if broken is None else f" (seq {seqs[broken]} at {broken})"))
    return ", ".join(parts)


def _first(rows: list[dict], kind: str, robot: str, since: float) -> float | None:
    return next((r["t"] for r in rows if r["kind"] == kind and r.get("robot") == robot and r["t"] >= since), None)


def test_no_observation_lost_across_a_15s_link_cut_and_a_router_restart(compose_bin, netns_lab, tmp_path):
    project = compose_config(compose_bin)
    fleet = ComposeFleet(netns_lab, project, tmp_path)
    robots = [n for n, s in project["services"].items() if s["command"] == ["robot"]]
    rids = {name: fleet.service(name)["environment"]["FLEETSLAM_ROBOT_ID"] for name in robots}
    receivers = ["central"]
    # real-time robots that outlive the faults; the test stops them
    running = {"FLEETSLAM_DURATION": "600", "FLEETSLAM_SPEEDUP": "1", "FLEETSLAM_START_DELAY": "0.5"}
    observed = fleet.start_fleet(receivers, robots, running)
    cut_name = robots[0]
    cut = rids[cut_name]
    figures: dict[str, float | int | str] = {"cut_s": CUT_S, "cut_robot": cut}

    def alive_processes() -> None:
        for name, process in fleet.processes.items():
            assert process.poll() is None, f"{name} exited with {process.returncode}: {fleet.log(name)[-1500:]}"

    def all_flowing(since: float) -> bool:
        alive_processes()
        rows = read_rows(observed)
        return all(_complete_so_far(rows, rid, since) for rid in rids.values())

    def wait(predicate, timeout: float, what: str) -> None:
        try:
            wait_until(predicate, timeout, 0.1, what)
        except AssertionError as error:
            raise AssertionError(f"{error}; the receiver holds {_summary(read_rows(observed), rids.values())}") from None

    wait(lambda: all_flowing(0.0), 60, "every robot's streams at the receiver")

    # 1. unplug r1 for 15 s
    t_cut = time.time()
    netns_lab.cut(cut_name)
    wait(lambda: _first(read_rows(observed), "gone", cut, t_cut), CUT_S, f"the router to drop {cut}")
    figures["lease_detection_s"] = round(_first(read_rows(observed), "gone", cut, t_cut) - t_cut, 2)
    time.sleep(max(0.0, t_cut + CUT_S - time.time()))  # the cut lasts its full 15 s, whatever happens meanwhile
    t_restore = time.time()
    netns_lab.restore(cut_name)
    wait(lambda: _first(read_rows(observed), "alive", cut, t_restore), 20, f"{cut} to reconnect by itself")
    figures["reconnect_s"] = round(_first(read_rows(observed), "alive", cut, t_restore) - t_restore, 2)
    wait(lambda: all_flowing(t_restore), 30, f"{cut}'s missed observations to be recovered")
    figures["link_recovered_s"] = round(time.time() - t_restore, 2)

    # 2. kill the router and start it again
    t_kill = time.time()
    router = fleet.processes["router"]
    router.send_signal(signal.SIGKILL)
    router.wait(timeout=10)
    fleet.start("router")
    figures["router_restart_s"] = round(fleet.wait_healthy("router", 20) - t_kill, 2)
    wait(lambda: all_flowing(t_kill), 40, "every stream after the router restart")
    figures["router_recovered_s"] = round(time.time() - t_kill, 2)

    # stop the robots; each says how many messages it sent; the receiver must hold them all, once, in order
    sent: dict[str, dict[str, int]] = {}
    for name in robots:
        process = fleet.processes.pop(name)
        assert process.poll() is None, f"{name} died: {fleet.log(name)[-1500:]}"
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=15) == 0, fleet.log(name)[-1500:]
        done = re.search(r"done: odom (\d+), scan (\d+), truth (\d+)", fleet.log(name))
        assert done, fleet.log(name)[-1500:]
        sent[rids[name]] = dict(zip(STREAMS, map(int, done.groups())))

    def everything_arrived() -> bool:
        rows = read_rows(observed)
        return all(len(_seqs(rows, rid, s)) >= n for rid, counts in sent.items() for s, n in counts.items())

    try:
        wait(everything_arrived, 15, "every message the robots sent")
    finally:
        rows = read_rows(observed)
        lost = {rid: {s: n - len(set(_seqs(rows, rid, s))) for s, n in counts.items()} for rid, counts in sent.items()}
        figures["sent"] = sum(sum(c.values()) for c in sent.values())
        figures["lost"] = sum(sum(c.values()) for c in lost.values())
        print("LINK-FAULT RECEIVER " + json.dumps(figures))
    for rid, counts in sent.items():
        for stream, n in counts.items():
            assert _seqs(rows, rid, stream) == list(range(n)), f"{rid}/{stream}: not every seq once and in order"
    assert figures["lost"] == 0
    for name in receivers:  # the service's own counters: everything in, nothing missing, nothing out of order
        totals = {stream: sum(c[stream] for c in sent.values()) for stream in ("odom", "scan")}

        def caught_up() -> dict | None:
            stats = [r["stats"] for r in read_rows(observed) if r["kind"] == "stats" and r["key"].endswith(f"/{name}/stats")]
            last = stats[-1] if stats else None
            done = last and all(last["messages_in"].get(s, 0) >= n for s, n in totals.items()) and not last["queue_depth"]
            return last if done else None

        wait(caught_up, 60, f"{name} to take in the {totals} messages sent")
        last = caught_up()
        assert last["extra"].get("missing") == 0, last
        assert not {"duplicate", "out_of_order", "time_backwards"} & set(last["rejected"]), last["rejected"]
        figures[f"{name}_messages_in"] = sum(last["messages_in"].get(s, 0) for s in totals)
    print("LINK-FAULT FIGURES " + json.dumps(figures))
