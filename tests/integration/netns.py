"""A throw-away multi-host network made of Linux network namespaces (as root).

Each host is a namespace with one veth whose peer is plugged into a bridge
that lives in a namespace of its own (the "switch"), so nothing is added to
the machine's own network and no packet can leave: every address is inside
the namespaces made here. ``/etc/netns/{ns}/hosts`` maps every host name to
its address, and ``ip netns exec`` bind-mounts it over ``/etc/hosts``, so
service names resolve as on a compose network.

Names carry the test process id, so parallel runs never collide, and
:meth:`NetnsLab.close` removes everything (also after a failure); labs left by
a killed run are removed by the next one (:func:`remove_stale`).
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import time
from pathlib import Path

NAME_PREFIX = "fleetslam-"
NETNS_ETC = Path("/etc/netns")
_STALE = re.compile(rf"^{NAME_PREFIX}(\d+)-")


def netns_unavailable() -> str | None:
    """Why namespaces cannot be made here (None when they can)."""
    if os.geteuid() != 0:
        return "network namespaces need root (ip netns add); run the suite as root to include this test"
    if shutil.which("ip") is None:
        return "the `ip` command (iproute2) is not installed"
    probe = f"{NAME_PREFIX}{os.getpid()}-probe"
    made = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True)
    if made.returncode != 0:
        return f"`ip netns add` failed: {made.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", probe], capture_output=True)
    return None


def _namespaces() -> list[str]:
    out = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    return [line.split()[0] for line in out.splitlines() if line.strip()]


def remove_stale() -> None:
    """Remove namespaces (and hosts files) of earlier runs whose process is gone."""
    for name in _namespaces():
        match = _STALE.match(name)
        if match and not Path(f"/proc/{match.group(1)}").exists():
            subprocess.run(["ip", "netns", "del", name], capture_output=True)
            shutil.rmtree(NETNS_ETC / name, ignore_errors=True)


def _ip(*words: str) -> None:
    result = subprocess.run(["ip", *words], capture_output=True, text=True)
    if result.returncode != 0:
        raise RuntimeError(f"ip {' '.join(words)}: {result.stderr.strip()}")


class NetnsLab:
    """Hosts on one isolated bridge; start processes in them; cut and restore their links."""

    def __init__(self, tag: str, subnet: str = "10.213.0"):
        remove_stale()
        self.run = f"{NAME_PREFIX}{os.getpid()}-{tag}"
        self.subnet = subnet
        self.switch = f"{self.run}-switch"
        self.hosts: dict[str, str] = {}  # host name -> address
        self.ports: dict[str, str] = {}  # host name -> its veth on the switch
        self.processes: list[subprocess.Popen] = []
        self._namespaces: list[str] = []
        self._add_namespace(self.switch)
        _ip("-n", self.switch, "link", "add", "br0", "type", "bridge")
        _ip("-n", self.switch, "link", "set", "br0", "up")

    def ns(self, host: str) -> str:
        return f"{self.run}-{host}"

    def _add_namespace(self, name: str) -> None:
        _ip("netns", "add", name)
        self._namespaces.append(name)
        _ip("-n", name, "link", "set", "lo", "up")

    def add_host(self, host: str) -> str:
        """A new namespace on the bridge; returns its address."""
        index = len(self.hosts) + 1
        if index > 250:
            raise ValueError("at most 250 hosts on one lab")
        ns, port = self.ns(host), f"p{index}"
        address = f"{self.subnet}.{index}"
        self._add_namespace(ns)
        _ip("-n", self.switch, "link", "add", port, "type", "veth", "peer", "name", "eth0", "netns", ns)
        _ip("-n", self.switch, "link", "set", port, "master", "br0")
        _ip("-n", self.switch, "link", "set", port, "up")
        _ip("-n", ns, "addr", "add", f"{address}/24", "dev", "eth0")
        _ip("-n", ns, "link", "set", "eth0", "up")
        self.hosts[host], self.ports[host] = address, port
        self._write_hosts()
        return address

    def _write_hosts(self) -> None:
        lines = ["127.0.0.1 localhost"] + [f"{address} {host}" for host, address in self.hosts.items()]
        for host in self.hosts:
            folder = NETNS_ETC / self.ns(host)
            folder.mkdir(parents=True, exist_ok=True)
            (folder / "hosts").write_text("\n".join(lines) + "\n")

    def command(self, host: str, argv: list[str]) -> list[str]:
        return ["ip", "netns", "exec", self.ns(host), *argv]

    def start(self, host: str, argv: list[str], env: dict[str, str], log_path: Path, cwd: Path) -> subprocess.Popen:
        """Run ``argv`` inside ``host``'s namespace (``ip netns exec`` execs it: the pid is the program's)."""
        handle = open(log_path, "a")
        process = subprocess.Popen(self.command(host, argv), env=env, stdout=handle, stderr=subprocess.STDOUT, cwd=cwd)
        handle.close()
        self.processes.append(process)
        return process

    def cut(self, host: str) -> None:
        """Unplug ``host``'s cable at the switch: its packets vanish silently (no reset, no error)."""
        _ip("-n", self.switch, "link", "set", self.ports[host], "down")

    def restore(self, host: str) -> None:
        _ip("-n", self.switch, "link", "set", self.ports[host], "up")

    def close(self, grace_s: float = 2.0) -> None:
        """Stop every process started here (SIGTERM, SIGKILL after ``grace_s``), delete every namespace
        and hosts file."""
        for process in self.processes:
            if process.poll() is None:
                process.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + grace_s
        for process in self.processes:
            try:
                process.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
        for name in reversed(self._namespaces):
            subprocess.run(["ip", "netns", "del", name], capture_output=True)
            shutil.rmtree(NETNS_ETC / name, ignore_errors=True)
        self._namespaces.clear()
