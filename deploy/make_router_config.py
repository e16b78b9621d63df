#!/usr/bin/env python3
"""Write the secured router's config: user/password authentication and access control.

    python deploy/make_router_config.py                      # deploy/router-acl.json5 (committed)
    python deploy/make_router_config.py --secrets deploy/secrets   # + one password per client (not committed)

The JSON5 file is merged into the router's config (``fleetslam router
--router-config FILE``). Every client logs in with its own user name (a robot
with its id, a service with its name) and the router enforces, with
``default_permission: deny``:

- robot ``{rid}`` may put, answer queries and declare its liveliness token
  only under ``{prefix}/robots/{rid}/**`` (and the advanced-publisher
  sub-keys ``.../@adv/**`` of its own streams), plus the simulator's world map
  ``{prefix}/world/truth``; it may not subscribe to or query anything;
- each service may put and answer only under its own keys
  (``{prefix}/{name}/**``) and may read (subscribe, query, watch liveliness)
  everything under ``{prefix}/**``;
- a client without credentials, or with a wrong password, fails the handshake.

Key expressions: ``**`` never matches a verbatim chunk such as ``@adv``, so the
advanced publisher/subscriber keys get rules of their own.

``--secrets DIR`` writes ``DIR/{user}.password`` (random) and the router's
dictionary ``DIR/users.txt`` (``user:password`` lines) in a 0700 folder (the
files are 0644 so that a container's non-root user can read them once
compose mounts them as secrets). Only the
standard library is used, so the script runs before the project is installed.
"""

from __future__ import annotations

import argparse
import json
import os
import secrets
from pathlib import Path

HERE = Path(__file__).resolve().parent
DEFAULT_ROBOTS = ("r1", "r2", "r3", "r4", "r5")
# service user -> the key roots it writes under (``{prefix}/{root}/**``)
DEFAULT_SERVICES = {
    "central": ("central",),
    "dslam": ("dslam",),
    "assoc": ("assoc",),
    "mcl": ("mcl",),
    "evaluate": ("eval",),
    "monitor": ("monitor",),
}
WRITE = ["put", "delete", "declare_queryable", "reply", "liveliness_token"]
READ = ["declare_subscriber", "query", "declare_liveliness_subscriber", "liveliness_query"]
EVERY_MESSAGE = WRITE + READ


def _own(root: str) -> list[str]:
    """Keys under ``root`` and the advanced publisher/subscriber keys below them."""
    return [f"{root}/**", f"{root}/**/@adv/**"]


def _subject(kind: str, user: str, auth: str) -> dict:
    """A user's subject: its user name, its certificate's common name, or both (both must match)."""
    subject: dict = {"id": f"{kind}-{user}"}
    if auth in ("password", "both"):
        subject["usernames"] = [user]
    if auth in ("certificate", "both"):
        subject["cert_common_names"] = [user]
    return subject


