"""A receiver for the network tests: records what reaches it, one JSON line each.

Runs as its own process (inside a network namespace), built on the same
:class:`ServiceShell` as every service, so ``FLEETSLAM_SUBSCRIBER_RECOVERY``
switches it to the advanced subscriber exactly as it does for the services.
Lines, flushed at once so the test reads them while the fleet runs:

- ``{"t": wall time, "kind": "sample", "robot": rid, "stream": s, "seq": n}`` per robot stream message,
- ``{"t": ..., "kind": "alive" | "gone", "robot": rid}`` per liveliness change of a robot,
- ``{"t": ..., "kind": "stats", "key": key, "stats": ServiceStats as JSON}`` per service statistics,
- ``{"t": ..., "kind": "other", "key": key}`` per message on any other key (estimates, maps).

    python -m tests.integration.observer --out FILE
"""

from __future__ import annotations

import argparse
import asyncio
import json
import time

import zenoh

from schemas.codec import decode
from schemas.config import FleetSettings
from schemas.messages import GroundTruth, Odometry, Scan, ServiceStats
from services.runtime import ServiceShell

MODELS = {"odom": Odometry, "scan": Scan, "truth": GroundTruth}


class Observer(ServiceShell):
    name = "observer"

    def __init__(self, settings: FleetSettings, out: str):
        super().__init__(settings)
        self.out = open(out, "a", buffering=1)

    def setup(self, session: zenoh.Session) -> None:
        self.subscribe(self.keys.all_robots, "robot")
        self.subscribe(self.keys.everything, "other", recover=False)
        self._declared.append(session.liveliness().declare_subscriber(self.keys.alive_any, self._on_alive, history=True))

    def _on_alive(self, sample: zenoh.Sample) -> None:
        parsed = self.keys.parse_robot_key(str(sample.key_expr))
        if parsed:
            self.enqueue("alive", parsed[0], b"alive" if sample.kind == zenoh.SampleKind.PUT else b"gone")

    def _write(self, **row) -> None:
        self.out.write(json.dumps({"t": time.time(), **row}) + "\n")

    async def handle(self, tag: str, key: str, payload: bytes) -> None:
        if tag == "alive":
            self._write(kind=payload.decode(), robot=key)
            return
        parsed = self.keys.parse_robot_key(key)
        if tag == "other":
            if parsed is None and key.endswith("/stats"):
                self._write(kind="stats", key=key, stats=decode(payload, ServiceStats).model_dump(mode="json"))
            elif parsed is None:
                self._write(kind="other", key=key)
        elif parsed is not None and parsed[1] in MODELS:
            message = decode(payload, MODELS[parsed[1]])
            self._write(kind="sample", robot=parsed[0], stream=parsed[1], seq=message.seq)

    def on_stop(self) -> None:
        self.out.close()


def read_rows(path) -> list[dict]:
    """The observer's lines so far (a line being written is skipped)."""
    rows = []
    try:
        text = open(path).read()
    except FileNotFoundError:
        return rows
    for line in text.splitlines():
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return rows


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    asyncio.run(Observer(FleetSettings(), args.out).run())


if __name__ == "__main__":
    main()
