"""The daemon as a ROS 2 node over rmw_zenoh (placeholder of helper A; helper D owns this file)."""
