"""Board identity and the compatibility checks: host pre-flight, the start policy on the
board (through real frames), and ``ucom check``."""

from __future__ import annotations

import json
from pathlib import Path

from click.testing import CliRunner, Result

from ucom_tools.cli.main import cli
from ucom_tools.image.formats import load_image
from ucom_tools.ops.flash import flash
from ucom_tools.ops.flash_types import FlashRequest, Selection
from ucom_tools.ops.robot import ConnectSpec, open_robot
from ucom_tools.wire.codes import BoardState, ErrorCode, StatusOp
from ucom_tools.wire.ids import seq

DATA = Path(__file__).parent / "data"
MIXED = str(DATA / "arm_mismatches.toml")
SWAPPED = str(DATA / "arm_swapped.toml")
ARMAR = "firmware_images/armar3.fl.S"


def ucom(*args: str) -> Result:
    return CliRunner().invoke(cli, list(args))


def test_swapped_plug_on_board_puts_the_fpga_in_neutral() -> None:
    r = ucom("fleet", "show", SWAPPED, "--json")
    boards = json.loads(r.stdout)["buses"][0]["boards"]
    assert [b["fpga"]["neutral"] for b in boards] == [False, True, False]
    assert boards[1]["plug_on_board_id"] == 3 and boards[1]["fpga"]["board_id"] == 1
    assert "NEUTRAL" in ucom("fleet", "show", SWAPPED).stdout


def test_flash_refuses_misfits_naming_board_field_expected_found() -> None:
    r = ucom("flash", ARMAR, "--virtual", MIXED, "--json")
    assert r.exit_code == 1
    boards = {b["seq_id"]: b for b in json.loads(r.stdout)["boards"]}
    assert [boards[n]["outcome"] for n in range(1, 6)] == [
        "verified", "refused", "refused", "refused", "verified"]
    assert "plug-on board: expected 1 (3M), found 3 (Valve)" in boards[2]["detail"]
    assert "App-ID: expected 1, found 2" in boards[3]["detail"]
    assert "FPGA major: expected 1, found 2" in boards[4]["detail"]
    assert any("built for FPGA 1.0, the FPGA is 1.1; it will run" in w
               for w in boards[5]["warnings"])
    assert "CAN1:2 (refused)" in r.stderr


def test_force_programs_with_a_warning_and_the_board_ends_the_program() -> None:
    r = ucom("flash", ARMAR, "--virtual", SWAPPED, "--boards", "2", "--force", "--start",
             "--json")
    assert r.exit_code == 1  # programmed, but the start was refused on the board
    (b,) = json.loads(r.stdout)["boards"]
    assert b["outcome"] == "verified" and b["started"] is False
    assert any(w.startswith("forced despite:") for w in b["warnings"])
    assert any("plug-on Board-ID: program built for 1, board has 3" in m for m in b["messages"])
    assert "did not start" in r.stderr


def test_start_policy_through_real_frames() -> None:
    robot = open_robot(ConnectSpec(virtual=MIXED))
    try:
        image = load_image(ARMAR)
        assert flash(robot, FlashRequest(image, force=True)).all_verified
        client = robot.buses["CAN1"].client
        boards = robot.buses["CAN1"].bus.fleet.boards["CAN1"]
        ok, swapped, app, major, minor = (client.start(seq(n))[0] for n in range(1, 6))
        assert ok.ok and ok.state is BoardState.RUNNING_FLASH
        assert not any("warning" in t for t in ok.reports)
        for result, field in ((swapped, "plug-on Board-ID"), (app, "App-ID")):
            assert [e.code for e in result.errors] == [ErrorCode.INCOMPATIBLE]
            assert field in result.errors[0].describe()
            assert any("ended" in t for t in result.reports)
            assert result.state is BoardState.BOOTLOADER
        assert boards[1].state is BoardState.BOOTLOADER and boards[2].application is None
        assert [e.code for e in major.errors] == [ErrorCode.VERSION_MISMATCH]
        assert major.state is BoardState.BOOTLOADER  # Ready(BOOT) of the reset that followed
        assert any("resetting" in t for t in major.reports)
        assert minor.ok and minor.state is BoardState.RUNNING_FLASH
        assert any("warning" in t and "FPGA 1.0, the FPGA is 1.1" in t for t in minor.reports)
    finally:
        robot.close()


def test_a_major_mismatch_with_autostart_does_not_loop(tmp_path: Path) -> None:
    robot_spec = ConnectSpec(virtual=MIXED, state_dir=tmp_path)
    robot = open_robot(robot_spec)
    try:
        request = FlashRequest(load_image(ARMAR), selection=Selection("list", (4,)), force=True)
        assert flash(robot, request).all_verified
        client = robot.buses["CAN1"].client
        assert client.set_status(seq(4), StatusOp.AUTOSTART, 1)[0].ok
    finally:
        robot.close()
    # power-up: AutoStart starts the program, which aborts and resets once, then stays put
    robot = open_robot(robot_spec)
    try:
        sim = robot.buses["CAN1"].bus.sim
        sim.run_until(sim.now + 100_000)
        board = robot.buses["CAN1"].bus.fleet.boards["CAN1"][3]
        assert board.state is BoardState.BOOTLOADER and board.application is None
        # quiet: nothing left to happen (a reset loop always has its next reset scheduled;
        # the board has no number yet, so a loop would send no frames to count)
        assert sim.next_event_time() is None
    finally:
        robot.close()


