"""The secured router: user/password (or client certificate) authentication and access control.

The router runs with a config made by deploy/make_router_config.py (the one
docker-compose.secure.yml mounts, made for this test's prefix): a robot may
write only under ``{prefix}/robots/{its id}/**``, a service only under its own
keys, and a client without valid credentials is refused at the handshake.
The compose wiring (users, password files as secrets, the router's config and
user dictionary) is read back from Compose's own resolution of the overlay.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import threading
from dataclasses import dataclass
from pathlib import Path

import pytest
import zenoh

from schemas.config import FleetSettings
from schemas.transport import ConnectError, open_session
from tests.helpers import REPO, Collector, Processes, free_port, wait_for_port, wait_until
from tests.integration.compose import compose_config

pytestmark = pytest.mark.integration

MAKE_CONFIG = REPO / "deploy" / "make_router_config.py"
MAKE_CERTS = REPO / "deploy" / "make-certs.sh"
SECURE = ("docker-compose.yml", "docker-compose.secure.yml")


def read_json5(path: Path) -> dict:
    """Our generated JSON5 is JSON with ``//`` comment lines and trailing commas."""
    text = "\n".join(line for line in path.read_text().splitlines() if not line.lstrip().startswith("//"))
    return json.loads(re.sub(r",(\s*[\]}])", r"\1", text))


@dataclass
class SecuredRouter:
    endpoint: str
    prefix: str
    secrets: Path

    def settings(self, user: str | None, password: str | None = None, timeout: float = 1.0, **extra) -> FleetSettings:
        if user is not None and password is None:
            password = (self.secrets / f"{user}.password").read_text().strip()
        return FleetSettings(zenoh_connect=self.endpoint, prefix=self.prefix, connect_timeout_s=timeout,
                             zenoh_user=user, zenoh_password=password, **extra)

    def session(self, user: str | None, password: str | None = None, **extra) -> zenoh.Session:
        return open_session(self.settings(user, password, **extra))

    def env(self, user: str | None) -> dict[str, str]:
        """A client process's environment, credentials as compose wires them (user + password file)."""
        env = {"FLEETSLAM_ZENOH_CONNECT": self.endpoint, "FLEETSLAM_PREFIX": self.prefix,
               "FLEETSLAM_CONNECT_TIMEOUT_S": "1"}
        if user:
            env.update(FLEETSLAM_ZENOH_USER=user, FLEETSLAM_ZENOH_PASSWORD_FILE=str(self.secrets / f"{user}.password"))
        return env


def _start_router(processes: Processes, folder: Path, scheme: str, *config_args: str) -> tuple[str, str]:
    port = free_port()
    prefix = f"s{port}"
    endpoint = f"{scheme}/127.0.0.1:{port}"
    config = folder / f"router-{port}.json5"
    subprocess.run([sys.executable, str(MAKE_CONFIG), "--prefix", prefix, "--robots", "r1,r2",
                    "--services", "central,monitor", "--out", str(config), *config_args], check=True)
    processes.start(f"router-{port}", "router", "--listen", endpoint, "--router-config", str(config))
    wait_for_port(port)
    return endpoint, prefix


@pytest.fixture(scope="module")
def secured(tmp_path_factory) -> SecuredRouter:
    """One password-and-ACL router for the tests of this module."""
    folder = tmp_path_factory.mktemp("secured")
    processes = Processes(folder, {**os.environ, "PYTHONUNBUFFERED": "1"})
    secrets = folder / "secrets"
    try:
        endpoint, prefix = _start_router(processes, folder, "tcp", "--secrets", str(secrets),
                                         "--users-file", str(secrets / "users.txt"))
        yield SecuredRouter(endpoint, prefix, secrets)
    finally:
        processes.stop_all()


