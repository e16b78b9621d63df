"""``fleetslam router``: the Zenoh router, a Python process in router mode.

No ``zenohd`` binary exists on PyPI or Debian; the Python library's router
mode routes, and enforces access control, user/password and TLS when a JSON5
config is given with ``--router-config``. Every other fleetslam process is a
client of this router. Stops cleanly on SIGINT/SIGTERM.
"""

from __future__ import annotations

import argparse
import logging

from schemas.config import RouterSettings, add_settings_arguments, settings_from_args
from schemas.transport import ConnectError, Shutdown, open_session

log = logging.getLogger("fleetslam.router")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, RouterSettings)


def main(args: argparse.Namespace) -> int:
    settings = settings_from_args(RouterSettings, args)
    shutdown = Shutdown()
    try:
        session = open_session(settings, mode="router", listen=settings.listen, base_file=settings.router_config)
    except ConnectError as exc:
        log.error("%s", exc)
        return 2
    try:
        log.info("router %s listening on %s", session.zid(), settings.listen)
        shutdown.wait()
        log.info("router stopping (%s)", shutdown.signal_name or "stop")
    finally:
        session.close()
    return 0
