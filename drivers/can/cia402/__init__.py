"""CANopen CiA 402 drives: codec (statusword / controlword, PDOs, NMT; no I/O), hardware (kind
``can-cia402``) and emulator; ``jtc_hw_drive.eds`` is the emulated drive's object dictionary."""
