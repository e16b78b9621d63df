"""ROS 2 robots in fleetslam: the fleet file, the message conversions, the live bridge over rmw_zenoh."""
