"""Scenario files of injected faults (``ucom(1)``, SCENARIOS): what they mean, and that every
mistake is refused before anything runs, naming FILE:LINE and the key (exit code 3)."""

from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner

from ucom_tools.cli.main import cli
from ucom_tools.config import topology as topo
from ucom_tools.config.scenario import FaultKind, InjectedFault, Scenario, injected
from ucom_tools.errors import InputError

ARMAR3 = topo.load("armar3")
GOOD = """\
description = "the right eye's board, then the whole robot"

[[fault]]
at = 0.5
kind = "power-off"
bus = "CAN0"
board = 3
for = 1.0

[[fault]]
at = 1
kind = "reset"
bus = "CAN1"
board = 1

[[fault]]
at = 2
kind = "cable"
bus = "CAN2"
for = 0.25

[[fault]]
at = 3
kind = "bus-off"
bus = "CAN3"
board = 2
for = 0.1

[[fault]]
at = 4
kind = "estop"
for = 2
"""


def test_a_scenario_reads_as_written_with_the_defaults() -> None:
    s = Scenario.parse(GOOD, "s.toml")
    s.check(ARMAR3)
    assert s.faults == (
        InjectedFault(FaultKind.POWER_OFF, "CAN0", 3, 1.0, 0.5),
        InjectedFault(FaultKind.RESET, "CAN1", 1, 0.0, 1.0),  # reset: for = 0 by default
        InjectedFault(FaultKind.CABLE, "CAN2", None, 0.25, 2.0),
        InjectedFault(FaultKind.BUS_OFF, "CAN3", 2, 0.1, 3.0),
        InjectedFault(FaultKind.ESTOP, None, None, 2.0, 4.0))
    assert [f.line for f in s.faults] == [3, 10, 16, 22, 29]
    assert [f.target for f in s.faults] == ["CAN0/3", "CAN1/1", "CAN2", "CAN3/2", "robot"]
    # each bus has its own faults and the whole robot's; a process of some buses the same
    assert s.of_bus("CAN0") == (s.faults[0], s.faults[4])
    assert s.only(["CAN1", "CAN3"]).faults == (s.faults[1], s.faults[3], s.faults[4])


def test_the_readme_s_example_scenario_fits_armar3() -> None:
    s = Scenario.load(Path(__file__).parent / "data" / "armar3_faults.toml")
    s.check(ARMAR3)
    assert [f.kind for f in s.faults] == [FaultKind.POWER_OFF, FaultKind.CABLE,
                                          FaultKind.ESTOP]


def bad(text: str) -> str:
    with pytest.raises(InputError) as err:
        Scenario.parse(text, "s.toml").check(ARMAR3)
    return str(err.value)


FAULT = '[[fault]]\nat = 1\nkind = "power-off"\nbus = "CAN0"\nboard = 3\nfor = 1\n'


@pytest.mark.parametrize("text, message", [
    ("[[fault]\n", "s.toml:1: not valid TOML"),
    ('name = "x"\n' + FAULT, "s.toml:1: name: unknown key; allowed: description, fault"),
    ("description = 3\n" + FAULT, "s.toml:1: description: expected a string"),
    ('description = "none"\n', "s.toml: fault: expected one or more [[fault]] tables"),
    ("[fault]\nat = 1\n", "s.toml:1: fault: expected one or more [[fault]] tables"),
    (FAULT + "colour = 1\n", "s.toml:7: fault[1].colour: unknown key; allowed: at, kind, "
                             "bus, board, for"),
    (FAULT.replace('kind = "power-off"\n', ""), "s.toml:1: fault[1]: missing key 'kind'"),
    (FAULT.replace('"power-off"', '"brown-out"'), "s.toml:3: fault[1].kind: expected one of "
     "power-off, reset, bus-off, cable, estop, got 'brown-out'"),
    (FAULT.replace("at = 1\n", ""), "s.toml:1: fault[1]: missing key 'at'"),
    (FAULT.replace("at = 1", "at = -1"), "s.toml:2: fault[1].at: expected seconds from 0 to "
     "86400, got -1"),
    (FAULT.replace("at = 1", "at = true"), "s.toml:2: fault[1].at: expected seconds"),
    (FAULT.replace("at = 1", "at = nan"), "s.toml:2: fault[1].at: expected seconds"),
    (FAULT.replace("for = 1\n", ""), "s.toml:1: fault[1]: missing key 'for': power-off "
     "needs a duration"),
    (FAULT.replace("for = 1", "for = 0"), "s.toml:6: fault[1].for: power-off for 0 s does "
     "nothing"),
    (FAULT.replace("for = 1", 'for = "1 s"'), "s.toml:6: fault[1].for: expected seconds"),
    (FAULT.replace("board = 3\n", ""), "s.toml:1: fault[1]: missing key 'board' (power-off "
     "acts on one board"),
    (FAULT.replace("board = 3", "board = 0"), "s.toml:5: fault[1].board: expected a seq ID "
     "1-31, got 0"),
    (FAULT.replace("board = 3", 'board = "3"'), "s.toml:5: fault[1].board: expected a seq "
     "ID"),
    (FAULT.replace('bus = "CAN0"\n', ""), "s.toml:1: fault[1]: missing key 'bus'"),
    (FAULT.replace('bus = "CAN0"', "bus = 0"), "s.toml:4: fault[1].bus: expected a bus "
     "name"),
    ('[[fault]]\nat = 1\nkind = "estop"\nbus = "CAN0"\nfor = 1\n', "s.toml:4: fault[1].bus: "
     "estop acts on the whole robot: no bus"),
    ('[[fault]]\nat = 1\nkind = "cable"\nbus = "CAN0"\nboard = 2\nfor = 1\n',
     "s.toml:5: fault[1].board: cable acts on a whole bus: no board"),
    # against the robot: what it lacks is named with what it has
    (FAULT + FAULT.replace("board = 3", "board = 4"), "s.toml:11: fault[2].board: no board "
     "4 on CAN0; its boards: 1 (neck), 2 (head left), 3 (head right)"),
    (FAULT.replace('"CAN0"', '"CAN9"'), "s.toml:4: fault[1].bus: no bus 'CAN9' in "
     "ARMAR-III; its buses: CAN0, CAN1, CAN2, CAN3"),
])
def test_every_mistake_names_the_file_the_line_and_the_key(text: str, message: str) -> None:
    assert bad(text).startswith(message), bad(text)


