"""CAN motors through python-can: one subpackage per protocol (``mit``, ``cia402``: codec,
hardware, emulator), and what they share: ``bus`` (python-can), ``emulation`` (the emulators'
threads and timers), ``socketcand`` (the server) and ``emulator`` (``jtc-hw emulate can``)."""
