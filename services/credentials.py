"""The secured router's credentials and access control: one user and random password per client, deny by default.

Used by ``fleetslam router --secrets-dir DIR`` (what ``docker compose up`` and
``fleetslam demo`` run), and by ``deploy/make_router_config.py``. Every client
logs in with its own user name (a robot with its id, a service with its name,
the world-map publisher as ``world``) and the router enforces, with
``default_permission: deny``:

- robot ``{rid}`` may put, answer queries and declare liveliness tokens only
  under ``{prefix}/robots/{rid}/**`` (its streams, its ``alive`` token and its
  session token ``alive/{zid}``; ``.../@adv/**``, the advanced publisher's
  cache queryable and liveliness); it may not subscribe to or query anything,
  and not write the world map;
- ``world`` may put and answer queries only on ``{prefix}/world/truth`` (and
  its ``@adv`` keys): the true landmark map, which MCL and the evaluator trust;
- each service may put and answer only under its own keys (``{prefix}/{root}/**``)
  and may read (subscribe, query, watch liveliness) everything under ``{prefix}/**``;
- a client without credentials, or with a wrong password, fails the handshake;
  with mutual TLS (``auth="both"``) a subject needs the user name AND the
  certificate's common name, so a client whose certificate names another user
  matches no subject and may do nothing (zenoh checks the two apart at the
  handshake: it admits such a client).

Key expressions: ``**`` never matches a verbatim chunk such as ``@adv``, so the
advanced publisher/subscriber keys get rules of their own. Only the standard
library is used, so ``deploy/make_router_config.py`` runs before the project is installed.
"""

from __future__ import annotations

import json
import os
import re
import secrets
from pathlib import Path

DEFAULT_ROBOTS = ("r1", "r2", "r3", "r4", "r5")
# service user -> the key roots it writes under (``{prefix}/{root}/**``)
DEFAULT_SERVICES = {
    "central": ("central",),
    "dslam": ("dslam",),
    "assoc": ("assoc",),
    "mcl": ("mcl",),
    "evaluate": ("eval",),
    "monitor": ("monitor",),
    "viz": ("viz",),
    "record": ("record",),
}
WORLD_USER = "world"  # the one client allowed to publish the true landmark map
ROUTER_USER = "router"  # the user routers of one fleet log in to each other with (a mesh of sites)
USER_NAME = re.compile(r"^[A-Za-z0-9_-]{1,64}$")  # robot ids' pattern: no ':' (the dictionary's separator)
WRITE = ["put", "delete", "declare_queryable", "reply", "liveliness_token"]
READ = ["declare_subscriber", "query", "declare_liveliness_subscriber", "liveliness_query"]
CONFIG_NAME, USERS_NAME = "router.json5", "users.txt"


def _own(root: str) -> list[str]:
    """Keys under ``root`` and the advanced publisher/subscriber keys below them."""
    return [f"{root}/**", f"{root}/**/@adv/**"]


def _subject(subject_id: str, user: str, auth: str) -> dict:
    """A user's subject: its user name, its certificate's common name, or both (both must match)."""
    subject: dict = {"id": subject_id}
    if auth in ("password", "both"):
        subject["usernames"] = [user]
    if auth in ("certificate", "both"):
        subject["cert_common_names"] = [user]
    return subject


def check_users(robots: list[str], services: dict[str, tuple[str, ...]]) -> list[str]:
    """Every user name (robots, services, ``world``), each valid and given once (ValueError otherwise)."""
    users = [*robots, *services, WORLD_USER, ROUTER_USER]
    bad = [u for u in users if not USER_NAME.match(u)]
    if bad:
        raise ValueError(f"user names must match {USER_NAME.pattern}: {', '.join(map(repr, bad))}")
    twice = sorted({u for u in users if users.count(u) > 1})
    if twice:
        raise ValueError(f"user names given twice (robot ids, service names, {WORLD_USER!r} and {ROUTER_USER!r} "
                         "must differ): "
                         f"{', '.join(twice)}")
    return users


