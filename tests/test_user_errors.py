"""What a user on a real robot meets (issue 8, A): the bus the command line names is the
bus used, missing boards fail the job, a taken seq ID is refused, tables are never cut
short, exit codes mean one thing each, and no user error (a mistake in what the user gives
ucom) ends in a traceback."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner, Result

from ucom_tools.cli.main import cli

IMAGE = "firmware_images/armar3.fl.S"


def ucom(*args: str, env: dict[str, str] | None = None) -> Result:
    return CliRunner().invoke(cli, list(args), env=env)


def js(r: Result) -> dict:
    assert r.stdout, r.stderr
    return json.loads(r.stdout)


# ----------------------------------------------------------------------------- A1
def test_the_command_line_wins_over_the_environment_and_says_so() -> None:
    r = ucom("init", "-i", "socketcand", "--host", "127.0.0.1", "--port", "1", "-c", "CAN0",
             env={"UCOM_VIRTUAL": "armar3"})
    assert r.exit_code == 4, r.stdout  # the real bus named on the command line: refused
    assert "Connection refused" in r.stderr
    assert "ignored from the environment: UCOM_VIRTUAL=armar3" in " ".join(r.stderr.split())
    # the exact command: no --host, so the command line bus is incomplete (exit 3),
    # and the virtual fleet of the environment is not used behind the user's back
    r = ucom("init", "-i", "socketcand", "--port", "1", "-c", "CAN0",
             env={"UCOM_VIRTUAL": "armar3"})
    assert r.exit_code == 3 and "--host" in r.stderr and not r.stdout
    assert "using -i socketcand --port 1 -c CAN0 from the command line" in r.stderr


def test_a_virtual_fleet_on_the_command_line_ignores_a_real_bus_in_the_environment() -> None:
    env = {"UCOM_INTERFACE": "socketcand", "UCOM_HOST": "127.0.0.1", "UCOM_PORT": "1",
           "UCOM_CHANNEL": "CAN0"}
    r = ucom("init", "--virtual", "rosi", "--json", env=env)
    assert r.exit_code == 0, r.stderr
    data = js(r)
    assert data["connection"]["bus"] == "--virtual rosi"
    assert data["connection"]["from"] == "command line"
    assert sorted(data["connection"]["ignored"]) == sorted(
        ["UCOM_INTERFACE=socketcand", "UCOM_HOST=127.0.0.1", "UCOM_PORT=1",
         "UCOM_CHANNEL=CAN0"])
    assert "ignored from the environment" in r.stderr


def test_two_buses_on_the_command_line_or_in_the_environment_are_refused() -> None:
    r = ucom("init", "--virtual", "rosi", "-i", "socketcand", "--host", "h", "--port", "1")
    assert r.exit_code == 2 and "two different buses" in r.stderr
    r = ucom("init", env={"UCOM_VIRTUAL": "rosi", "UCOM_INTERFACE": "socketcan",
                          "UCOM_CHANNEL": "can0"})
    assert r.exit_code == 3 and "environment names two different buses" in r.stderr
    r = ucom("init", "--json", env={"UCOM_VIRTUAL": "odete"})
    assert r.exit_code == 0 and js(r)["connection"] == {
        "bus": "--virtual odete", "from": "environment", "ignored": []}


def test_only_documented_environment_variables_are_read() -> None:
    """UCOM_FLASH_FORCE was an accident of click's auto_envvar_prefix: it is gone."""
    r = ucom("flash", "firmware_images/armar3_fpga2.fl.S", "--virtual", "rosi", "--json",
             env={"UCOM_FLASH_FORCE": "1", "UCOM_FLASH_BOARDS": "7"})
    assert r.exit_code == 1
    (board,) = js(r)["boards"]
    assert board["outcome"] == "refused" and board["seq_id"] == 1


# ----------------------------------------------------------------------------- A2
def _topology(tmp_path: Path, boards: int, *, unpowered_last: bool = False) -> str:
    text = 'name = "arm"\n[[bus]]\nname = "CAN0"\n'
    for i in range(boards):
        text += f'[[bus.board]]\nplacement = "joint {i + 1}"\nboard = "3M"\n'
        text += f'joints = ["axis {i + 1}"]\n'
    if unpowered_last:
        text += "powered = false\n"
    path = tmp_path / "arm.toml"
    path.write_text(text)
    return str(path)


