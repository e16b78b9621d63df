"""Centralised multi-robot FastSLAM (Howard, "Multi-robot simultaneous localization and mapping using particle
filters"): the numeric core, vectorised over particles (:mod:`central.fastslam.core`).

``core.make_estimator(options, infos)`` builds it for ``fleetslam run --estimator fastslam`` and the benchmarks;
the ``fleetslam central`` service (:mod:`central.service`) wraps it.
"""
