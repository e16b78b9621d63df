"""The processes without kernels load neither numba nor scipy: together they cost a process about 60 MB and half a
second, and a fleet runs a router, a monitor, a world, an evaluator and a process per robot. Importing
``schemas.config`` (every process reads its settings) once pulled both in through FastSLAM's re-acquisition rule,
and the service shell through the kernels' warm-up."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

LIGHT = ["services.router", "robots.process", "robots.truth", "services.monitor", "services.evaluation.service",
         "services.viz.service", "services.record", "services.launcher", "schemas.config"]


@pytest.mark.parametrize("module", LIGHT)
def test_a_process_without_kernels_imports_neither_numba_nor_scipy(module):
    code = ("import importlib, sys; importlib.import_module(sys.argv[1]); "
            "print(sorted(m for m in ('numba', 'scipy') if m in sys.modules))")
    result = subprocess.run([sys.executable, "-c", code, module], cwd=ROOT, capture_output=True, text=True,
                            timeout=120, env={"PATH": "/usr/bin:/bin", "PYTHONPATH": str(ROOT)})
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "[]"


def test_a_service_with_kernels_does_import_them():
    """The check can fail: FastSLAM's service loads numba."""
    code = "import central.service, sys; print('numba' in sys.modules)"
    result = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120,
                            env={"PATH": "/usr/bin:/bin", "PYTHONPATH": str(ROOT)})
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "True"
