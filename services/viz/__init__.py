"""Live and recorded views of the fleet in Rerun.

- :mod:`~services.viz.config`: :class:`~services.viz.config.VizConfig`, what is drawn and how often.
- :mod:`~services.viz.scene`: pure functions and :class:`~services.viz.scene.Scene`, from decoded messages (or an
  offline run) to Rerun archetypes at entity paths; no Zenoh, no I/O.
- :mod:`~services.viz.recording`: opens a Rerun recording on its sinks (native viewer, web viewer, .rrd file).
- :mod:`~services.viz.service`: ``fleetslam viz``, the thin Zenoh shell.
"""

from importlib.util import find_spec

INSTALL_HINT = "pip install 'fleetslam[viz]' (make demo and make test install it; the Docker image leaves it out)"


def rerun_missing() -> str | None:
    """Why Rerun views cannot be made here (rerun-sdk is the optional ``viz`` extra), or None when they can."""
    return None if find_spec("rerun") is not None else f"rerun-sdk is not installed: {INSTALL_HINT}"
