"""``fleetslam world``: the world's true landmark map on ``{prefix}/world/truth``, under its own identity.

MCL (with ``--source truth``) localizes against this map and the evaluator
scores maps with it, so in a secured fleet no robot may write it: the router
lets only the user ``world`` put and answer on that key, and this process is
that user (``docker compose up`` and ``fleetslam demo`` start it; their robots
run with ``--no-publish-world``). The map is the simulated world's (drawn from
``--world`` and ``--seed``, as the robots draw it) or a data set's
(``--replay``). It is published once and then answered to every late joiner's
query until SIGINT/SIGTERM.
"""

from __future__ import annotations

import argparse
import logging

from schemas.codec import encode
from schemas.config import WorldSettings, add_settings_arguments, settings_from_args
from schemas.keys import Keys
from schemas.messages import WorldTruth
from schemas.transport import Shutdown, StreamPublisher, answer_with, run_command, session_scope, undeclare_all

log = logging.getLogger("fleetslam.world")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, WorldSettings)


def world_truth(settings: WorldSettings) -> WorldTruth:
    """The true map: the data set's (``replay``) or the simulated world's, as a robot of the same settings has it."""
    if settings.replay:
        from robots.loaders import load_dataset

        dataset = load_dataset(settings.replay)
        if dataset.landmarks is None:
            raise ValueError(f"--replay {settings.replay!r} holds no true landmark map")
        return WorldTruth(world=dataset.name, stamp=dataset.start_stamp, landmarks=dataset.landmarks,
                          landmark_ids=dataset.landmark_ids)
    from robots.worlds import make_world

    world = make_world(settings.world, settings.seed)
    return WorldTruth(world=f"sim:{world.name}", stamp=0.0, landmarks=world.landmarks, landmark_ids=world.landmark_ids)


def run(settings: WorldSettings, shutdown: Shutdown) -> int:
    """Publish the map once, answer queries for it until stopped; returns the number of landmarks."""
    truth = world_truth(settings)
    payload = encode(truth)
    key = Keys(settings.prefix).world_truth
    with session_scope(settings) as session:
        answer = answer_with(session, key, payload)
        publisher = StreamPublisher(session, key)
        try:
            publisher.put(payload)
            log.info("world map %s: %d landmarks on %s (and to late joiners) until stopped", truth.world,
                     len(truth.landmarks), key)
            shutdown.wait()
        finally:
            undeclare_all([publisher, answer])
    return len(truth.landmarks)


def main(args: argparse.Namespace) -> int:
    return run_command(run, settings_from_args(WorldSettings, args), log, "world", (OSError, ValueError))
