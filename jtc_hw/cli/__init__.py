"""``jtc-hw``: run the daemon, check a configuration, and talk to a running daemon.

Exit status: 0 success; 1 a goal ended without success (aborted, canceled); 2 bad input
(configuration, trajectory file), a socket whose listener is not trusted, a socket you may
not connect to (permission denied), or the daemon answered and refused (rejected goal, bad
request, not active); 3 only when no daemon answers (none running, no reply).

:mod:`.parser` builds the parser and maps what a command raises to its exit status. Each
command group is a module that adds its subcommands (``add_parsers``) and runs them (``cmd_*``):

- :mod:`.run`: ``run``, ``check`` (the daemon and its configuration)
- :mod:`.demo`: ``demo``;  :mod:`.emulate`: ``emulate``;  :mod:`.calibrate`: ``calibrate``
- :mod:`.goals`: ``send``, ``cancel`` (trajectory files);  :mod:`.state`: ``state``, ``query``
- :mod:`.motion`: ``stop``, ``rearm``, ``speed``, ``pause``, ``resume``
- :mod:`.params`: ``param``
- :mod:`.status`: ``status``, ``hardware``;  :mod:`.record`: ``record``, ``plot``
- :mod:`.fleet`: ``fleet`` (Zenoh)

What several of them share (exit statuses, the client options, the connection, the progress
of a goal) is in :mod:`.common`, the one module they import from the package: the command
modules never import each other (``pyproject.toml``'s contracts).
"""

from __future__ import annotations

from collections.abc import Sequence

__all__ = ["main"]


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``jtc-hw`` (the console script) and of ``python -m jtc_hw``."""
    # Start-up time: a daemon started by the console script imports this package again in its
    # loop process (multiprocessing's spawn runs the script), which must not load the commands,
    # the client and the recorders; they load here, when a command runs.
    from .parser import parse_and_run

    return parse_and_run(argv)
