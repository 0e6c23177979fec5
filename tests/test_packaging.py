"""A wheel holds every subpackage: ``pyproject.toml`` lists packages explicitly.

An editable install finds a subpackage missing from the list anyway (it maps the folder), so
only a real ``pip install .`` would show the gap, on a user's machine. This compares the list
with the folders that hold an ``__init__.py``.
"""

from __future__ import annotations

import sys

if sys.version_info >= (3, 11):
    import tomllib
else:  # Python 3.10: the same parser, published as tomli (the test extra installs it there)
    import tomli as tomllib

from conftest import ROOT


def test_every_subpackage_is_listed_for_the_wheel() -> None:
    setuptools = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    listed = set(setuptools["packages"])
    sources = {"jtc_hw": ROOT / "jtc_hw", "jtc_hw.drivers": ROOT / "drivers"}
    found = set()
    for name, folder in sources.items():
        for init in folder.rglob("__init__.py"):
            relative = init.parent.relative_to(folder).parts
            found.add(".".join((name, *relative)))
    assert found == listed, f"missing from pyproject: {found - listed}; stale: {listed - found}"


def test_every_public_name_of_the_packages_imports() -> None:
    import importlib

    for package in ("jtc_hw", "jtc_hw.controller", "jtc_hw.hardware", "jtc_hw.api"):
        module = importlib.import_module(package)
        missing = [name for name in module.__all__ if not hasattr(module, name)]
        assert not missing, f"{package}.__all__ names what it does not define: {missing}"
