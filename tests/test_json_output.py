"""JSON is typed, and there is always a document (issue 19, A.6): edge values are JSON
numbers (their exact text in a field of its own), and a command that fails with --json
prints a JSON object naming the error on standard output, with the usual exit code."""

from __future__ import annotations

import json
import socket

from click.testing import CliRunner

from ucom_tools.cli.main import cli


def closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_a_bus_error_with_json_is_a_json_object() -> None:
    port = closed_port()
    r = CliRunner().invoke(cli, ["init", "-i", "socketcand", "--host", "127.0.0.1",
                                 "--port", str(port), "-c", "CAN0", "--json"])
    assert r.exit_code == 4
    error = json.loads(r.stdout)["error"]
    assert error["kind"] == "bus error" and error["exit_code"] == 4
    assert f"127.0.0.1:{port}" in error["message"] and "refused" in error["message"]
    assert "bus error" in r.stderr  # the line for people stays


def test_bad_input_with_json_is_a_json_object_too() -> None:
    r = CliRunner().invoke(cli, ["srec", "info", "no-such.S", "--json"])
    assert r.exit_code == 3
    assert json.loads(r.stdout)["error"]["kind"] == "bad input"


def test_without_json_nothing_goes_to_standard_output() -> None:
    r = CliRunner().invoke(cli, ["srec", "info", "no-such.S"])
    assert r.exit_code == 3 and r.stdout == ""
