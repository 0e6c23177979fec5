"""Third-party libraries' loggers kept at WARNING, in both daemon processes.

canopen logs every PDO mapping and NMT change at INFO (nearly 200 lines for a six-drive CiA
402 start), python-can its interface set-up: noise to a user, useful when debugging a bus.
``jtc-hw -v`` sets :data:`VERBOSE_ENV` so the daemon it starts (and its loop process, which
inherits the environment) keeps their INFO lines.
"""

from __future__ import annotations

import logging
import os

THIRD_PARTY_LOGGERS = ("canopen", "can")
"""Loggers set to WARNING unless :data:`VERBOSE_ENV` is set."""

VERBOSE_ENV = "JTC_HW_VERBOSE"
"""Environment variable: non-empty keeps the third-party loggers at the root's level."""


def quiet_third_party_loggers() -> None:
    """Raise :data:`THIRD_PARTY_LOGGERS` to WARNING unless ``$JTC_HW_VERBOSE`` is set.

    A logger already set higher (e.g. ERROR for socketcand's split-frame warnings) keeps it.
    """
    if os.environ.get(VERBOSE_ENV):
        return
    for name in THIRD_PARTY_LOGGERS:
        logger = logging.getLogger(name)
        logger.setLevel(max(logger.level, logging.WARNING))