def test_a_file_that_cannot_be_read_is_named(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"missing\.toml: no such scenario file"):
        Scenario.load(tmp_path / "missing.toml")
    (tmp_path / "latin1.toml").write_bytes(b'description = "\xe9"\n')
    with pytest.raises(InputError, match=r"latin1\.toml: cannot read"):
        Scenario.load(tmp_path / "latin1.toml")


def test_a_fault_by_hand_must_fit_its_target() -> None:
    assert injected("estop", "robot", 2) == InjectedFault(FaultKind.ESTOP, None, None, 2.0)
    assert injected("reset", "CAN1/2", None).for_s == 0.0
    # a board as every other command names it (BUS:N) is the same board
    assert injected("reset", "CAN1:2", None) == injected("reset", "CAN1/2", None)
    for kind, target, message in [
            ("power-off", "CAN0", "TARGET: power-off acts on a board: give BUS/BOARD"),
            ("cable", "CAN0/3", "TARGET: cable acts on a bus: give BUS"),
            ("estop", "CAN0", "TARGET: estop acts on a robot: give robot"),
            ("melt", "CAN0/3", "KIND: 'melt' is no fault kind"),
            ("reset", "CAN0/x", "TARGET: 'CAN0/x': the board after the bus is its seq ID"),
            ("reset", "CAN0:x", "TARGET: 'CAN0:x': the board after the bus is its seq ID"),
            ("reset", "CAN 0", "TARGET: 'CAN 0': expected BUS/BOARD")]:
        with pytest.raises(InputError, match=message):
            injected(kind, target, 1.0)
    with pytest.raises(InputError, match="for_s: bus-off needs a duration") as caught:
        injected("bus-off", "CAN0/1", None)  # the parameter; the command line's --for:
    from ucom_tools.cli.errortext import describe
    assert describe(caught.value).startswith("--for: bus-off needs a duration")


def test_the_cli_refuses_a_bad_scenario_before_anything_runs(tmp_path: Path) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(FAULT.replace("board = 3", "board = 9"))
    runner = CliRunner()
    served = runner.invoke(cli, ["fleet", "serve", "armar3", "--port", "0", "--scenario",
                                 str(path)])
    assert served.exit_code == 3, served.output
    assert f"{path}:5: fault[1].board: no board 9 on CAN0" in served.output
    assert "listening" not in served.output  # it never served
    run = runner.invoke(cli, ["init", "--virtual", "armar3", "--scenario", str(path)])
    assert run.exit_code == 3 and f"{path}:5: fault[1].board" in run.output, run.output
    real = runner.invoke(cli, ["init", "-i", "socketcand", "--host", "127.0.0.1", "--port",
                               "1", "-c", "CAN0", "--scenario", str(path)])
    assert real.exit_code == 2 and "--scenario injects faults into the in-process virtual " \
        "fleet: give it with --virtual" in real.output, real.output
