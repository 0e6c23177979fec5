"""Dynamixel X-series servos over Protocol 2.0: driver (dynamixel-sdk) and pty emulator."""
