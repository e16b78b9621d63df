"""docker-compose.yml without a Docker engine: a real Compose v2 to read it, and
its services started as local processes, each in its own network namespace.

:func:`compose_binary` finds the ``docker-compose`` executable that
``make test`` fetched into ``.venv`` (``deploy/fetch_compose.py``; fetched here
when missing). :func:`compose_config` asks it for the resolved project as JSON
(profiles, ``.env``, YAML anchors and interpolation applied by Compose itself).
:class:`ComposeFleet` starts a service's command (the image's entrypoint is
``fleetslam``) with exactly the service's environment, in a namespace named
after the service, so ``tcp/router:7447`` resolves as on a compose network;
volume, secret and config targets (``/reports``, ``/state``, ``/secrets``, ``/data``, ``/run/secrets/...``)
are mapped to local files and folders (a named volume to the folder of its name in the work folder).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from robots.loaders import data_root
from services.healthcheck import check, endpoint_ports
from tests.helpers import REPO, wait_until
from tests.integration.netns import NetnsLab

FETCH = REPO / "deploy" / "fetch_compose.py"
PLUGIN_DIR = REPO / ".venv" / "docker" / "cli-plugins"


def compose_binary() -> tuple[Path | None, str]:
    """(the docker-compose binary, "") or (None, why it cannot be had)."""
    binary = PLUGIN_DIR / "docker-compose"
    if binary.exists():
        return binary, ""
    result = subprocess.run([sys.executable, str(FETCH), "--dest", str(PLUGIN_DIR)], capture_output=True, text=True,
                            timeout=300)
    if result.returncode == 0:
        return Path(result.stdout.strip()), ""
    return None, result.stderr.strip() or f"{FETCH.name} exited with {result.returncode}"


def compose_command(binary: Path) -> tuple[list[str], dict[str, str]]:
    """``docker compose`` through the docker CLI when it is installed (the plugin is found through
    DOCKER_CONFIG), else the standalone binary; with the environment to run it in."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("FLEETSLAM_", "COMPOSE_"))}
    docker = shutil.which("docker")
    if docker:
        return [docker, "compose"], {**env, "DOCKER_CONFIG": str(binary.parent.parent)}
    return [str(binary)], env


def run_compose(binary: Path, *words: str, files: tuple[str, ...] = ("docker-compose.yml",)) -> subprocess.CompletedProcess:
    command, env = compose_command(binary)
    args = [*command, "--project-directory", str(REPO)]
    for name in files:
        args += ["-f", str(REPO / name)]
    return subprocess.run([*args, *words], capture_output=True, text=True, env=env, cwd=REPO, timeout=60)


def compose_config(binary: Path, *words: str, files: tuple[str, ...] = ("docker-compose.yml",)) -> dict:
    """The project as Compose resolves it (``docker compose config --format json``)."""
    result = run_compose(binary, *words, "config", "--format", "json", files=files)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)



