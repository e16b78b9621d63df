"""Live and recorded views of the fleet in Rerun.

- :mod:`~services.viz.config`: :class:`~services.viz.config.VizConfig`, what is drawn and how often.
- :mod:`~services.viz.scene`: pure functions and :class:`~services.viz.scene.Scene`, from decoded messages (or an
  offline run) to Rerun archetypes at entity paths; no Zenoh, no I/O.
- :mod:`~services.viz.recording`: opens a Rerun recording on its sinks (native viewer, web viewer, .rrd file).
- :mod:`~services.viz.service`: ``fleetslam viz``, the thin Zenoh shell.
"""