def test_flash_fails_naming_an_expected_board_that_never_answered(tmp_path: Path) -> None:
    topo = _topology(tmp_path, 4, unpowered_last=True)
    r = ucom("flash", IMAGE, "--virtual", topo, "--json")
    assert r.exit_code == 1, r.stderr
    data = js(r)
    assert not data["all_verified"]
    outcomes = [(b["seq_id"], b["placement"], b["outcome"]) for b in data["boards"]]
    assert outcomes == [(1, "joint 1", "verified"), (2, "joint 2", "verified"),
                        (3, "joint 3", "verified"), (None, "joint 4", "missing")]
    assert "position 4 (joint 4; joints axis 4)" in data["boards"][3]["detail"]
    assert "CAN0:joint 4 (missing)" in r.stderr
    # the other multi-board operations say the same
    for command in (["count", "--init"], ["check"], ["prog-enable", "all", "--init"]):
        r = ucom(*command, "--virtual", topo)
        assert r.exit_code == 1, command
        assert "joint 4" in r.stdout, command


# ----------------------------------------------------------------------------- A3
def test_set_seqid_refuses_a_seq_id_another_board_holds_and_sends_nothing() -> None:
    from ucom_tools.ops import options as ops
    from ucom_tools.ops.robot import ConnectSpec, open_robot

    robot = open_robot(ConnectSpec(virtual="armar3"))
    try:
        h = robot.buses["CAN0"]
        h.client.init_chain()
        sim = h.bus.sim  # type: ignore[attr-defined]
        before = sim.stats.by_function[7]  # SetStatus frames on the bus
        from ucom_tools.errors import InputError
        with pytest.raises(InputError, match="seq ID 3 is already held by the board"):
            ops.set_seqid(robot, ops.parse_ref("2"), 3, bus="CAN0")
        assert sim.stats.by_function[7] == before
        assert sorted(a.number for a in h.client.info_many()) == [1, 2, 3]
        rows = ops.set_seqid(robot, ops.parse_ref("2"), 9, bus="CAN0")
        assert [(r.address.number, r.ok) for r in rows if r.address] == [(9, True)]
        assert sorted(a.number for a in h.client.info_many()) == [1, 3, 9]
    finally:
        robot.close()
    r = ucom("set-seqid", "2", "3", "--virtual", "armar3", "--bus", "CAN0", "--init")
    assert r.exit_code == 3 and "already held" in r.stderr and "nothing was sent" in r.stderr


# ----------------------------------------------------------------------------- A6
def test_tables_are_never_cut_short_when_piped_or_narrow() -> None:
    r = ucom("count", "--virtual", "armar3", "--init")
    assert r.exit_code == 0
    serials = re.findall(r"0x[0-9A-F]{8}", r.stdout)
    assert len(set(serials)) >= 11 and "…" not in r.stdout
    assert "right shoulder front" in ucom("init", "--virtual", "armar3").stdout
    narrow = ucom("init", "--virtual", "armar3", env={"COLUMNS": "60"})
    assert "…" not in narrow.stdout
    assert max(len(line) for line in narrow.stdout.splitlines()) <= 60
    wide = ucom("init", "--virtual", "armar3", env={"COLUMNS": "200"})
    for serial in re.findall(r"0x[0-9A-F]{8}", r.stdout)[:3]:
        assert serial in wide.stdout


# ----------------------------------------------------------------------------- A7
@pytest.mark.parametrize("args, code", [
    (["init", "--virtual", "rosi"], 0),
    (["init", "--virtual", "tests/data/arm_broken_line.toml"], 1),
    (["init", "--virtual", "rosi", "--frobnicate"], 2),
    (["init", "--virtual", "no/such/topology.toml"], 3),
    (["init", "-i", "socketcand", "--host", "127.0.0.1", "--port", "1", "-c", "CAN0"], 4),
    (["flash", IMAGE, "--virtual", "armar3", "--bus", "CAN3"], 0),
    (["flash", "firmware_images/armar3_fpga2.fl.S", "--virtual", "rosi"], 1),
    (["flash"], 2),
    (["flash", "README.md", "--virtual", "rosi"], 3),
    (["flash", IMAGE, "-i", "socketcand", "--host", "127.0.0.1", "--port", "1", "-c", "C"], 4),
    (["srec", "info", IMAGE], 0),
    (["srec", "info"], 2),
    (["srec", "info", "README.md"], 3),
    (["fleet", "show", "rosi"], 0),
    (["fleet", "show", "nonesuch"], 3),
    (["fleet", "serve", "rosi", "--port", "99999"], 2),
    (["info", "1", "--virtual", "rosi"], 1),
    (["info", "99", "--virtual", "rosi"], 3),
    (["check", "--virtual", "tests/data/arm_mismatches.toml"], 1),
    (["count", "--virtual", "rosi", "--state", "README.md"], 3),
])
def test_exit_codes_mean_one_thing_in_every_command_family(args: list[str], code: int) -> None:
    r = ucom(*args)
    assert r.exit_code == code, (args, r.stdout[-500:], r.stderr[-500:])
    assert "Traceback" not in r.stderr
    if code in (3, 4):
        assert r.stderr.startswith("ucom: ")


