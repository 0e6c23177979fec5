"""The daemon as upstream's joint_trajectory_controller in a ROS 2 graph over rmw_zenoh
(``daemon.ros2``, docs/ros2.md): ``node`` is the transport; ``types`` and ``wire`` say what
rmw_zenoh puts on the wire, ``cdr`` decodes large goals into numpy columns, ``actions`` keeps
the action server's books and ``messages`` builds what is published."""
