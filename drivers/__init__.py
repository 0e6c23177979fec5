"""Hardware drivers for jtc_hw, one subpackage per kind, each with its protocol emulator.

The source folder is ``drivers/``; it installs as ``jtc_hw.drivers`` (see ``pyproject.toml``) so
that it cannot collide with another distribution's top-level ``drivers`` package.
"""
