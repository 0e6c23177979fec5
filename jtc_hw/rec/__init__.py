"""Recordings of what the robot did: rosbag2 directories with MCAP storage, and plots of them.

``bag`` turns the socket's ``state`` events (and ``get_status`` replies) into ROS 2 messages and
writes them with ``rosbags``; ``plot`` draws a recording with matplotlib; ``flight`` and
``continuous`` are the daemon's recorders (its API process runs them). The ``jtc-hw record``
and ``jtc-hw plot`` commands are ``jtc_hw.cli.record``. Both libraries are optional extras
(``jtc_hw[record]``, ``jtc_hw[plot]``) imported lazily, so ``import jtc_hw`` and the daemon work
without them. See ``docs/recording.md``.
"""
