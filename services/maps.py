"""Maps that outlive a run: start an estimator from a saved map (``--map``), save its map (``--map-out``).

The file format is :mod:`schemas.mapfile`. Here is what the runners and service shells share:

- :func:`seed_estimator`: put a saved map into a mapping estimator that offers
  ``load_landmarks(ids, means, covs, hits)`` (the central FastSLAM, D-SLAM), in the saved frame. Landmarks
  without ids get 0, 1, 2, ... (refused with known association, where ids are the scans' landmark ids).
- :func:`options_with_map`: the :class:`~schemas.contract.RunOptions` of an estimator started from a file.
- :class:`MapSaver`: writes an estimator's map to ``--map-out`` (atomically), at the end and, in a service,
  every ``map_out_period_s``.
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace
from typing import Any

import numpy as np

from schemas.contract import MapView, RunOptions
from schemas.mapfile import MapFile, MapFileError, load_map, save_map

log = logging.getLogger("fleetslam.maps")


def seed_estimator(estimator, view: MapView, hits: np.ndarray | None, association: str) -> int:
    """Load the saved map ``view`` into ``estimator``; the number of landmarks loaded (:class:`MapFileError`
    when the estimator cannot start from a map, or known association gets a map without ids)."""
    if not hasattr(estimator, "load_landmarks"):
        raise MapFileError(f"{type(estimator).__name__} cannot start from a saved map")
    n = len(view.means)
    if view.ids is None and association == "known":
        raise MapFileError("the map has no landmark ids, and known association needs them (the scans' ids name "
                           "landmarks): start it with --association unknown")
    ids = np.arange(n, dtype=np.int64) if view.ids is None else np.asarray(view.ids, np.int64)
    estimator.load_landmarks(ids, view.means, view.covs, hits)
    return n


def options_with_map(options: RunOptions, saved: MapFile) -> RunOptions:
    """``options`` carrying the saved map: the map a localizer (mcl) localizes against, or the one a mapping
    estimator starts from (covariances and hits given)."""
    view = saved.view()
    return replace(options, landmarks=view.means, landmark_ids=view.ids, landmark_covs=view.covs,
                   landmark_hits=saved.hits())


def seed_from_options(estimator, options: RunOptions) -> None:
    """Start a mapping estimator from the saved map in ``options`` (a map with covariances), if there is one."""
    if options.landmark_covs is None or options.landmarks is None or options.estimator == "mcl":
        return
    view = MapView(np.asarray(options.landmarks, float), np.asarray(options.landmark_covs, float), options.landmark_ids)
    loaded = seed_estimator(estimator, view, options.landmark_hits, options.association)
    log.info("%s starts from a saved map of %d landmarks", options.estimator, loaded)


def seed_from_file(estimator, path: str | None, association: str) -> int:
    """Start a service's estimator from the saved map at ``path`` (nothing without one); the landmarks loaded
    (:class:`MapFileError` when the file is refused)."""
    prior = load_prior(path)
    return 0 if prior is None else seed_estimator(estimator, prior.view(), prior.hits(), association)


def serve_mapping_service(build) -> int:
    """Build a mapping service (``build()``) and serve it; a refused ``--map`` file ends it with one line (exit 2)."""
    try:
        service = build()
    except MapFileError as error:
        log.error("cannot start: %s", error)
        return 2
    return service.serve()


def load_prior(path: str | None) -> MapFile | None:
    """The saved map at ``path`` (None without one), logged; :class:`MapFileError` when it is refused."""
    if not path:
        return None
    saved = load_map(path)
    log.info("map %s: %d landmarks (%s ids), frame %s, made by %s on %s", path, len(saved.landmarks),
             "with" if saved.has_ids else "without", saved.frame, saved.source.get("estimator", "?"),
             saved.created.isoformat(timespec="seconds"))
    return saved


class MapSaver:
    """Writes an estimator's map to ``path`` at most every ``period_s`` (0: only when asked with ``force``)."""

    def __init__(self, path: str | None, source: dict[str, Any], period_s: float = 0.0):
        self.path = path
        self.source = source
        self.period_s = period_s
        self.last = time.monotonic()
        self.saved = 0

    def due(self) -> bool:
        return bool(self.path) and self.period_s > 0 and time.monotonic() - self.last >= self.period_s

    def save(self, view: MapView) -> bool:
        """Write ``view`` now; False (logged) when it cannot be written."""
        if not self.path:
            return False
        self.last = time.monotonic()
        try:
            save_map(self.path, view, self.source)
        except MapFileError as error:
            log.error("map not saved: %s", error)
            return False
        self.saved += 1
        log.info("map of %d landmarks saved to %s", len(view.means), self.path)
        return True
