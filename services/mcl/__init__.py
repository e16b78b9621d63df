"""Monte Carlo localisation on a landmark map (paper 004), and its service ``fleetslam mcl``.

- :mod:`~services.mcl.likelihood`: scan likelihood with unknown correspondence (best-matching landmark, clutter floor,
  negative information), vectorised over particles × observations × candidate landmarks.
- :mod:`~services.mcl.kld`: the KLD-sampling bound (Fox 2003, paper 004 eq. 2).
- :mod:`~services.mcl.resetting`: sensor resetting — poses drawn from a scan and the map.
- :mod:`~services.mcl.clustering`: grid clustering of the particles into hypotheses.
- :mod:`~services.mcl.resampling`: systematic and two-stage (cluster, then systematic) resampling.
- :mod:`~services.mcl.core`: the filter, in the variants mcl, kld, srl, kld_srl, csrl, cluster_kld_srl (tables 1-4).
- :mod:`~services.mcl.estimator`: the filter behind the estimator protocol (``fleetslam run --estimator mcl``).
- :mod:`~services.mcl.service`: the Zenoh service; :mod:`~services.mcl.scenarios`: runs shared by tests and benchmarks.
"""
