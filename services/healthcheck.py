"""Container health check: is this process's Zenoh link up?

    python -m services.healthcheck router   # a socket listens on the port of FLEETSLAM_LISTEN
    python -m services.healthcheck client   # a TCP connection to the port of FLEETSLAM_ZENOH_CONNECT is established

It reads the kernel's socket tables (``/proc/net/tcp``, ``tcp6``) of the
container's network namespace instead of opening a Zenoh session, so a check
costs a few milliseconds and imports neither zenoh nor numpy. A client whose
link to the router is cut (and not yet re-established) is unhealthy. Exit
status 0 when healthy, 1 when not (with the reason on stderr), as Docker's
HEALTHCHECK expects.
"""

from __future__ import annotations

import sys
from pathlib import Path

from schemas.config import FleetSettings, RouterSettings

LISTEN, ESTABLISHED = "0A", "01"
TABLES = (Path("/proc/net/tcp"), Path("/proc/net/tcp6"))


def endpoint_ports(endpoints: str) -> set[int]:
    """Ports of zenoh endpoints ``proto/host:port[?config][#metadata]``, comma-separated."""
    ports = set()
    for endpoint in filter(None, (e.strip() for e in endpoints.split(","))):
        address = endpoint.partition("/")[2].split("?")[0].split("#")[0]
        port = address.rpartition(":")[2]
        if port.isdigit():
            ports.add(int(port))
    return ports


def sockets(tables=TABLES) -> list[tuple[int, int, str]]:
    """(local port, remote port, state) of every TCP socket in this network namespace."""
    found = []
    for table in tables:
        try:
            lines = table.read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            local, remote, state = fields[1], fields[2], fields[3]
            found.append((int(local.rpartition(":")[2], 16), int(remote.rpartition(":")[2], 16), state))
    return found


def check(role: str, tables=TABLES, ports: set[int] | None = None) -> str | None:
    """None when healthy, else why not (``ports``: the router's, by default from the settings)."""
    table = sockets(tables)
    if role == "router":
        ports = endpoint_ports(RouterSettings().listen) if ports is None else ports
        if any(state == LISTEN and local in ports for local, _, state in table):
            return None
        return f"nothing listens on port(s) {sorted(ports)}"
    ports = endpoint_ports(FleetSettings().zenoh_connect) if ports is None else ports
    if any(state == ESTABLISHED and remote in ports for _, remote, state in table):
        return None
    return f"no established connection to the router port(s) {sorted(ports)}"


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    role = args[0] if args else "client"
    if role not in ("router", "client"):
        print("usage: python -m services.healthcheck router|client", file=sys.stderr)
        return 2
    problem = check(role)
    if problem:
        print(f"unhealthy: {problem}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