def test_a_robot_cannot_write_into_another_robots_keys(secured, processes):
    watcher = secured.session("monitor")
    seen = Collector(watcher, f"{secured.prefix}/**")
    tokens: list[str] = []
    watcher.liveliness().declare_subscriber(f"{secured.prefix}/robots/*/alive",
                                            lambda s: tokens.append(str(s.key_expr)), history=True)
    robot = ("robot", "--rate", "10", "--duration", "2", "--speedup", "4", "--start-delay", "0.3")
    honest = processes.start("r1", *robot, "--id", "r1", env=secured.env("r1"))
    forger = processes.start("r1-as-r2", *robot, "--id", "r2", env=secured.env("r1"))  # r1's credentials, r2's keys
    for process in (honest, forger):
        assert process.wait(timeout=30) == 0, processes.log("r1")[-1000:] + processes.log("r1-as-r2")[-1000:]
    own = f"{secured.prefix}/robots/r1/"
    wait_until(lambda: seen.count(lambda k: k == own + "scan") >= 20, 10, what="the honest robot's scans")
    assert seen.count(lambda k: k.startswith(f"{secured.prefix}/robots/r2/")) == 0
    assert f"{secured.prefix}/robots/r2/alive" not in tokens and f"{secured.prefix}/robots/r1/alive" in tokens
    # a robot may not write where a service writes, a service may not write as a robot
    r1, central = secured.session("r1"), secured.session("central")
    r1.put(f"{secured.prefix}/central/estimate", b"forged")
    central.put(f"{secured.prefix}/robots/r1/odom", b"forged")
    central.put(f"{secured.prefix}/central/estimate", b"fine")
    wait_until(lambda: seen.count(lambda k: k.endswith("/central/estimate")) >= 1, 5, what="the central estimate")
    assert not any(payload == b"forged" for _, payload in seen.snapshot())
    for session in (r1, central, watcher):
        session.close()


def test_a_client_without_or_with_wrong_credentials_is_refused(secured, processes):
    anonymous = processes.start("anonymous", "robot", "--id", "r1", env=secured.env(None))
    assert anonymous.wait(timeout=20) == 2
    assert "could not reach the zenoh router" in processes.log("anonymous")
    for user, password in (("r1", "wrong"), ("intruder", "secret"), (None, None)):
        with pytest.raises(ConnectError):
            secured.session(user, password)
    secured.session("r1").close()  # the right password is let in


def test_mutual_tls_admits_only_certificates_of_the_ca_and_applies_the_acl_to_their_common_names(processes, tmp_path):
    if shutil.which("openssl") is None or shutil.which("sh") is None:
        pytest.skip("openssl is not installed")
    tls = tmp_path / "tls"
    subprocess.run(["sh", str(MAKE_CERTS), str(tls), "localhost,127.0.0.1", "r1 monitor"], check=True,
                   capture_output=True)
    endpoint, prefix = _start_router(processes, tmp_path, "tls", "--auth", "certificate", "--tls-dir", str(tls))

    foreign = tmp_path / "foreign"  # another CA's certificate for the same name
    subprocess.run(["sh", str(MAKE_CERTS), str(foreign), "localhost", "r1"], check=True, capture_output=True)

    def session(user: str | None, folder: Path = tls, timeout: float = 3.0) -> zenoh.Session:
        extra = {"tls_root_ca": str(tls / "ca.pem")}
        if user:
            extra.update(tls_cert=str(folder / f"{user}.pem"), tls_key=str(folder / f"{user}-key.pem"))
        return open_session(FleetSettings(zenoh_connect=endpoint, prefix=prefix, connect_timeout_s=timeout, **extra))

    for user, folder in ((None, tls), ("r1", foreign)):
        with pytest.raises(ConnectError):
            session(user, folder, timeout=1.5)
    watcher = session("monitor")
    got = threading.Event()
    keys: list[str] = []
    watcher.declare_subscriber(f"{prefix}/**", lambda s: (keys.append(str(s.key_expr)), got.set()))
    r1 = session("r1")
    wait_until(lambda: (r1.put(f"{prefix}/robots/r1/odom", b"x"), got.is_set())[1], 10, 0.2, "r1's sample over TLS")
    r1.put(f"{prefix}/robots/r2/odom", b"forged")
    r1.put(f"{prefix}/robots/r1/scan", b"x")
    wait_until(lambda: f"{prefix}/robots/r1/scan" in keys, 5, what="r1's scan")
    assert f"{prefix}/robots/r2/odom" not in keys
    for s in (r1, watcher):
        s.close()


