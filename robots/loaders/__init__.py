"""Real data sets as :class:`~robots.dataset.Dataset`: MR.CLAM, Victoria Park, the ACFR car park.

One entry point, :func:`load_dataset`, parses a spec:

- ``mrclam:PATH`` (all five robots) or ``mrclam:PATH:N`` (robot N only, for a replay robot),
- ``victoria-park:PATH``, ``car-park:PATH``,
- ``mcap:FILE``: a fleet recorded by ``fleetslam record`` (every recorded robot),
- ``rosbag2:PATH``: a ROS 2 bag (folder or storage file) read through a fleet file, the option ``fleet`` (a path
  or a :class:`services.ros2.fleet.FleetFile`; default: the bag folder's ``fleet.yaml``),
- ``sim:WORLD`` (delegates to :func:`robots.simulator.simulate`).

A relative PATH that does not exist is looked up under :func:`data_root`;
an empty PATH means the data set's usual folder there. Data are read in place,
never copied.
"""

from __future__ import annotations

import os
from pathlib import Path

from robots.dataset import Dataset
from robots.loaders.car_park import detect_beacons, load_car_park
from robots.loaders.mcap import load_mcap
from robots.loaders.mrclam import load_mrclam
from robots.loaders.rosbag2 import load_rosbag2
from robots.loaders.victoria_park import load_victoria_park

REPO_ROOT = Path(__file__).resolve().parents[2]
DEFAULT_FOLDERS = {"mrclam": "utias_mrclam/MRCLAM_Dataset6", "victoria-park": "victoria_park", "car-park": "acfr_car_park"}
KINDS = ("mrclam", "victoria-park", "car-park", "mcap", "rosbag2", "sim")

__all__ = ["data_root", "load_dataset", "resolve_path", "load_mrclam", "load_victoria_park", "load_car_park",
           "detect_beacons", "load_mcap", "load_rosbag2", "KINDS"]


def data_root() -> Path | None:
    """The shared data folder: ``FLEETSLAM_DATA``, else ``<repo>/../shared/data``; None when it does not exist."""
    root = Path(os.environ.get("FLEETSLAM_DATA") or REPO_ROOT.parent / "shared" / "data")
    return root if root.is_dir() else None


def resolve_path(kind: str, path: str) -> Path:
    """The folder a spec names: as given if it exists, else under :func:`data_root`."""
    candidate = Path(path or DEFAULT_FOLDERS[kind]).expanduser()
    if candidate.exists() or candidate.is_absolute():
        return candidate
    root = data_root()
    if root is not None and (root / candidate).exists():
        return root / candidate
    return candidate


def load_dataset(spec: str, **options) -> Dataset:
    """Load the data set a spec names (see the module docstring).

    ``options`` go to the simulator for ``sim:`` (robots, seed, duration,
    robot_ids, ...), ``fleet`` to ``rosbag2:``, and to the loader otherwise (noise settings).
    """
    kind, sep, rest = spec.partition(":")
    if not sep or kind not in KINDS:
        raise ValueError(f"data set spec {spec!r}: expected one of {', '.join(k + ':...' for k in KINDS)}")
    if kind == "sim":
        from robots.simulator import simulate

        return simulate(rest, **options)
    if kind == "mrclam":
        path, robots = rest, None
        head, colon, tail = rest.rpartition(":")
        if colon and tail.isdigit():
            path, robots = head, [int(tail)]
        return load_mrclam(resolve_path(kind, path), robots=robots, **options)
    if kind == "mcap":
        return load_mcap(rest)
    if kind == "rosbag2":
        return load_rosbag2(rest, **options)
    if kind == "victoria-park":
        return load_victoria_park(resolve_path(kind, rest), **options)
    return load_car_park(resolve_path(kind, rest), **options)
