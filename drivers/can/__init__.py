"""CAN motors through python-can: MIT-mode and CANopen CiA 402 drivers, and their emulators."""
