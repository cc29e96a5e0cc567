"""``ucom console`` driven by scripted input, and the session logic behind it."""

from __future__ import annotations

from click.testing import CliRunner

from ucom_tools.cli.main import cli
from ucom_tools.image.formats import load_image

IMAGE = "firmware_images/armar3.fl.S"
PROGID = f"0x{load_image(IMAGE).progid:08X}"


def console(script: str, *args: str) -> str:
    r = CliRunner().invoke(cli, ["console", *args], input=script)
    assert r.exit_code == 0, r.stdout + r.stderr
    return " ".join(r.stdout.split())


def test_menu_lists_every_option() -> None:
    out = console("q\n", "--virtual", "armar3")
    for title in ("Reset All", "Init", "GetInfo", "SetProgEnable", "Program", "ExtRAMLoad",
                  "Start", "SetAutoStart", "XReset", "SetInitIn", "SetInitOut", "SetSeqID",
                  "Count", "Get First", "Get Last", "DSPListUpdate", "Print DspList",
                  "Load S-Record File", "Calc ProgID", "ProgAll", "Reset Specific", "Quit"):
        assert title in out, title


def test_a_new_users_session() -> None:
    script = "\n".join([
        "3 2",                 # before init: explained
        "2",                   # init
        "info",                # missing argument is asked for ...
        "2",                   # ... and answered
        "bus CAN1",
        f"load {IMAGE}",
        "19",
        "4 all",
        "5 all",
        "7 3",
        "13",
        "14",
        "15",
        "16",
        "17",
        "10 1 set",
        "21 1",
        "frobnicate",
        "q",
    ]) + "\n"
    out = console(script, "--virtual", "armar3")
    assert "no board has a seq ID yet" in out and "run option 2 (Init) first" in out
    assert "CAN3: 2 board(s) found of 2 expected" in out
    assert "board (seq ID, F<n> for a fixed ID, or all): 2" in out
    assert f"ucom [CAN1 | armar3.fl.S {PROGID}]>" in out
    assert f"ProgID of armar3.fl.S: {PROGID}" in out
    assert "3 of 3 board(s) verified" in out
    assert "program 'armar3.fl.S' running" in out
    assert "CAN1: first board: seq ID 1" in out and "CAN1: last board: seq ID 3" in out
    assert "DSP list updated: 3 active board(s)" in out
    assert "LEDs red+green" in out
    assert "unknown option 'frobnicate'" in out


def test_program_asks_for_an_image_when_none_is_loaded() -> None:
    out = console("2\n20\nfirmware_images/rosi.fl.S\nq\n", "--virtual", "rosi")
    assert "no S-record file loaded" in out
    assert "1 of 1 board(s) verified" in out


def test_bad_input_keeps_the_console_running() -> None:
    out = console("load /nonexistent.S\n3 99\n12 1 77\nq\n", "--virtual", "rosi")
    assert "/nonexistent.S: no such file" in out
    assert "out of range" in out
    assert "not a seq ID" in out


def test_image_option_and_progall_on_a_faulty_chain() -> None:
    out = console("2\n20\nq\n", "--virtual", "tests/data/arm_broken_line.toml",
                  "--image", IMAGE)
    assert "init line cut between position 2" in out
    assert "not programmed: the init chain is faulty" in out
    assert "0 of 3 board(s) verified" in out


def test_end_of_input_quits_cleanly() -> None:
    out = console("2\n", "--virtual", "rosi")
    assert "1 board(s) found of 1 expected" in out


def test_every_option_that_needs_init_says_so_by_name_without_empty_parentheses() -> None:
    from ucom_tools.cli.menu import OPTIONS

    lines = {3: "3 2", 4: "4 2", 5: "5 2", 6: "6 2", 7: "7 2", 8: "8 2", 10: "10 2 set",
             11: "11 2 set", 12: "12 2 5", 21: "21 2"}
    assert set(lines) == {o.number for o in OPTIONS if o.needs_init}
    out = console("load firmware_images/rosi.fl.S\n" + "\n".join(lines.values()) + "\nq\n",
                  "--virtual", "rosi")
    assert "()" not in out
    for o in OPTIONS:
        if o.needs_init:
            assert f"Option {o.number} ({o.title}) works only after a successful init" in out


def test_option_7_starts_an_extram_program_and_the_readme_session_programs() -> None:
    out = console("2\nload firmware_images/rosi.fl.S\n6 1\n7 1 extram\n3 1\nq\n",
                  "--virtual", "rosi")
    assert "1 of 1 board(s) verified" in out
    assert "Start (ExtRAM)" in out and "running (ExtRAM)" in out
    # the README's console example: init, info, load, enable, program, start
    out = console(f"2\n3 1\nload {IMAGE}\n4 all\n5 all\n7 all\nq\n", "--virtual", "armar3")
    assert "11 of 11 board(s) verified" in out and "program 'armar3.fl.S' running" in out
    out = console(f"2\nload {IMAGE}\n5 all\nq\n", "--virtual", "rosi")
    assert "no board is ProgEnabled" in out and "'4 all' first" in out


def test_ctrl_c_at_an_argument_prompt_cancels_the_prompt_not_the_console() -> None:
    from ucom_tools.cli.console import Session
    from ucom_tools.ops.robot import ConnectSpec, open_robot

    robot = open_robot(ConnectSpec(virtual="rosi"))
    try:
        def interrupted(prompt: str) -> str:
            raise KeyboardInterrupt

        session = Session(robot, None, ask=interrupted)
        assert session.execute("info") is True  # asks for the board: Ctrl-C there
        assert session.execute("2") is True  # and the console goes on
        assert robot.buses["CAN0"].client.info_many()
    finally:
        robot.close()
