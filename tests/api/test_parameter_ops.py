"""Runtime parameters over the socket (issue 11 point 14): the ``get_parameters`` /
``set_parameters`` ops, ``Client`` methods and ``jtc-hw param``, against the real ``Server``
on the stand-in backend (the real controller on a simulated clock).

Reference: jtc_upstream_behaviour.md section 7 step 2 and 8.2 (when a change takes effect),
section 1 (read-only parameters).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from helpers.fake_backend import ServerThread

from jtc_hw.api import Client, RequestError
from jtc_hw.api.protocol import parse_request
from jtc_hw.api.requests import GetParameters, SetParameters
from jtc_hw.cli import main
from jtc_hw.cli.common import EXIT_BAD_INPUT, EXIT_OK

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources


def test_requests_are_parsed_strictly() -> None:
    """docs/protocol.md: ``names`` is a non-empty array of strings, ``parameters`` a non-empty
    object; the values themselves are the controller's to check."""
    assert parse_request({"op": "get_parameters"}) == GetParameters()
    assert parse_request({"op": "get_parameters", "names": ["cmd_timeout"]}) == GetParameters(
        None, ("cmd_timeout",)
    )
    assert parse_request(
        {"op": "set_parameters", "id": 3, "parameters": {"gains.j1.p": "x"}}
    ) == SetParameters(3, {"gains.j1.p": "x"})
    for bad, where in [
        ({"op": "get_parameters", "names": []}, "names: give at least one name"),
        ({"op": "get_parameters", "names": [1]}, "names[0]: expected a string"),
        ({"op": "get_parameters", "names": "cmd_timeout"}, "names: expected an array"),
        ({"op": "set_parameters"}, "missing required field 'parameters'"),
        ({"op": "set_parameters", "parameters": {}}, "parameters: expected a non-empty"),
        ({"op": "set_parameters", "parameters": [1]}, "parameters: expected a non-empty"),
    ]:
        with pytest.raises(RequestError, match=where.replace("[", r"\[").replace("]", r"\]")):
            parse_request(bad)


def test_client_reads_and_changes_parameters(client: Client, daemon: ServerThread) -> None:
    """Section 7 step 2: the change is applied by the controller and ``get_config`` shows it."""
    got = client.get_parameters(["gains.j1.p", "joints"])
    assert got["parameters"] == {"gains.j1.p": 0.0, "joints": ["j1", "j2"]}
    assert got["read_only"] == ["joints"]
    assert len(client.get_parameters()["parameters"]) > 20

    reply = client.set_parameters({"constraints.j2.goal": 0.02, "cmd_timeout": 1})
    assert reply["parameters"] == {"constraints.j2.goal": 0.02, "cmd_timeout": 1.0}
    assert reply["takes_effect"] == {
        "constraints.j2.goal": "next goal or trajectory",
        "cmd_timeout": "next activation",
    }
    assert reply["warnings"] == []
    backend = daemon.backend
    assert daemon.call(lambda: backend.ctrl.config.constraints.joints["j2"].goal) == 0.02
    assert client.get_config()["controller"]["constraints"]["j2"]["goal"] == 0.02


def test_refusals_are_bad_requests_naming_what_to_fix(client: Client) -> None:
    """Section 1: read-only parameters are refused, all named; a bad value reads as in the
    configuration file; nothing changes."""
    with pytest.raises(RequestError) as refused:
        client.set_parameters({"gains.j1.p": 2.0, "joints": ["a"], "update_rate": 50})
    assert refused.value.code == "bad_request"
    assert "read-only parameters joints, update_rate" in str(refused.value)
    with pytest.raises(RequestError, match=r"^constraints\.j1\.goal: must be >= 0, got -1$"):
        client.set_parameters({"constraints.j1.goal": -1})
    with pytest.raises(RequestError, match="did you mean 'goal_time'"):
        client.get_parameters(["constraints.goal_tme"])
    assert client.get_parameters(["gains.j1.p"])["parameters"] == {"gains.j1.p": 0.0}


def test_cli_param_get_and_set(
    daemon: ServerThread, sock: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``jtc-hw param``: VALUE is YAML; exit 2 for what the daemon refuses."""
    s = ["--socket", str(sock)]
    assert main(["param", "set", "gains.j1.p", "12", "allow_partial_joints_goal", "true", *s]) \
        == EXIT_OK
    out = capsys.readouterr().out
    assert "gains.j1.p                 12.0   takes effect: next cycle" in out
    assert "allow_partial_joints_goal  true   takes effect: next goal or trajectory" in out

    assert main(["param", "get", "gains.j1.p", "joints", *s]) == EXIT_OK
    assert capsys.readouterr().out.splitlines() == [
        "gains.j1.p  12.0",
        'joints      ["j1", "j2"]   (read-only)',
    ]
    assert main(["param", "get", "--json", "cmd_timeout", *s]) == EXIT_OK
    assert json.loads(capsys.readouterr().out) == {
        "parameters": {"cmd_timeout": 0.0}, "read_only": [],
    }

    assert main(["param", "set", "cmd_timeout", "0.5", *s]) == EXIT_OK
    assert "jtc-hw rearm" in capsys.readouterr().out  # when "next activation" comes here

    assert main(["param", "set", "interpolation_method", "none", *s]) == EXIT_BAD_INPUT
    assert "read-only parameter interpolation_method" in capsys.readouterr().err
    assert main(["param", "set", "gains.j1.p", "{a: 1}", *s]) == EXIT_BAD_INPUT
    assert "expected a scalar or a list" in capsys.readouterr().err
    assert main(["param", "set", "gains.j1.p", *s]) == EXIT_BAD_INPUT
    assert "NAME VALUE pairs" in capsys.readouterr().err
    assert main(["param", "get", "gains.j9.p", *s]) == EXIT_BAD_INPUT
    assert "'j9' is not a configured joint" in capsys.readouterr().err
