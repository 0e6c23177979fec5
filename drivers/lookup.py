"""Looking a name up in a driver's tables: the error and its did-you-mean hint.

Both serial-servo drivers (Dynamixel, Feetech) resolve register and model names typed in
configuration files; a miss raises a ``KeyError`` subclass (so ``except KeyError`` still works)
whose message reads as a sentence rather than as ``KeyError``'s quoted repr.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable

__all__ = ["NamedKeyError", "did_you_mean"]


class NamedKeyError(KeyError):
    """A ``KeyError`` whose ``str()`` is its message, unquoted."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else "unknown name"


def did_you_mean(name: str, known: Iterable[str]) -> str:
    """`` (did you mean 'x'?)`` for the known name closest to ``name``, or ``""``."""
    close = difflib.get_close_matches(name, list(known), n=1)
    return f" (did you mean {close[0]!r}?)" if close else ""
