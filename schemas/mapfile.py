"""The map file: a landmark map saved by one session and loaded by the next (``--map-out`` / ``--map``).

A JSON document, version 1::

    {"format": "fleetslam-map", "version": 1, "frame": "world",
     "created": "2025-01-01T12:00:00+00:00",
     "source": {"estimator": "fastslam", "association": "known", ...},
     "landmarks": [{"id": 7, "mean": [x, y], "cov": [[sxx, sxy], [sxy, syy]], "hits": 12}, ...]}

- ``frame``: the name of the frame the means are in: ``world``, the session's world frame (DESIGN §3: the
  start pose of the first robot with a known start pose, or the first robot to scan); a session started from
  the file keeps it.
- ``source``: what made the map (estimator, association, settings, data set, robots); free-form, for people.
- ``landmarks``: ``id`` (the landmark's id: the scans' ids with known association; null when the estimator has
  none), ``mean`` (m), ``cov`` (the landmark's marginal covariance, m²: symmetric, positive definite; the
  cross-covariances between landmarks are not kept), ``hits`` (times associated, null when unknown).

:func:`save_map` writes atomically (a temporary file beside the target, fsync, rename): a reader sees the old
file or the new one, never half of one. :func:`load_map` refuses a file that is not JSON (corrupt, truncated),
of another format or version, or with a bad landmark (wrong shape, NaN, a covariance that is not one), with a
one-line :class:`MapFileError`; nothing is half-loaded.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from schemas.contract import MapView

FORMAT = "fleetslam-map"
VERSION = 1


class MapFileError(ValueError):
    """A map file that cannot be read or written; the message is one line with the path and the reason."""


class Landmark(BaseModel):
    """One landmark: id (or null), mean ``[x, y]``, marginal covariance ``[[..],[..]]``, hits (or null)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    id: int | None = None
    mean: tuple[float, float]
    cov: tuple[tuple[float, float], tuple[float, float]]
    hits: int | None = Field(None, ge=0)

    @field_validator("mean")
    @classmethod
    def _finite_mean(cls, value):
        if not all(math.isfinite(v) for v in value):
            raise ValueError("mean holds NaN or infinity")
        return value

    @field_validator("cov")
    @classmethod
    def _covariance(cls, value):
        cov = np.asarray(value, float)
        if not np.all(np.isfinite(cov)):
            raise ValueError("cov holds NaN or infinity")
        if not np.isclose(cov[0, 1], cov[1, 0], rtol=1e-6, atol=1e-12):
            raise ValueError("cov is not symmetric")
        if cov[0, 0] <= 0 or cov[0, 0] * cov[1, 1] - cov[0, 1] * cov[1, 0] <= 0:
            raise ValueError("cov is not positive definite")
        return value


class MapFile(BaseModel):
    """The whole file (see the module docstring)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    format: Literal["fleetslam-map"] = FORMAT
    version: Literal[1] = VERSION
    frame: str = Field("world", min_length=1)
    created: datetime
    source: dict[str, Any] = Field(default_factory=dict)
    landmarks: list[Landmark]

    @model_validator(mode="after")
    def _ids(self) -> "MapFile":
        ids = [lm.id for lm in self.landmarks]
        given = [i for i in ids if i is not None]
        if given and len(given) != len(ids):
            raise ValueError("either every landmark has an id or none has")
        if len(set(given)) != len(given):
            raise ValueError("landmark ids repeat")
        return self

    # ------------------------------------------------------------ arrays
    @property
    def has_ids(self) -> bool:
        return bool(self.landmarks) and self.landmarks[0].id is not None

    def view(self) -> MapView:
        """Means ``(n, 2)``, covariances ``(n, 2, 2)`` and ids ``(n,)`` (None when the landmarks have none)."""
        means = np.array([lm.mean for lm in self.landmarks], float).reshape(-1, 2)
        covs = np.array([lm.cov for lm in self.landmarks], float).reshape(-1, 2, 2)
        ids = np.array([lm.id for lm in self.landmarks], np.int64) if self.has_ids else None
        return MapView(means, covs, ids)

    def hits(self) -> np.ndarray | None:
        """Hit counts ``(n,)``, or None when some landmark's is unknown."""
        if any(lm.hits is None for lm in self.landmarks):
            return None
        return np.array([lm.hits for lm in self.landmarks], np.int64)


