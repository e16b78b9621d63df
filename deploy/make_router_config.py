#!/usr/bin/env python3
"""Write a secured router's config: user/password and/or certificate authentication, and access control.

    python deploy/make_router_config.py                            # deploy/router-acl.json5 (committed)
    python deploy/make_router_config.py --secrets DIR --users-file DIR/users.txt --out DIR/router.json5

``fleetslam router --secrets-dir DIR`` (what ``docker compose up`` and
``fleetslam demo`` run) does this itself at every start; this script is for a
router configured by hand (``fleetslam router --router-config FILE``) and for
certificate-only authentication (``--auth certificate``). The rules are in
``services/credentials.py``: each robot writes only under its own keys, the
``world`` user only the world map, each service only under its own root, and
a client without valid credentials is refused. The committed
``deploy/router-acl.json5`` is what the compose router enforces (prefix
``fleet``, robots r1-r5, the default services).

``--secrets DIR`` writes ``DIR/{user}.password`` (random, kept if already
there) and the router's dictionary ``DIR/users.txt`` (``user:password``
lines) in a 0700 folder, files 0600. Only the standard library is used (the
project's own ``services/credentials.py`` is imported from this checkout), so
the script runs before the project is installed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from services.credentials import (DEFAULT_ROBOTS, DEFAULT_SERVICES, check_users, format_services,  # noqa: E402
                                  parse_robots, parse_services, render, router_config, write_secrets)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--prefix", default="fleet", help="key prefix (FLEETSLAM_PREFIX)")
    parser.add_argument("--robots", default=",".join(DEFAULT_ROBOTS), help="robot ids, comma-separated")
    parser.add_argument("--services", default=format_services(DEFAULT_SERVICES),
                        help="service users, comma-separated; NAME=ROOT+ROOT names the key roots it writes under")
    parser.add_argument("--users-file", default="/secrets/users.txt",
                        help="where the router reads the user:password dictionary (compose: the volume 'secrets')")
    parser.add_argument("--auth", choices=["password", "certificate", "both"], default="password",
                        help="how clients prove who they are: user/password, client certificate (mutual TLS; the "
                        "common name is the user), or both")
    parser.add_argument("--tls-dir", default=None,
                        help="where the router reads ca.pem, router.pem, router-key.pem (deploy/make-certs.sh)")
    parser.add_argument("--out", default=str(HERE / "router-acl.json5"), help="the JSON5 file to write")
    parser.add_argument("--secrets", default=None, help="also write passwords and the dictionary into this folder")
    args = parser.parse_args(argv)
    robots = parse_robots(args.robots)
    services = parse_services(args.services)
    try:
        config = router_config(args.prefix, robots, services, args.users_file, args.auth, args.tls_dir)
    except ValueError as error:
        parser.error(str(error))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(render(config))
    if args.secrets:
        write_secrets(Path(args.secrets), check_users(robots, services))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
