"""Data association (Zhang, Xie, Adams, "An Efficient Data Association Approach to Simultaneous Localization and
Map Building", and JCBB): core and solvers (numeric, no Zenoh), the ``fleetslam assoc`` queryable and its client."""
