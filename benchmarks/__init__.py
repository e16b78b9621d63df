"""Benchmarks of fleetslam: scripts run as ``python benchmarks/NAME.py`` (see each one's docstring)."""