def test_a_served_port_in_use_is_a_bus_failure() -> None:
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        r = ucom("fleet", "serve", "rosi", "--port", str(taken.getsockname()[1]))
        assert r.exit_code == 4 and "cannot listen on 127.0.0.1" in r.stderr


def test_ctrl_c_during_a_flash_is_exit_130_and_aborts_the_transfer(tmp_path: Path) -> None:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(
        [sys.executable, "-m", "ucom_tools", "-v", "flash", "firmware_images/bench64k.fl.S",
         "--virtual", "rosi", "--pace", "--state", str(tmp_path)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        assert proc.stderr is not None
        line = proc.stderr.readline()  # "programming ... on CAN0": the transfer starts
        assert line.startswith("programming bench64k.fl.S"), line
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    assert "flash cancelled" in err and "Traceback" not in err
    r = ucom("info", "1", "--virtual", "rosi", "--state", str(tmp_path), "--init", "--json")
    (board,) = js(r)["boards"]
    assert board["flash_valid"] is False  # no startable half-image


# ----------------------------------------------------------------------------- A8
def test_a_corrupt_or_unreadable_state_is_bad_input_naming_the_file(tmp_path: Path) -> None:
    state = tmp_path / "state"
    assert ucom("flash", "firmware_images/rosi.fl.S", "--virtual", "rosi", "--state",
                str(state)).exit_code == 0
    (record,) = state.glob("*.json")
    (flash,) = state.glob("*.flash")
    record.write_text("{ not json")
    r = ucom("count", "--virtual", "rosi", "--state", str(state))
    assert r.exit_code == 3 and str(record) in r.stderr and "corrupt JSON" in r.stderr
    record.write_text('{"autostart": "yes"}')
    r = ucom("count", "--virtual", "rosi", "--state", str(state))
    assert r.exit_code == 3 and "autostart: expected bool" in r.stderr
    record.unlink()
    flash.write_bytes(b"\0" * 10)
    r = ucom("fleet", "show", "rosi", "--state", str(state))
    assert r.exit_code == 3 and str(flash) in r.stderr and "10 bytes" in r.stderr
    for r in (ucom("count", "--virtual", "rosi", "--state", "README.md"),
              ucom("fleet", "show", "rosi", "--state", "README.md")):
        assert r.exit_code == 3 and "must name a directory" in r.stderr
        assert "Traceback" not in r.stderr


def test_topology_errors_name_the_topology_file_line_and_board(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    readme = Path("README.md").resolve()
    bad.write_text('name = "x"\n[[bus]]\nname = "CAN0"\n[[bus.board]]\nplacement = "a"\n'
                   f'board = "3M"\nprogram = "{readme}"\n')
    r = ucom("init", "--virtual", str(bad))
    assert r.exit_code == 3
    assert r.stderr.startswith(f"ucom: bad input: {bad}:4:")
    assert "CAN0, board 1 (a), program" in r.stderr and "README.md:1" in r.stderr
    bad.write_text('name = "x"\n[[bus]]\nname = "CAN0"\n[[bus.board]]\nplacement = "a"\n'
                   'board = "3M"\nprogram = "nope.S"\n')
    r = ucom("init", "--virtual", str(bad))
    assert r.exit_code == 3 and f"no such S-record file: {tmp_path / 'nope.S'}" in r.stderr
    dup = tmp_path / "dup.toml"
    dup.write_text('name = "x"\n[[bus]]\nname = "CAN0"\n[[bus.board]]\nplacement = "neck"\n'
                   'board = "3M"\n[[bus]]\nname = "CAN1"\n[[bus.board]]\nplacement = "neck"\n'
                   'board = "3M"\n')
    for args in (["init", "--virtual", str(dup)], ["fleet", "show", str(dup)],
                 ["init", "-i", "virtual", "-c", "x", "--topology", str(dup)]):
        r = ucom(*args)
        assert r.exit_code == 3, args
        assert f"{dup}:10: bus[2].board[1].placement: 'neck' is also the placement of " \
               "board 1 on CAN0" in r.stderr
