"""The warm-up compiles every kernel for the argument types the services pass: a run after it compiles nothing
more, so no live service's first scans wait for the compiler (numba compiles once per distinct argument type,
read-only arrays included)."""

from __future__ import annotations

import pytest

from central.fastslam import kernels as fastslam_kernels
from robots import kernels as robot_kernels
from robots.simulator import simulate
from schemas.contract import RunOptions
from services.association import kernels as association_kernels
from services.compiled import warm_up
from services.mcl import kernels as mcl_kernels
from services.offline import run_estimator


def compiled_signatures() -> dict[str, int]:
    """Signatures compiled so far per kernel of every group."""
    found = {}
    for module in (association_kernels, fastslam_kernels, mcl_kernels, robot_kernels):
        for name, value in vars(module).items():
            if hasattr(value, "signatures"):
                found[f"{module.__name__}.{name}"] = len(value.signatures)
    return found


@pytest.mark.parametrize("estimator, settings", [("fastslam", {}), ("fastslam", {"association": "nn"}),
                                                 ("fastslam", {"association": "mht"}), ("dslam", {}),
                                                 ("mcl", {"variant": "csrl"})])
def test_a_run_without_ids_compiles_nothing_after_the_warm_up(estimator, settings):
    warm_up()
    before = compiled_signatures()
    data = simulate("arena", robots=2, seed=2, duration=12.0, clutter_rate=0.3)
    landmarks = data.landmarks if estimator == "mcl" else None  # MCL localizes on the world's map, with resetting
    run = run_estimator(data, RunOptions(estimator=estimator, association="unknown", particles=30, seed=1,
                                         settings=settings, landmarks=landmarks))
    assert run.events["scan"] > 100
    after = compiled_signatures()
    assert {name: (before.get(name), count) for name, count in after.items() if before.get(name) != count} == {}