def access_control(prefix: str, robots: list[str], services: dict[str, tuple[str, ...]], auth: str = "password") -> dict:
    """The ``access_control`` section: one subject per user, deny by default."""
    check_users(robots, services)
    truth = f"{prefix}/world/truth"
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
        {"id": "world-writes", "permission": "allow", "flows": ["ingress"], "messages": WRITE,
         "key_exprs": [truth, f"{truth}/@adv/**"]},
    ]
    # Another router of the fleet: everything under the prefix passes its link both ways. Each router enforces the
    # rules on its own clients' ingress and egress, so a client has the same rights through any router of the mesh.
    rules.append({"id": "router-link", "permission": "allow", "flows": ["ingress", "egress"],
                  "messages": [*WRITE, *READ], "key_exprs": _own(prefix)})
    # With certificates a router is known by its certificate alone: the router that opens a link sees the other's
    # certificate but never a user name (password authentication is one-way). Only routers get certificates named
    # "router" from the fleet's CA (deploy/make-certs.sh).
    router = {"id": ROUTER_USER, "cert_common_names": [ROUTER_USER]} if auth in ("certificate", "both") \
        else _subject(ROUTER_USER, ROUTER_USER, auth)
    subjects: list[dict] = [_subject(WORLD_USER, WORLD_USER, auth), router]
    policies: list[dict] = [{"id": WORLD_USER, "subjects": [WORLD_USER], "rules": ["told-about-readers", "world-writes"]},
                            {"id": ROUTER_USER, "subjects": [ROUTER_USER], "rules": ["router-link"]}]
    for rid in robots:
        rules.append({"id": f"robot-{rid}-writes", "permission": "allow", "flows": ["ingress"], "messages": WRITE,
                      "key_exprs": _own(f"{prefix}/robots/{rid}")})
        estimates = [key for root in (f"{prefix}/central/estimate", f"{prefix}/dslam/pose/{rid}",
                                      f"{prefix}/mcl/{rid}/pose") for key in (root, f"{root}/@adv/**")]
        rules.append({"id": f"robot-{rid}-follows-its-estimates", "permission": "allow", "flows": ["ingress"],
                      "messages": ["declare_subscriber"], "key_exprs": estimates})
        rules.append({"id": f"robot-{rid}-receives-its-estimates", "permission": "allow", "flows": ["egress"],
                      "messages": ["put"], "key_exprs": estimates})
        subjects.append(_subject(f"robot-{rid}", rid, auth))
        policies.append({"id": f"robot-{rid}", "subjects": [f"robot-{rid}"],
                         "rules": ["told-about-readers", f"robot-{rid}-writes", f"robot-{rid}-follows-its-estimates",
                                   f"robot-{rid}-receives-its-estimates"]})
    for name, roots in services.items():
        rules.append({"id": f"service-{name}-writes", "permission": "allow", "flows": ["ingress"], "messages": WRITE,
                      "key_exprs": [key for root in roots for key in _own(f"{prefix}/{root}")]})
        subjects.append(_subject(f"service-{name}", name, auth))
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
            raise ValueError("certificate authentication needs a TLS folder (where the router finds its certificates)")
        transport["link"] = {"tls": {
            "root_ca_certificate": f"{tls_dir}/ca.pem",
            "listen_certificate": f"{tls_dir}/router.pem",
            "listen_private_key": f"{tls_dir}/router-key.pem",
            "connect_certificate": f"{tls_dir}/router.pem",  # shown to the routers this one connects to
            "connect_private_key": f"{tls_dir}/router-key.pem",
            "enable_mtls": True,
        }}
    return {"transport": transport, "access_control": access_control(prefix, robots, services, auth)}


def render(config: dict) -> str:
    """The config as JSON5 with a header, one rule, subject or policy a line."""
    header = (
        "// Generated by services/credentials.py (fleetslam router --secrets-dir, deploy/make_router_config.py); "
        "do not edit by hand.\n"
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


def _write_private(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically, readable by its owner only from the first byte."""
    part = path.with_name(path.name + ".part")
    fd = os.open(part, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as handle:
        handle.write(text)
        handle.flush()
        os.fsync(handle.fileno())
    os.chmod(part, 0o600)
    os.replace(part, path)


def write_secrets(folder: Path, users: list[str]) -> Path:
    """One random password per user in ``folder/{user}.password`` (kept if already there: a restart or a second
    ``docker compose up`` reuses them) and the router's dictionary ``users.txt`` of exactly ``users``.
    The folder is 0700 and the files 0600: every fleetslam container runs as the same user (uid 10001)."""
    folder.mkdir(parents=True, exist_ok=True)
    os.chmod(folder, 0o700)
    lines = []
    for user in users:
        path = folder / f"{user}.password"
        if not path.exists() or not path.read_text().strip():
            _write_private(path, secrets.token_urlsafe(24) + "\n")
        lines.append(f"{user}:{path.read_text().strip()}")
    dictionary = folder / USERS_NAME
    _write_private(dictionary, "\n".join(lines) + "\n")
    return dictionary


def secure_folder(folder: Path, prefix: str, robots: list[str], services: dict[str, tuple[str, ...]],
                  tls_dir: str | None = None) -> Path:
    """Make (first start) or reuse every user's password in ``folder``, write the dictionary and the router's
    config (``router.json5``: password authentication, with ``tls_dir`` mutual TLS too, and the access control);
    returns the config's path."""
    users = check_users(robots, services)
    folder = folder.resolve()
    dictionary = write_secrets(folder, users)
    config = router_config(prefix, robots, services, str(dictionary), "both" if tls_dir else "password", tls_dir)
    path = folder / CONFIG_NAME
    _write_private(path, render(config))
    return path


def parse_robots(text: str) -> list[str]:
    """``r1,r2`` -> ["r1", "r2"]."""
    return [r.strip() for r in text.split(",") if r.strip()]


def parse_services(text: str) -> dict[str, tuple[str, ...]]:
    """``central,evaluate=eval+evaluate`` -> {"central": ("central",), "evaluate": ("eval", "evaluate")}."""
    services = {}
    for item in filter(None, (t.strip() for t in text.split(","))):
        name, _, roots = item.partition("=")
        services[name] = tuple(roots.split("+")) if roots else DEFAULT_SERVICES.get(name, (name,))
    return services


def format_services(services: dict[str, tuple[str, ...]]) -> str:
    """The inverse of :func:`parse_services`."""
    return ",".join(name if roots == (name,) else f"{name}={'+'.join(roots)}" for name, roots in services.items())
