"""The baselines every estimator is compared with (numeric cores, no Zenoh):

- :mod:`services.baselines.dead_reckoning` — dead reckoning, registered as ``odometry``
- :mod:`services.baselines.ekf_slam` — single-robot EKF-SLAM with pluggable data association, registered as ``ekf``
"""
