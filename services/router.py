"""``fleetslam router``: the Zenoh router, a Python process in router mode.

No ``zenohd`` binary exists on PyPI or Debian; the Python library's router
mode routes, and enforces access control, user/password and TLS. With
``--secrets-dir DIR`` (what ``docker compose up`` and ``fleetslam demo`` run)
it makes one random password per robot and service in DIR on its first start,
keeps them on later starts, and runs with them and the access control of
:mod:`services.credentials`; ``--router-config FILE`` merges a JSON5 config of
your own instead. With neither it is open, for development, and says so in a
warning. Every other fleetslam process is a client of this router. It does
not stamp samples with its clock (``--router-timestamps``: nothing reads Zenoh
timestamps, and they cost 27 bytes a sample on every link after) and offers
lz4 compression on its links (``--link-compression``: taken up where the other
end offers it too, that is between routers). Stops cleanly on SIGINT/SIGTERM.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from schemas.config import RouterSettings, add_settings_arguments, settings_from_args
from schemas.contract import SettingsError
from schemas.transport import ConnectError, Shutdown, open_session
from services.credentials import ROUTER_USER, parse_robots, parse_services, secure_folder

log = logging.getLogger("fleetslam.router")

OPEN_WARNING = (
    "this router is OPEN: no authentication and no access control. Any process that reaches %s can read and write "
    "everything: forge any robot's odometry, scans and RobotInfo, the world map and every service's output, and "
    "read them all. Fine on a development machine; to secure it, start it with --secrets-dir DIR (a password per "
    "robot and service, made once and kept in DIR, and access control that denies by default; clients log in with "
    "FLEETSLAM_ZENOH_USER=USER and FLEETSLAM_ZENOH_PASSWORD_FILE=DIR/USER.password) or --router-config FILE "
    "(deploy/make_router_config.py)"
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, RouterSettings)


def main(args: argparse.Namespace) -> int:
    settings = settings_from_args(RouterSettings, args)
    if settings.secrets_dir and settings.router_config:
        raise SettingsError("--secrets-dir and --router-config: give one (credentials and access control made in a "
                            "folder, or a config of your own), not both")
    base_file = settings.router_config
    if settings.secrets_dir:
        robots, services = parse_robots(settings.robot_users), parse_services(settings.service_users)
        try:
            base_file = str(secure_folder(Path(settings.secrets_dir), settings.prefix, robots, services,
                                          settings.tls_dir))
        except (OSError, ValueError) as exc:
            log.error("cannot prepare the credentials in %s: %s", settings.secrets_dir, exc)
            return 2
        log.info("secured%s: users %s, %s and world; access control denies by default (prefix %s); passwords "
                 "in %s, kept across restarts", " with mutual TLS" if settings.tls_dir else "", ",".join(robots),
                 ",".join(services), settings.prefix, Path(settings.secrets_dir).resolve())
    elif not base_file:
        log.warning(OPEN_WARNING, settings.listen)
    if settings.connect_routers and settings.secrets_dir and not settings.tls_dir:
        raise SettingsError("--connect with --secrets-dir needs --tls-dir too: routers of a secured fleet know each "
                            "other by their certificates (zenoh's password check is one-way: the router that opens "
                            "the link could not tell that the other is a router of the fleet, and would refuse it)")
    if settings.connect_routers and settings.secrets_dir:  # log in to the other routers of the fleet
        settings = settings.model_copy(update={
            "zenoh_user": ROUTER_USER, "zenoh_password": None,
            "zenoh_password_file": str(Path(settings.secrets_dir) / f"{ROUTER_USER}.password")})
    shutdown = Shutdown()
    try:
        session = open_session(settings, mode="router", listen=settings.listen, base_file=base_file,
                               routers=settings.connect_routers)
    except ConnectError as exc:
        log.error("%s", exc)
        return 2
    try:
        log.info("router %s listening on %s%s", session.zid(), settings.listen,
                 f", connecting to {settings.connect_routers}" if settings.connect_routers else "")
        shutdown.wait()
        log.info("router stopping (%s)", shutdown.signal_name or "stop")
    finally:
        session.close()
    return 0