class ComposeFleet:
    """Starts services of a resolved compose project as processes in namespaces of one lab."""

    def __init__(self, lab: NetnsLab, project: dict, workdir: Path):
        self.lab = lab
        self.project = project
        self.workdir = workdir
        self.mounts: dict[str, Path] = {"/data": data_root() or workdir / "no-data"}
        for service in project["services"].values():  # a named volume is a folder of its name, shared by its mounts
            for volume in service.get("volumes") or []:
                if volume["type"] == "volume":
                    self.mounts[volume["target"]] = workdir / volume["source"]
        self.processes: dict[str, subprocess.Popen] = {}
        self.base_env = {k: v for k, v in os.environ.items() if not k.startswith("FLEETSLAM_")}
        self.base_env["PYTHONUNBUFFERED"] = "1"

    def mount_secrets(self, folder: Path) -> None:
        """Map every secret's target (``/run/secrets/NAME``) to the file of the same name in ``folder``."""
        for service in self.project["services"].values():
            for secret in service.get("secrets") or []:
                self.mounts[secret["target"]] = folder / Path(self.project["secrets"][secret["source"]]["file"]).name

    def service(self, name: str) -> dict:
        return self.project["services"][name]

    def command(self, name: str) -> str:
        return self.service(name)["command"][0]

    def _local(self, value: str) -> str:
        for target, local in self.mounts.items():
            if value == target or value.startswith(target + "/"):
                return str(local) + value[len(target):]
        return value

    def env(self, name: str, overrides: dict[str, str] | None = None) -> dict[str, str]:
        service_env = {k: self._local(str(v)) for k, v in (self.service(name).get("environment") or {}).items()}
        return {**self.base_env, **service_env, **(overrides or {})}

    def add_hosts(self, names: list[str]) -> None:
        for name in names:
            if name not in self.lab.hosts:
                self.lab.add_host(name)

    def start(self, name: str, overrides: dict[str, str] | None = None) -> subprocess.Popen:
        """``fleetslam COMMAND...`` in the service's namespace, with the service's environment."""
        self.mounts["/reports"].mkdir(parents=True, exist_ok=True)
        argv = [sys.executable, "-m", "services.cli", *(self._local(w) for w in self.service(name)["command"])]
        process = self.lab.start(name, argv, self.env(name, overrides), self.workdir / f"{name}.log", REPO)
        self.processes[name] = process
        return process

    def start_fleet(self, services: list[str], robots: list[str], robot_env: dict[str, str]) -> Path:
        """The router first, until healthy (compose's ``depends_on: service_healthy``), then the test's
        receiver (host "observer"), the services and the robots (with ``robot_env`` over their environment).
        Returns the receiver's file."""
        self.add_hosts(["router", *robots, *services, "observer"])
        self.start("router")
        self.wait_healthy("router", 20)
        observed = self.start_observer("observer", like="monitor")
        for name in services:
            self.start(name)
        for name in robots:
            self.start(name, robot_env)
        return observed

    def start_observer(self, host: str, like: str) -> Path:
        """The test's own receiver (tests/integration/observer.py) in ``host``, a client configured like
        service ``like`` with subscriber recovery on; returns the file it writes."""
        out = self.workdir / f"{host}.jsonl"
        env = self.env(like, {"FLEETSLAM_SUBSCRIBER_RECOVERY": "true"})
        self.processes[host] = self.lab.start(host, [sys.executable, "-m", "tests.integration.observer", "--out", str(out)],
                                              env, self.workdir / f"{host}.log", REPO)
        return out

    def healthcheck(self, name: str, overrides: dict[str, str] | None = None) -> subprocess.Popen:
        """Start the service's compose healthcheck in its namespace, as Docker would run it in its container."""
        test = self.service(name)["healthcheck"]["test"]
        assert test[0] == "CMD" and test[1] == "python", test
        return subprocess.Popen(self.lab.command(name, [sys.executable, *test[2:]]), env=self.env(name, overrides),
                                cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)

    def unhealthy(self, services: dict[str, dict[str, str] | None]) -> dict[str, str]:
        """Run the healthchecks of ``services`` (name -> environment overrides) at once; the failing ones and why."""
        checks = {name: self.healthcheck(name, overrides) for name, overrides in services.items()}
        failing = {}
        for name, process in checks.items():
            _, err = process.communicate(timeout=30)
            if process.returncode != 0:
                failing[name] = err.strip()
        return failing

    def wait_healthy(self, name: str, timeout: float) -> float:
        """Wait until the service's own socket table says what its healthcheck tests (read from the host
        through /proc/PID/net, costing no process per poll), then run the real healthcheck once.
        Returns the wall time at which it came up."""
        role = self.service(name)["healthcheck"]["test"][-1]
        env = self.env(name)
        ports = endpoint_ports(env["FLEETSLAM_LISTEN"] if role == "router" else env["FLEETSLAM_ZENOH_CONNECT"])
        process = self.processes[name]
        tables = (Path(f"/proc/{process.pid}/net/tcp"), Path(f"/proc/{process.pid}/net/tcp6"))

        def up() -> bool:
            if process.poll() is not None:
                raise AssertionError(f"{name} exited with {process.returncode}: {self.log(name)[-1500:]}")
            return check(role, tables, ports) is None

        wait_until(up, timeout, 0.05, f"{name}'s healthcheck")
        came_up = time.time()
        assert not self.unhealthy({name: None}), f"{name}'s compose healthcheck fails"
        return came_up

    def log(self, name: str) -> str:
        path = self.workdir / f"{name}.log"
        return path.read_text() if path.exists() else ""
