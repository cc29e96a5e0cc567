"""The old names of renamed options and commands still work and say they are the old
names: ``fleet serve --fault`` (now ``--defect``), ``fleet faults`` (now ``fleet
defects``), so that scripts written for them do not break; neither is offered in help."""

from __future__ import annotations

import json

from click.testing import CliRunner

from tests.test_multiserve import STOP_S, served, until
from ucom_tools.cli.main import cli
from ucom_tools.virtual.board import mutants


def test_fault_is_the_old_name_of_defect_and_says_so() -> None:
    result = CliRunner().invoke(cli, ["fleet", "serve", "armar3", "--fault", "seq-from-one"])
    assert result.exit_code == 3
    assert "--fault is the old name of --defect" in result.stderr
    assert "--fault: unknown defect 'seq-from-one'; known: seq-from-zero" in result.output
    both = CliRunner().invoke(cli, ["fleet", "serve", "armar3", "--fault", "so-slow",
                                    "--defect", "so-slow"])
    assert both.exit_code == 2
    assert "--fault is the old name of --defect: give one of them" in both.output


def test_the_old_fault_option_serves_mutant_boards() -> None:
    with served("--processes", "1", "--fault", "seq-from-zero") as server:
        until(lambda: "mutant boards (seq-from-zero)" in " ".join(server.stderr().split()),
              what="the banner naming the defect")
        assert "--fault is the old name of --defect" in server.stderr()
        server.interrupt()
        assert server.wait(STOP_S) == 130, server.stderr()


def test_fleet_faults_is_the_old_name_of_fleet_defects_and_says_so() -> None:
    new = CliRunner().invoke(cli, ["fleet", "defects", "--json"])
    old = CliRunner().invoke(cli, ["fleet", "faults", "--json"])
    assert old.exit_code == new.exit_code == 0
    assert json.loads(old.stdout)["faults"] == json.loads(new.stdout)["defects"]  # the old key
    assert [d["name"] for d in json.loads(old.stdout)["faults"]] == list(mutants.NAMES)
    table = CliRunner().invoke(cli, ["fleet", "faults"], terminal_width=200)
    assert table.stdout == CliRunner().invoke(cli, ["fleet", "defects"],
                                              terminal_width=200).stdout
    assert "'fleet faults' is the old name of 'fleet defects'" in " ".join(old.stderr.split())
    assert "old name" not in new.stderr


def test_the_old_names_are_not_offered_in_help() -> None:
    fleet = CliRunner().invoke(cli, ["fleet", "--help"], terminal_width=200)
    assert " defects " in fleet.output and " faults " not in fleet.output
    serve = CliRunner().invoke(cli, ["fleet", "serve", "--help"], terminal_width=200)
    assert "--defect NAME" in serve.output and "--fault " not in serve.output