def map_from_view(view: MapView, source: dict[str, Any] | None = None, frame: str = "world",
                  hits: np.ndarray | None = None) -> MapFile:
    """The file model of an estimator's map (:class:`MapFileError` if a value is not finite or a covariance bad)."""
    means = np.asarray(view.means, float).reshape(-1, 2)
    n = means.shape[0]
    covs = np.asarray(view.covs, float).reshape(n, 2, 2)
    ids = None if view.ids is None else np.asarray(view.ids).reshape(-1)
    if (ids is not None and ids.size != n) or (hits is not None and len(hits) != n):
        raise MapFileError(f"map of {n} landmarks with {len(ids) if ids is not None else len(hits)} ids or hit counts")
    try:
        return MapFile.model_validate({"created": datetime.now(timezone.utc), "frame": frame, "source": source or {},
                                       "landmarks": [{"id": None if ids is None else int(ids[k]),
                                                      "mean": means[k].tolist(),
                                                      "cov": (0.5 * (covs[k] + covs[k].T)).tolist(),
                                                      "hits": None if hits is None else int(hits[k])}
                                                     for k in range(n)]})
    except ValidationError as error:
        raise MapFileError(f"cannot save the map: {_first_problem(error)}") from None


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def save_map(path: str | Path, view: MapView, source: dict[str, Any] | None = None, frame: str = "world",
             hits: np.ndarray | None = None) -> MapFile:
    """Write the map atomically to ``path`` (temporary file in the same folder, fsync, rename); the model written."""
    document = map_from_view(view, source, frame, hits)
    text = _to_json(document)
    target = Path(path)
    folder = target.parent if str(target.parent) else Path(".")
    try:
        folder.mkdir(parents=True, exist_ok=True)
        handle, temporary = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=folder)
        os.chmod(temporary, 0o666 & ~_umask())  # mkstemp makes it private; a map file is as readable as any other
        try:
            with os.fdopen(handle, "w", encoding="utf-8") as out:
                out.write(text)
                out.flush()
                os.fsync(out.fileno())
            os.replace(temporary, target)
        except BaseException:
            Path(temporary).unlink(missing_ok=True)
            raise
        directory = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(directory)
        finally:
            os.close(directory)
    except OSError as error:
        raise MapFileError(f"{path}: cannot write the map: {error.strerror or error}") from None
    return document


def _to_json(document: MapFile) -> str:
    """The document as JSON text: the header indented, one landmark per line."""
    body = document.model_dump(mode="json")
    landmarks = [json.dumps(landmark, allow_nan=False) for landmark in body.pop("landmarks")]
    head = json.dumps(body, indent=1, allow_nan=False).removesuffix("\n}")
    rows = "".join(f"\n  {row}," for row in landmarks).removesuffix(",")
    return f'{head},\n "landmarks": [{rows}\n ]\n}}\n'


def load_map(path: str | Path) -> MapFile:
    """Read and check a map file; :class:`MapFileError` (one line: the path and the reason) when it is refused."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as error:
        raise MapFileError(f"{path}: cannot read: {getattr(error, 'strerror', None) or error}") from None
    try:
        raw = json.loads(text, parse_constant=_refuse_constant)
    except json.JSONDecodeError as error:
        raise MapFileError(f"{path}: not a JSON document, truncated or corrupt ({error.msg} at line "
                           f"{error.lineno} column {error.colno})") from None
    except ValueError as error:
        raise MapFileError(f"{path}: {error}") from None
    if not isinstance(raw, dict) or raw.get("format") != FORMAT:
        found = raw.get("format") if isinstance(raw, dict) else type(raw).__name__
        raise MapFileError(f"{path}: not a {FORMAT} file (format {found!r})")
    if raw.get("version") != VERSION:
        raise MapFileError(f"{path}: {FORMAT} version {raw.get('version')!r} is not supported (this fleetslam "
                           f"reads version {VERSION})")
    try:
        return MapFile.model_validate(raw)
    except ValidationError as error:
        raise MapFileError(f"{path}: {_first_problem(error)}") from None


def _refuse_constant(name: str):
    raise ValueError(f"the file holds {name}, which is not a number")


def _first_problem(error: ValidationError) -> str:
    """``where: what`` of the first problem pydantic found (``landmarks.3.cov``: ...)."""
    first = error.errors()[0]
    where = ".".join(str(part) for part in first["loc"])
    message = first["msg"].removeprefix("Value error, ")
    return f"{where}: {message}" if where else message
