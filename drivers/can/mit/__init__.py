"""MIT-mode CAN motors (mini-cheetah, CubeMars AK, Damiao): codec (the frames, no I/O),
hardware (kind ``can-mit``) and emulator."""