def test_compose_wires_every_client_credentials_from_secret_files(compose_bin):
    secrets_dir = REPO / "deploy" / "secrets"
    variants = [((), SECURE, "router-acl.json5"), (("--profile", "mrclam"), SECURE, "router-acl.json5"),
                ((), (*SECURE, "docker-compose.tls.yml"), "router-acl-tls.json5")]
    for profile, files, acl_name in variants:
        project = compose_config(compose_bin, *profile, files=files)
        services, secrets, configs = project["services"], project["secrets"], project["configs"]

        def secret_file(service: dict, target: str) -> Path:
            mounted = next(s for s in service["secrets"] if s["target"] == target)
            return Path(secrets[mounted["source"]]["file"])

        router = services["router"]
        config_target = router["environment"]["FLEETSLAM_ROUTER_CONFIG"]
        mounted = next(c for c in router["configs"] if c["target"] == config_target)
        acl_path = REPO / "deploy" / acl_name
        assert Path(configs[mounted["source"]]["file"]) == acl_path
        acl = read_json5(acl_path)
        assert secret_file(router, acl["transport"]["auth"]["usrpwd"]["dictionary_file"]) == secrets_dir / "users.txt"
        tls = acl["transport"].get("link", {}).get("tls")
        if tls:
            assert router["environment"]["FLEETSLAM_LISTEN"].startswith("tls/")
            assert secret_file(router, tls["listen_certificate"]) == secrets_dir / "tls" / "router.pem"
            assert secret_file(router, tls["listen_private_key"]) == secrets_dir / "tls" / "router-key.pem"
            assert secret_file(router, tls["root_ca_certificate"]) == secrets_dir / "tls" / "ca.pem"
        users = {u for subject in acl["access_control"]["subjects"] for u in subject["usernames"]}
        for name, service in services.items():
            if name == "router":
                continue
            env = service["environment"]
            user = env["FLEETSLAM_ZENOH_USER"]
            assert user in users, f"{name} logs in as {user}, unknown to the router's ACL"
            assert secret_file(service, env["FLEETSLAM_ZENOH_PASSWORD_FILE"]) == secrets_dir / f"{user}.password"
            assert "FLEETSLAM_ZENOH_PASSWORD" not in env, f"{name}: a password in the environment, not in a secret"
            if tls:
                assert env["FLEETSLAM_ZENOH_CONNECT"].startswith("tls/")
                assert secret_file(service, env["FLEETSLAM_TLS_CERT"]) == secrets_dir / "tls" / f"{user}.pem"
                assert secret_file(service, env["FLEETSLAM_TLS_KEY"]) == secrets_dir / "tls" / f"{user}-key.pem"
                assert secret_file(service, env["FLEETSLAM_TLS_ROOT_CA"]) == secrets_dir / "tls" / "ca.pem"
            if service["command"] == ["robot"]:
                replay = env.get("FLEETSLAM_REPLAY")
                robot_id = env.get("FLEETSLAM_ROBOT_ID") or f"r{replay.rpartition(':')[2]}"
                assert user == robot_id, f"{name} publishes as {robot_id} but logs in as {user}"


@pytest.mark.parametrize("name, args", [("router-acl.json5", []),
                                         ("router-acl-tls.json5", ["--auth", "both", "--tls-dir", "/run/secrets/tls"])])
def test_the_committed_router_configs_are_what_the_generator_makes(tmp_path, name, args):
    fresh = tmp_path / name
    subprocess.run([sys.executable, str(MAKE_CONFIG), *args, "--out", str(fresh)], check=True)
    assert fresh.read_text() == (REPO / "deploy" / name).read_text(), \
        f"deploy/{name} is stale: run python deploy/make_router_config.py {' '.join(args)} --out deploy/{name}"
