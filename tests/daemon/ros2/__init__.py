"""The ROS 2 (rmw_zenoh) tests, issue 25. A package so that its conftest.py is imported as
``ros2.conftest``, leaving the name ``conftest`` to tests/conftest.py (helpers import it)."""
