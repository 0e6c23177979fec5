"""The first hour's friction points of ``jtc-hw``, each checked: help text everywhere with the
exit codes, ``--version``, ``check`` refusing what ``run`` refuses (each error once), every
example configuration with its own socket, third-party loggers quiet unless ``-v``."""

from __future__ import annotations

import argparse
import logging
import os
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml

from jtc_hw import __version__
from jtc_hw.cli import main
from jtc_hw.cli.common import EXIT_BAD_INPUT
from jtc_hw.cli.parser import build_parser
from jtc_hw.daemon.logs import THIRD_PARTY_LOGGERS, VERBOSE_ENV, quiet_third_party_loggers
from jtc_hw.daemon.robot import load_robot

from conftest import ROOT

CONFIGS = sorted((ROOT / "config").glob("*.yaml"))


def _subcommands() -> Iterator[tuple[str, argparse.ArgumentParser, str | None]]:
    parser = build_parser()
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help for a in action._choices_actions}
            for name, sub in action.choices.items():
                yield name, sub, helps.get(name)


def test_every_subcommand_and_argument_has_help_text() -> None:
    missing = []
    parser = build_parser()
    for action in parser._actions:
        if not action.help and not isinstance(action, argparse._SubParsersAction):
            missing.append(f"jtc-hw {'/'.join(action.option_strings)}")
    commands = list(_subcommands())
    assert len(commands) >= 15
    for name, sub, summary in commands:
        if not summary or not summary.strip():
            missing.append(f"{name} (summary)")
        if not sub.description or not sub.description.strip():
            missing.append(f"{name} (description)")
        for action in sub._actions:
            if not action.help or not action.help.strip():
                missing.append(f"{name} {action.dest}")
    assert missing == []


def test_every_subcommands_help_states_its_exit_codes(
    capsys: pytest.CaptureFixture[str],
) -> None:
    for name, _, _ in _subcommands():
        with pytest.raises(SystemExit) as exit_:
            main([name, "--help"])
        assert exit_.value.code == 0
        text = " ".join(capsys.readouterr().out.split())
        assert "Exit status: 0 " in text, name
    # A client command's help says what 2 and 3 mean; only a goal's (send) speaks of 1.
    with pytest.raises(SystemExit):
        main(["state", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "1 the goal aborted or was canceled" not in text
    assert "or the daemon answered and refused the request" in text
    assert "3 no daemon answers" in text
    with pytest.raises(SystemExit):
        main(["send", "--help"])
    assert "1 the goal aborted or was canceled" in " ".join(capsys.readouterr().out.split())


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out == f"jtc-hw {__version__}\n"


def test_each_example_configuration_has_its_own_socket() -> None:
    # The real robots' examples name none: under the unit they serve /run/jtc-hw/jtc-hw.sock
    # (docs/systemd.md; tests/daemon/test_systemd_unit.py).
    named = [p for p in CONFIGS if "socket:" in re.sub(r"#.*", "", p.read_text())]
    sockets = {path.name: load_robot(path).daemon.socket for path in named}
    assert len(sockets) >= 5
    assert len(set(sockets.values())) == len(sockets), sockets
    for name, socket in sockets.items():
        assert Path(socket).parent.is_dir(), (name, socket)  # a manual run can create it


def test_readme_client_example_uses_the_socket_of_the_config_it_runs() -> None:
    text = (ROOT / "README.md").read_text()
    mirror = load_robot(ROOT / "config" / "mirror-arm.yaml").daemon.socket
    assert "jtc-hw run config/mirror-arm.yaml" in text
    assert f'Client.connect("{mirror}")' in text


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("lag_s", "slow", "hardware[0].params.lag_s: expected a number, got 'slow' (str)"),
        (
            "baudrate", 1000000,
            "hardware[0].params.baudrate: unknown parameter 'baudrate' of dynamixel hardware "
            "'arm'; did you mean 'baud_rate'?",
        ),
    ],
)
def test_check_refuses_what_run_refuses_with_the_same_message_once(
    tmp_path: Path, key: str, value: object, message: str
) -> None:
    """``check`` and ``run`` go through the same ``create_hardware_set``: the same error, once
    each, exit 2 (run before opening any device or socket)."""
    source = ROOT / "config" / (
        "mirror-arm.yaml" if key == "lag_s" else "dynamixel-arm-emulated.yaml"
    )
    config = yaml.safe_load(source.read_text())
    config["hardware"][0]["params"][key] = value
    config["daemon"]["socket"] = str(tmp_path / "d.sock")
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(config))
    for command in ("check", "run"):
        done = subprocess.run(
            [sys.executable, "-m", "jtc_hw", command, str(path)],
            capture_output=True, text=True, timeout=60, cwd=ROOT, stdin=subprocess.DEVNULL,
        )
        assert done.returncode == EXIT_BAD_INPUT, (command, done.stdout, done.stderr)
        assert done.stderr.count(message) == 1, (command, done.stderr)
        assert "Traceback" not in done.stderr and "OK" not in done.stdout
    assert not (tmp_path / "d.sock").exists()


@pytest.fixture
def third_party_levels() -> Iterator[None]:
    saved = {name: logging.getLogger(name).level for name in THIRD_PARTY_LOGGERS}
    yield
    for name, level in saved.items():
        logging.getLogger(name).setLevel(level)


@pytest.mark.usefixtures("third_party_levels")
def test_third_party_loggers_are_quiet_unless_verbose(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(VERBOSE_ENV, raising=False)
    for name in THIRD_PARTY_LOGGERS:
        logging.getLogger(name).setLevel(logging.NOTSET)
    logging.getLogger("can").setLevel(logging.ERROR)  # set higher elsewhere: kept
    quiet_third_party_loggers()
    assert logging.getLogger("canopen").level == logging.WARNING
    assert not logging.getLogger("canopen.pdo.base").isEnabledFor(logging.INFO)
    assert logging.getLogger("can").level == logging.ERROR
    logging.getLogger("canopen").setLevel(logging.NOTSET)
    monkeypatch.setenv(VERBOSE_ENV, "1")  # what jtc-hw -v sets for the daemon it starts
    quiet_third_party_loggers()
    assert logging.getLogger("canopen").level == logging.NOTSET


def test_verbose_option_reaches_the_processes_the_cli_starts(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv(VERBOSE_ENV, "")  # restored (unset) after the test; empty: not verbose
    main(["-v", "check", str(ROOT / "config" / "mirror-arm.yaml")])
    assert capsys.readouterr().out.startswith(f"{ROOT / 'config' / 'mirror-arm.yaml'}: OK")
    assert os.environ.get(VERBOSE_ENV) == "1"