def test_image_without_descriptor_is_programmable_but_flagged() -> None:
    r = ucom("flash", "firmware_images/legacy_nodesc.fl.S", "--virtual", "rosi", "--start",
             "--json")
    assert r.exit_code == 0
    (b,) = json.loads(r.stdout)["boards"]
    assert b["outcome"] == "verified" and b["started"]
    assert any("no descriptor" in w for w in b["warnings"])
    assert any("without an image descriptor" in m for m in b["messages"])


def test_check_matrix_clean_on_armar3_and_after_flashing(tmp_path: Path) -> None:
    r = ucom("check", "--virtual", "armar3", "--json")
    assert r.exit_code == 0
    data = json.loads(r.stdout)
    assert data["clean"] and len(data["boards"]) == 11
    assert {b["verdict"] for b in data["boards"]} == {"no program"}
    assert ucom("flash", ARMAR, "--virtual", "armar3", "--state", str(tmp_path)).exit_code == 0
    r = ucom("check", "--virtual", "armar3", "--state", str(tmp_path), "--json")
    assert r.exit_code == 0
    boards = json.loads(r.stdout)["boards"]
    assert {b["verdict"] for b in boards} == {"ok"}
    assert boards[0]["program"]["descriptor"]["application"].startswith("ARMAR-III")
    assert "clean" in ucom("check", "--virtual", "armar3", "--state", str(tmp_path)).stdout


def test_check_matrix_shows_every_kind_of_mismatch(tmp_path: Path) -> None:
    assert ucom("flash", ARMAR, "--virtual", MIXED, "--state", str(tmp_path),
                "--force").exit_code == 0
    r = ucom("check", "--virtual", MIXED, "--state", str(tmp_path), "--json")
    assert r.exit_code == 1
    rows = json.loads(r.stdout)["boards"]
    assert [b["verdict"] for b in rows] == ["ok", "mismatch", "mismatch", "mismatch",
                                            "warning"]
    assert rows[1]["fpga"]["neutral"] and rows[1]["plug_on_board"]["board"] == "Valve"
    assert [f["field"] for f in rows[2]["reasons"]] == ["App-ID"]
    assert [f["field"] for f in rows[3]["reasons"]] == ["FPGA major"]
    assert [(f["field"], f["severity"]) for f in rows[4]["reasons"]] == [("FPGA minor",
                                                                           "warning")]


def test_console_refuses_and_forces() -> None:
    script = f"2\nload {ARMAR}\n20\n20 force\n7 2\nq\n"
    r = CliRunner().invoke(cli, ["console", "--virtual", SWAPPED], input=script)
    out = " ".join(r.stdout.split())
    assert "refused" in out and "add 'force' to program them anyway" in out
    assert "3 of 3 board(s) verified" in out
    assert "program 'armar3.fl.S' ended" in out


def test_topology_fpga_table_is_checked(tmp_path: Path) -> None:
    path = tmp_path / "t.toml"
    path.write_text('name = "t"\n[[bus]]\nname = "A"\n[[bus.board]]\nplacement = "x"\n'
                    'board = "3M"\nfpga = { app_id = 200 }\n')
    r = ucom("fleet", "show", str(path))
    assert r.exit_code == 3 and f"{path}:7: bus[1].board[1].fpga: app_id must be 0..127" in \
        r.stderr
    path.write_text(path.read_text().replace("app_id = 200", "colour = 1"))
    assert "unknown key 'colour'" in ucom("fleet", "show", str(path)).stderr


def test_corrupt_descriptor_in_a_file_is_bad_input(tmp_path: Path) -> None:
    lines = Path(ARMAR).read_text().splitlines()
    import bincopy
    for i, line in enumerate(lines):
        rec = bincopy.unpack_srec(line)
        if rec[0] == "3" and rec[1] == 0x7DE0:
            data = bytearray(rec[3])
            data[8] ^= 0xFF  # format word
            lines[i] = bincopy.pack_srec("3", rec[1], len(data), bytes(data))
            bad_line = i + 1
    path = tmp_path / "corrupt.S"
    path.write_text("\n".join(lines) + "\n")
    r = ucom("srec", "info", str(path))
    assert r.exit_code == 3
    assert f"{path}:{bad_line}: image descriptor at P:7DE0" in " ".join(r.stderr.split())


def test_info_shows_all_three_identities(tmp_path: Path) -> None:
    assert ucom("flash", ARMAR, "--virtual", SWAPPED, "--state", str(tmp_path), "--force",
                "--boards", "2").exit_code == 0
    r = ucom("info", "2", "--virtual", SWAPPED, "--state", str(tmp_path), "--init", "--json")
    (b,) = json.loads(r.stdout)["boards"]
    assert b["plug_on_board"] == "3 (Valve)"
    assert b["fpga"] == "3M app 1 v1.0 NEUTRAL"
    assert b["built_for"] == "3M app 1 FPGA v1.0, program v3.2"
    r = ucom("fleet", "show", SWAPPED, "--json")
    plug = json.loads(r.stdout)["buses"][0]["boards"][1]["plug_on"]
    assert plug["name"].startswith("UCoM@Ventiltreiberboard") and "valve" in plug["carries"]
