"""The secured router: user/password (and certificate) authentication and access control.

The router runs as ``docker compose up`` and ``fleetslam demo`` run it
(``fleetslam router --secrets-dir DIR``: the passwords and the access control
of services/credentials.py made in DIR, for this test's prefix): a robot may
write only under ``{prefix}/robots/{its id}/**``, only the user ``world`` the
world map, a service only under its own keys, and a client without valid
credentials is refused at the handshake. With mutual TLS a client needs the
password and a certificate of its own name; zenoh admits a client whose
certificate names another user, and the access control lets it do nothing.
The compose wiring (users, password files on the volume "secrets", the
router's secrets folder and certificates) is read back from Compose's own
resolution of the files.
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

from schemas.config import FleetSettings, RouterSettings
from schemas.transport import ConnectError, open_session
from services.credentials import (DEFAULT_ROBOTS, DEFAULT_SERVICES, ROUTER_USER, WORLD_USER, parse_robots, parse_services,
                                  secure_folder)
from tests.helpers import REPO, Collector, Processes, free_port, put_until_seen, wait_for_port, wait_until
from tests.integration.compose import compose_config

pytestmark = pytest.mark.integration

MAKE_CONFIG = REPO / "deploy" / "make_router_config.py"
MAKE_CERTS = REPO / "deploy" / "make-certs.sh"
VARIANTS = {"default": ((), ("docker-compose.yml",)), "mrclam": (("--profile", "mrclam"), ("docker-compose.yml",)),
            "tls": ((), ("docker-compose.yml", "docker-compose.tls.yml")),
            "tls-mrclam": (("--profile", "mrclam"), ("docker-compose.yml", "docker-compose.tls.yml"))}


def read_json5(path: Path) -> dict:
    """Our generated JSON5 is JSON with ``//`` comment lines and trailing commas."""
    text = "\n".join(line for line in path.read_text().splitlines() if not line.lstrip().startswith("//"))
    return json.loads(re.sub(r",(\s*[\]}])", r"\1", text))


@dataclass
class SecuredRouter:
    endpoint: str
    prefix: str
    secrets: Path
    tls: Path | None = None

    def settings(self, user: str | None, password: str | None = None, timeout: float = 1.0,
                 cert: str | None = None) -> FleetSettings:
        """A client's settings: ``user``'s password (from the secrets folder unless given); with TLS the
        certificate of ``cert`` (default: the user's own)."""
        if user is not None and password is None:
            password = (self.secrets / f"{user}.password").read_text().strip()
        extra = {}
        if self.tls is not None:
            extra["tls_root_ca"] = str(self.tls / "ca.pem")
            if cert or user:
                extra.update(tls_cert=str(self.tls / f"{cert or user}.pem"), tls_key=str(self.tls / f"{cert or user}-key.pem"))
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


def _start_router(processes: Processes, scheme: str, *router_args: str, port: int | None = None) -> tuple[str, str, int]:
    """``fleetslam router`` on ``port`` (default: a free one) with the prefix ``s{port}``; (endpoint, prefix, port)."""
    port = port or free_port()
    prefix = f"s{port}"
    endpoint = f"{scheme}/127.0.0.1:{port}"
    processes.start(f"router-{port}", "router", "--listen", endpoint, "--prefix", prefix, *router_args)
    wait_for_port(port)
    return endpoint, prefix, port


def _secured_router(processes: Processes, folder: Path, scheme: str = "tcp", *extra: str) -> SecuredRouter:
    secrets = folder / "secrets"
    endpoint, prefix, _ = _start_router(processes, scheme, "--secrets-dir", str(secrets), "--robot-users", "r1,r2",
                                        "--service-users", "central,monitor", *extra)
    return SecuredRouter(endpoint, prefix, secrets)


def _refused(settings: FleetSettings) -> bool:
    """Whether the router refuses a session of ``settings`` (one it admits is closed at once)."""
    try:
        open_session(settings).close()
    except ConnectError:
        return True
    return False


def _replies(session: zenoh.Session, key: str, timeout: float = 1.5) -> list[bytes]:
    """Every successful reply to a query on ``key`` (the query ends at ``timeout``)."""
    return [r.ok.payload.to_bytes() for r in session.get(key, timeout=timeout) if r.ok is not None]


