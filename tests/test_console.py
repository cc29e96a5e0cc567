"""``ucom console`` driven by scripted input, and the session logic behind it."""

from __future__ import annotations

from click.testing import CliRunner

from ucom_tools.cli.main import cli
from ucom_tools.image import load_image

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
    assert "no board has a seq ID yet" in out and "run option 2 (init) first" in out
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