def access_control(prefix: str, robots: list[str], services: dict[str, tuple[str, ...]], auth: str = "password") -> dict:
    """The ``access_control`` section: one subject per user, deny by default."""
    rules: list[dict] = [
        # Everyone is told about the readers and the queries of the whole fleet, so
        # publishers route to subscribers they match and queryables get their queries.
        {"id": "told-about-readers", "permission": "allow", "flows": ["egress"], "messages": READ,
         "key_exprs": _own(prefix)},
        {"id": "service-reads-all", "permission": "allow", "flows": ["ingress", "egress"],
         "messages": READ, "key_exprs": _own(prefix)},
        {"id": "service-receives-all", "permission": "allow", "flows": ["egress"],
         "messages": ["put", "delete", "reply", "liveliness_token"], "key_exprs": _own(prefix)},
        {"id": "service-subscriber-tokens", "permission": "allow", "flows": ["ingress"],
         "messages": ["liveliness_token"], "key_exprs": [f"{prefix}/**/@adv/**"]},
    ]
    subjects: list[dict] = []
    policies: list[dict] = []
    for rid in robots:
        rules.append({"id": f"robot-{rid}-writes", "permission": "allow", "flows": ["ingress"], "messages": WRITE,
                      "key_exprs": [*_own(f"{prefix}/robots/{rid}"), f"{prefix}/world/truth"]})
        subjects.append(_subject("robot", rid, auth))
        policies.append({"id": f"robot-{rid}", "subjects": [f"robot-{rid}"],
                         "rules": ["told-about-readers", f"robot-{rid}-writes"]})
    for name, roots in services.items():
        rules.append({"id": f"service-{name}-writes", "permission": "allow", "flows": ["ingress"], "messages": WRITE,
                      "key_exprs": [key for root in roots for key in _own(f"{prefix}/{root}")]})
        subjects.append(_subject("service", name, auth))
        policies.append({"id": f"service-{name}", "subjects": [f"service-{name}"],
                         "rules": ["service-reads-all", "service-receives-all", "service-subscriber-tokens",
                                   f"service-{name}-writes"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def router_config(prefix: str, robots: list[str], services: dict[str, tuple[str, ...]], users_file: str,
                  auth: str = "password", tls_dir: str | None = None) -> dict:
    """Authentication (user/password dictionary, mutual TLS or both) and access control."""
    transport: dict = {}
    if auth in ("password", "both"):
        transport["auth"] = {"usrpwd": {"dictionary_file": users_file}}
    if auth in ("certificate", "both"):
        if not tls_dir:
            raise ValueError("certificate authentication needs --tls-dir (where the router finds its certificates)")
        transport["link"] = {"tls": {
            "root_ca_certificate": f"{tls_dir}/ca.pem",
            "listen_certificate": f"{tls_dir}/router.pem",
            "listen_private_key": f"{tls_dir}/router-key.pem",
            "enable_mtls": True,
        }}
    return {"transport": transport, "access_control": access_control(prefix, robots, services, auth)}


def render(config: dict) -> str:
    header = (
        "// Generated by deploy/make_router_config.py (see its --help); do not edit by hand.\n"
        "// Merged into the router's config: fleetslam router --router-config THIS_FILE\n"
    )
    acl = config["access_control"]
    lines = [header + "{", f'  "transport": {json.dumps(config["transport"])},', '  "access_control": {',
             f'    "enabled": {json.dumps(acl["enabled"])},', f'    "default_permission": {json.dumps(acl["default_permission"])},']
    for section in ("rules", "subjects", "policies"):
        lines.append(f'    "{section}": [')
        lines += [f"      {json.dumps(item)}," for item in acl[section]]
        lines.append("    ],")
    return "\n".join(lines + ["  }", "}"]) + "\n"


def write_secrets(folder: Path, users: list[str]) -> Path:
    """One random password per user (kept if already there) and the router's dictionary."""
    folder.mkdir(parents=True, exist_ok=True)
    os.chmod(folder, 0o700)
    lines = []
    for user in users:
        path = folder / f"{user}.password"
        if not path.exists():
            path.write_text(secrets.token_urlsafe(24) + "\n")
        lines.append(f"{user}:{path.read_text().strip()}")
    dictionary = folder / "users.txt"
    dictionary.write_text("\n".join(lines) + "\n")
    for path in folder.glob("*"):
        os.chmod(path, 0o644)  # a non-root container user reads them bind-mounted; the 0700 folder guards the host
    return dictionary


def parse_services(text: str) -> dict[str, tuple[str, ...]]:
    """``central,evaluate=eval+evaluate`` -> {"central": ("central",), "evaluate": ("eval", "evaluate")}."""
    services = {}
    for item in filter(None, (t.strip() for t in text.split(","))):
        name, _, roots = item.partition("=")
        services[name] = tuple(roots.split("+")) if roots else DEFAULT_SERVICES.get(name, (name,))
    return services


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--prefix", default="fleet", help="key prefix (FLEETSLAM_PREFIX)")
    parser.add_argument("--robots", default=",".join(DEFAULT_ROBOTS), help="robot ids, comma-separated")
    parser.add_argument("--services", default=",".join(DEFAULT_SERVICES),
                        help="service users, comma-separated; NAME=ROOT+ROOT names the key roots it writes under")
    parser.add_argument("--users-file", default="/run/secrets/zenoh_users",
                        help="where the router reads the user:password dictionary (a docker secret in compose)")
    parser.add_argument("--auth", choices=["password", "certificate", "both"], default="password",
                        help="how clients prove who they are: user/password, client certificate (mutual TLS; the "
                        "common name is the user), or both")
    parser.add_argument("--tls-dir", default=None,
                        help="where the router reads ca.pem, router.pem, router-key.pem (deploy/make-certs.sh)")
    parser.add_argument("--out", default=str(HERE / "router-acl.json5"), help="the JSON5 file to write")
    parser.add_argument("--secrets", default=None, help="also write passwords and the dictionary into this folder")
    args = parser.parse_args(argv)
    robots = [r.strip() for r in args.robots.split(",") if r.strip()]
    services = parse_services(args.services)
    config = router_config(args.prefix, robots, services, args.users_file, args.auth, args.tls_dir)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(render(config))
    if args.secrets:
        write_secrets(Path(args.secrets), [*robots, *services])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