@pytest.fixture
def keep():
    """``keep(session)``: closed at the test's end, also when it fails (a session with callbacks left open hangs
    the interpreter's exit)."""
    opened: list[zenoh.Session] = []

    def keep_session(session: zenoh.Session) -> zenoh.Session:
        opened.append(session)
        return session

    yield keep_session
    for session in reversed(opened):
        session.close()


@pytest.fixture(scope="module")
def secured(tmp_path_factory) -> SecuredRouter:
    """One password-and-ACL router, as compose and the demo run it, for the tests of this module."""
    folder = tmp_path_factory.mktemp("secured")
    processes = Processes(folder, {**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        yield _secured_router(processes, folder)
    finally:
        processes.stop_all()


def test_a_robot_cannot_write_into_another_robots_keys(secured, processes, keep):
    watcher = keep(secured.session("monitor"))
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
    r1, central = keep(secured.session("r1")), keep(secured.session("central"))
    put_until_seen(r1, own + "odom", b"route", seen)  # both routes known before anything is forged
    put_until_seen(central, f"{secured.prefix}/central/estimate", b"fine", seen)
    r1.put(f"{secured.prefix}/central/estimate", b"forged")
    central.put(f"{secured.prefix}/robots/r1/odom", b"forged")
    put_until_seen(central, f"{secured.prefix}/central/estimate", b"fine again", seen)
    assert not any(payload == b"forged" for _, payload in seen.snapshot())


def test_a_robot_reads_the_estimates_of_itself_but_not_the_other_robots_streams(secured, keep):
    """What RobotLink.estimates() follows is open to a robot (the central estimate, its own D-SLAM pose); another
    robot's odometry and another robot's D-SLAM pose are not."""
    p = secured.prefix
    r1, r2, central, monitor = (keep(secured.session(user)) for user in ("r1", "r2", "central", "monitor"))
    estimate, own_pose = Collector(r1, f"{p}/central/estimate"), Collector(r1, f"{p}/dslam/pose/r1")
    others = Collector(r1, f"{p}/robots/r2/odom")
    other_pose = Collector(r1, f"{p}/dslam/pose/r2")
    seen = Collector(monitor, f"{p}/**")
    put_until_seen(central, f"{p}/central/estimate", b"fused", estimate)
    put_until_seen(r2, f"{p}/robots/r2/odom", b"r2 moves", seen)
    with open_session(secured.settings("r1")) as writer:  # r1 itself may not write a pose: only services do
        writer.put(f"{p}/dslam/pose/r1", b"self-made")
    put_until_seen(central, f"{p}/central/estimate", b"fused again", estimate)
    assert others.count() == 0 and other_pose.count() == 0
    assert (f"{p}/dslam/pose/r1", b"self-made") not in own_pose.snapshot() + seen.snapshot()


def test_only_the_world_user_writes_or_answers_the_world_map(secured, keep):
    """A robot (which used to publish it) can neither put the true map nor answer queries for it: it cannot move
    MCL's robots or the evaluator's map score. The user ``world`` can, and only there."""
    truth = f"{secured.prefix}/world/truth"
    watcher, r1, world = (keep(secured.session(user)) for user in ("monitor", "r1", WORLD_USER))
    seen = Collector(watcher, f"{secured.prefix}/**")
    forged_answer = r1.declare_queryable(truth, lambda query: query.reply(truth, b"forged"))
    put_until_seen(r1, f"{secured.prefix}/robots/r1/odom", b"route", seen)  # both routes known before forging
    put_until_seen(world, truth, b"true map", seen)
    r1.put(truth, b"forged")
    world.put(f"{secured.prefix}/robots/r1/odom", b"forged")  # nor may the world user write as a robot
    put_until_seen(world, truth, b"true map again", seen)
    assert {p for k, p in seen.snapshot()} == {b"route", b"true map", b"true map again"}
    assert _replies(watcher, truth) == []  # r1's queryable is never asked
    honest_answer = world.declare_queryable(truth, lambda query: query.reply(truth, b"true map"))
    assert wait_until(lambda: _replies(watcher, truth), 5, what="the world user's answer") == [b"true map"]
    for entity in (forged_answer, honest_answer, seen):
        entity.undeclare()


def test_a_robot_declares_its_session_token_only_under_its_own_id(secured, keep):
    """Robot r1 declares ``robots/r1/alive/{zid}`` (the session token services tell robot owners apart by), and
    services see it on ``robots/*/alive/*``; a token of r1's under r2's id never reaches them."""
    watcher, r1 = keep(secured.session("monitor")), keep(secured.session("r1"))
    tokens: list[str] = []
    watcher.liveliness().declare_subscriber(f"{secured.prefix}/robots/*/alive/*",
                                            lambda s: tokens.append(str(s.key_expr)), history=True)
    zid = str(r1.zid())
    forged = r1.liveliness().declare_token(f"{secured.prefix}/robots/r2/alive/{zid}")
    own = r1.liveliness().declare_token(f"{secured.prefix}/robots/r1/alive/{zid}")
    wait_until(lambda: f"{secured.prefix}/robots/r1/alive/{zid}" in tokens, 5, what="r1's session token")
    assert tokens == [f"{secured.prefix}/robots/r1/alive/{zid}"]
    for entity in (forged, own):
        entity.undeclare()


def test_a_client_without_or_with_wrong_credentials_is_refused(secured, processes):
    anonymous = processes.start("anonymous", "robot", "--id", "r1", env=secured.env(None))
    assert anonymous.wait(timeout=20) == 2
    assert "could not reach the zenoh router" in processes.log("anonymous")
    for user, password in (("r1", "wrong"), ("intruder", "secret"), (None, None),
                           (WORLD_USER, (secured.secrets / "r1.password").read_text().strip())):
        assert _refused(secured.settings(user, password)), (user, password)
    assert not _refused(secured.settings("r1"))  # the right password is let in


def test_a_router_without_a_config_is_open_and_says_so_and_a_secured_one_keeps_its_passwords(processes, tmp_path):
    _, _, port = _start_router(processes, "tcp")
    log = f"router-{port}"
    wait_until(lambda: "this router is OPEN" in processes.log(log), 5, what="the open router's warning")
    assert re.search(r"WARNING .*this router is OPEN.*--secrets-dir", processes.log(log))
    assert not _refused(FleetSettings(zenoh_connect=f"tcp/127.0.0.1:{port}", connect_timeout_s=2))

    first = _secured_router(processes, tmp_path)
    passwords = {p.name: p.read_text() for p in first.secrets.glob("*.password")}
    assert set(passwords) == {f"{u}.password" for u in ("r1", "r2", "central", "monitor", WORLD_USER, ROUTER_USER)}
    assert all(oct(p.stat().st_mode & 0o777) == "0o600" for p in first.secrets.iterdir())
    assert oct(first.secrets.stat().st_mode & 0o777) == "0o700"
    second = _secured_router(processes, tmp_path)  # a second start with the same folder: the same passwords
    assert {p.name: p.read_text() for p in second.secrets.glob("*.password")} == passwords
    assert not _refused(second.settings("r1"))
    assert "OPEN" not in "".join(processes.log(name) for name, _ in processes.started if name != log)


def _certs(folder: Path, users: str) -> Path:
    if shutil.which("openssl") is None or shutil.which("sh") is None:
        pytest.skip("openssl is not installed")
    subprocess.run(["sh", str(MAKE_CERTS), str(folder), "localhost,127.0.0.1", users], check=True, capture_output=True)
    return folder


def test_mutual_tls_admits_only_certificates_of_the_ca_and_applies_the_acl_to_their_common_names(processes, tmp_path,
                                                                                                     keep):
    tls = _certs(tmp_path / "tls", "r1 monitor")
    config, port = tmp_path / "router-cert.json5", free_port()
    subprocess.run([sys.executable, str(MAKE_CONFIG), "--prefix", f"s{port}", "--robots", "r1,r2", "--services",
                    "central,monitor", "--auth", "certificate", "--tls-dir", str(tls), "--out", str(config)], check=True)
    endpoint, prefix, _ = _start_router(processes, "tls", "--router-config", str(config), port=port)
    subjects = {subject["id"]: subject for subject in read_json5(config)["access_control"]["subjects"]}
    assert subjects["robot-r1"] == {"id": "robot-r1", "cert_common_names": ["r1"]}

    foreign = _certs(tmp_path / "foreign", "r1")  # another CA's certificate for the same name

    def session(user: str | None, folder: Path = tls, timeout: float = 3.0) -> zenoh.Session:
        extra = {"tls_root_ca": str(tls / "ca.pem")}
        if user:
            extra.update(tls_cert=str(folder / f"{user}.pem"), tls_key=str(folder / f"{user}-key.pem"))
        return open_session(FleetSettings(zenoh_connect=endpoint, prefix=prefix, connect_timeout_s=timeout, **extra))

    for user, folder in ((None, tls), ("r1", foreign)):
        extra = {"tls_cert": str(folder / f"{user}.pem"), "tls_key": str(folder / f"{user}-key.pem")} if user else {}
        assert _refused(FleetSettings(zenoh_connect=endpoint, prefix=prefix, connect_timeout_s=1.5,
                                      tls_root_ca=str(tls / "ca.pem"), **extra)), user
    watcher = keep(session("monitor"))
    got = threading.Event()
    keys: list[str] = []
    watcher.declare_subscriber(f"{prefix}/**", lambda s: (keys.append(str(s.key_expr)), got.set()))
    r1 = keep(session("r1"))
    wait_until(lambda: (r1.put(f"{prefix}/robots/r1/odom", b"x"), got.is_set())[1], 10, 0.2, "r1's sample over TLS")
    r1.put(f"{prefix}/robots/r2/odom", b"forged")
    r1.put(f"{prefix}/robots/r1/scan", b"x")
    wait_until(lambda: f"{prefix}/robots/r1/scan" in keys, 5, what="r1's scan")
    assert f"{prefix}/robots/r2/odom" not in keys


def test_a_tls_client_whose_certificate_names_another_user_can_do_nothing(processes, tmp_path, keep):
    """``--secrets-dir`` with ``--tls-dir``: each subject needs the user name AND the certificate's common name.
    Zenoh checks the password and the certificate apart, so a client with r1's password and r2's certificate
    passes the handshake (or, with a later zenoh, is refused there); it then matches no subject and may neither
    put, subscribe, query, answer queries, declare liveliness tokens nor watch them."""
    tls = _certs(tmp_path / "tls", "r1 r2 monitor")
    router = _secured_router(processes, tmp_path, "tls", "--tls-dir", str(tls))
    router.tls = tls
    p = router.prefix
    # the password alone is not enough: no certificate, no TLS session
    assert _refused(router.settings("r1").model_copy(update={"tls_cert": None, "tls_key": None}))
    watcher, r1 = keep(router.session("monitor", timeout=3.0)), keep(router.session("r1", timeout=3.0))
    try:
        mixed = keep(router.session("r1", cert="r2", timeout=3.0))
    except ConnectError:
        return  # refused at the handshake: nothing more to check
    seen = Collector(watcher, f"{p}/**")
    tokens: list[str] = []
    watcher.liveliness().declare_subscriber(f"{p}/**", lambda s: tokens.append(str(s.key_expr)), history=True)
    asked: list[str] = []
    watcher.declare_queryable(f"{p}/monitor/ask", lambda q: (asked.append(str(q.key_expr)), q.reply(q.key_expr, b"ok")))
    # what the mixed client tries first, then what r1 does honestly: r1's must arrive, the mixed client's never
    mixed_seen = Collector(mixed, f"{p}/**")
    mixed_tokens: list[str] = []
    mixed.liveliness().declare_subscriber(f"{p}/**", lambda s: mixed_tokens.append(str(s.key_expr)), history=True)
    for key in (f"{p}/robots/r1/odom", f"{p}/robots/r2/odom", f"{p}/world/truth", f"{p}/monitor/x"):
        mixed.put(key, b"forged")
    mixed_token = mixed.liveliness().declare_token(f"{p}/robots/r1/alive/mixed")
    mixed_answer = mixed.declare_queryable(f"{p}/robots/r1/info", lambda q: q.reply(q.key_expr, b"forged"))
    assert _replies(mixed, f"{p}/monitor/ask") == [] and asked == []
    honest_token = r1.liveliness().declare_token(f"{p}/robots/r1/alive/honest")
    honest_answer = r1.declare_queryable(f"{p}/robots/r1/history", lambda q: q.reply(q.key_expr, b"ok"))
    put_until_seen(r1, f"{p}/robots/r1/scan", b"ok", seen)
    wait_until(lambda: f"{p}/robots/r1/alive/honest" in tokens, 5, what="r1's honest token")
    assert wait_until(lambda: _replies(watcher, f"{p}/robots/r1/*"), 5, what="r1's honest answer") == [b"ok"]
    assert {payload for _, payload in seen.snapshot()} == {b"ok"}
    assert tokens == [f"{p}/robots/r1/alive/honest"]
    # the mixed client hears only itself (a session delivers its own puts and tokens locally)
    assert [payload for _, payload in mixed_seen.snapshot() if payload != b"forged"] == []
    assert [token for token in mixed_tokens if not token.endswith("/mixed")] == []
    for entity in (mixed_token, mixed_answer, honest_token, honest_answer):
        entity.undeclare()


def _mounts(service: dict, source: str) -> list[dict]:
    return [v for v in service.get("volumes") or [] if v["type"] == "volume" and v["source"] == source]


@pytest.mark.parametrize("variant", VARIANTS)
def test_compose_logs_every_client_in_as_itself_with_a_password_from_the_secrets_volume(compose_bin, variant):
    words, files = VARIANTS[variant]
    project = compose_config(compose_bin, *words, files=files)
    services, tls = project["services"], "docker-compose.tls.yml" in files
    router = services["router"]
    env = router["environment"]
    secrets_dir = env["FLEETSLAM_SECRETS_DIR"]
    assert [(v["target"], v.get("read_only", False)) for v in _mounts(router, "secrets")] == [(secrets_dir, False)]
    robots = parse_robots(env.get("FLEETSLAM_ROBOT_USERS", RouterSettings.model_fields["robot_users"].default))
    known = {*robots, *parse_services(env.get("FLEETSLAM_SERVICE_USERS",
                                              RouterSettings.model_fields["service_users"].default)), WORLD_USER}
    if tls:
        tls_dir = env["FLEETSLAM_TLS_DIR"]
        assert env["FLEETSLAM_LISTEN"].startswith("tls/")
        mounted = {s["target"]: Path(project["secrets"][s["source"]]["file"]) for s in router["secrets"]}
        assert {mounted[f"{tls_dir}/{n}.pem"].name for n in ("ca", "router", "router-key")} == \
               {"ca.pem", "router.pem", "router-key.pem"}
    for name, service in services.items():
        if name == "router":
            continue
        env = service["environment"]
        user = env["FLEETSLAM_ZENOH_USER"]
        assert user in known, f"{name} logs in as {user}, unknown to the router"
        (mount,) = _mounts(service, "secrets")
        assert mount.get("read_only") and env["FLEETSLAM_ZENOH_PASSWORD_FILE"] == f"{mount['target']}/{user}.password"
        assert "FLEETSLAM_ZENOH_PASSWORD" not in env, f"{name}: a password in the environment"
        if service["command"] == ["robot"]:
            robot_id = env.get("FLEETSLAM_ROBOT_ID") or f"r{env['FLEETSLAM_REPLAY'].rpartition(':')[2]}"
            assert user == robot_id, f"{name} publishes as {robot_id} but logs in as {user}"
            assert env["FLEETSLAM_PUBLISH_WORLD"] == "false", f"{name} would publish the world map"
        if service["command"] == ["world"]:
            assert user == WORLD_USER
        if tls:
            assert env["FLEETSLAM_ZENOH_CONNECT"].startswith("tls/")
            mounted = {s["target"]: Path(project["secrets"][s["source"]]["file"]) for s in service["secrets"]}
            assert mounted[env["FLEETSLAM_TLS_CERT"]].name == f"{user}.pem"
            assert mounted[env["FLEETSLAM_TLS_KEY"]].name == f"{user}-key.pem"
            assert mounted[env["FLEETSLAM_TLS_ROOT_CA"]].name == "ca.pem"
    assert sum(1 for s in services.values() if s["command"] == ["world"]) == 1, "one publisher of the world map"


def test_the_committed_router_config_is_what_the_compose_router_makes(tmp_path):
    """deploy/router-acl.json5 (the script's default output) is the config the compose router writes into /secrets."""
    made = secure_folder(tmp_path, "fleet", list(DEFAULT_ROBOTS), DEFAULT_SERVICES)
    fresh = tmp_path / "fresh.json5"
    subprocess.run([sys.executable, str(MAKE_CONFIG), "--out", str(fresh)], check=True)
    committed = (REPO / "deploy" / "router-acl.json5").read_text()
    assert fresh.read_text() == committed, "deploy/router-acl.json5 is stale: run python deploy/make_router_config.py"
    assert made.read_text().replace(str(tmp_path.resolve()), "/secrets") == committed
