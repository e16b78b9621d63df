"""Data association (paper 000 and JCBB): core, solvers, the EKF-SLAM baseline and the ``fleetslam assoc`` queryable."""
