"""D-SLAM (Wang, Huang, Dissanayake, "Implementation Issues and Experimental Evaluation of D-SLAM"):
a static, exactly sparse information-filter map of absolute landmark positions, fed by the shift- and
rotation-invariant part z_map of every robot's scans, and a 3-dof localization per robot by covariance
intersection.

- :mod:`services.dslam.config` — :class:`DslamConfig`, the core's settings
- :mod:`services.dslam.recast` — z_map and its covariance (eqs. 3, 4, 7-9)
- :mod:`services.dslam.information_filter` — the sparse information matrix and vector, updates (eq. 10),
  recovery of the mean and of covariance columns by warm-started PCG
- :mod:`services.dslam.localization` — process-model and observation estimates, covariance intersection
- :mod:`services.dslam.core` — the filter :class:`DSlam` (phases I/II, tentative list, association) and
  ``make_estimator``
- :mod:`services.dslam.service` — ``fleetslam dslam``, the Zenoh shell (the only module that imports Zenoh)
"""
