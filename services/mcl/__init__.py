"""Monte Carlo localization on a landmark map (Sehestedt and Schneider, "Monte Carlo Localization in Highly
Symmetric Environments"), and its service ``fleetslam mcl``.

- :mod:`~services.mcl.config`: :class:`~services.mcl.config.MclConfig`, the filter's settings.
- :mod:`~services.mcl.likelihood`: scan likelihood with unknown correspondence (best-matching landmark, clutter floor,
  negative information), vectorized over particles × observations × candidate landmarks.
- :mod:`~services.mcl.kld`: the KLD-sampling bound (Fox 2003; eq. 2 of the paper).
- :mod:`~services.mcl.resetting`: sensor resetting — poses drawn from a scan and the map.
- :mod:`~services.mcl.clustering`: grid clustering of the particles into hypotheses.
- :mod:`~services.mcl.resampling`: two-stage (cluster, then systematic) resampling.
- :mod:`~services.mcl.core`: the filter of one robot, in the variants mcl, kld, srl, kld_srl, csrl, cluster_kld_srl
  (tables 1-4).
- :mod:`~services.mcl.fleet`: one filter per robot on a shared map, for the service and for
  ``fleetslam run --estimator mcl`` (:func:`~services.mcl.fleet.make_estimator`).
- :mod:`~services.mcl.service`: the Zenoh service.
"""
