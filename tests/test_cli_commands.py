"""Every console option as a subcommand, against the in-process virtual fleet."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner, Result

from ucom_tools.cli.main import cli
from ucom_tools.image.formats import load_image

IMAGE = "firmware_images/armar3.fl.S"
PROGID = f"0x{load_image(IMAGE).progid:08X}"
DATA = Path(__file__).parent / "data"


def ucom(*args: str, env: dict[str, str] | None = None) -> Result:
    return CliRunner().invoke(cli, list(args), env=env)


def js(r: Result) -> dict:
    assert r.stdout, r.stderr
    return json.loads(r.stdout)


def test_reset_before_init_finds_nobody_and_says_why() -> None:
    r = ucom("reset", "--virtual", "armar3")
    assert r.exit_code == 0
    assert "no board answered" in r.stdout and "init" in r.stdout


def test_init_json_on_armar3() -> None:
    r = ucom("init", "--virtual", "armar3", "--json")
    assert r.exit_code == 0
    buses = js(r)["buses"]
    assert [(b["name"], b["expected"], b["found"]) for b in buses] == [
        ("CAN0", 3, 3), ("CAN1", 3, 3), ("CAN2", 3, 3), ("CAN3", 2, 2)]
    assert all(b["diagnosis"] == [] for b in buses)
    assert [x["seq_id"] for x in buses[0]["boards"]] == [1, 2, 3]
    assert buses[0]["boards"][0]["placement"] == "neck"
    assert buses[0]["boards"][0]["state"] == "bootloader"


@pytest.mark.parametrize("topology, kind, text", [
    ("arm_broken_line", "broken-line",
     "init line cut between position 2 (right shoulder back) and position 3 (right belly)"),
    ("arm_unpowered", "unpowered", "position 3 (right belly) did not answer"),
    ("arm_fixed_clash", "fixed-id-clash", "fixed ID 7 is used by 2 boards"),
])
def test_init_diagnoses_faulty_wiring(topology: str, kind: str, text: str) -> None:
    r = ucom("init", "--virtual", str(DATA / f"{topology}.toml"), "--json")
    assert r.exit_code == 1
    (bus,) = js(r)["buses"]
    assert [d["kind"] for d in bus["diagnosis"]] == [kind]
    assert text in bus["diagnosis"][0]["message"]
    r = ucom("init", "--virtual", str(DATA / f"{topology}.toml"))
    assert text in " ".join(r.stdout.split())
    assert "LEDs" in r.stdout or kind == "fixed-id-clash"


def test_first_and_last_show_a_broken_line() -> None:
    r = ucom("first", "--virtual", str(DATA / "arm_broken_line.toml"), "--json")
    assert r.exit_code == 1
    (bus,) = js(r)["buses"]
    assert bus["broken"] and len(bus["answers"]) == 2
    r = ucom("last", "--virtual", "armar3", "--bus", "CAN0", "--json")
    assert r.exit_code == 0
    assert len(js(r)["buses"][0]["answers"]) == 1


def test_options_needing_init_explain_it() -> None:
    for args in (["info", "2"], ["prog-enable", "all"], ["set-init-in", "1", "set"],
                 ["set-seqid", "1", "5"], ["reset-one", "2"],
                 ["program", "all", IMAGE]):
        r = ucom(*args, "--virtual", "rosi")
        assert r.exit_code == 1, args
        msg = " ".join(r.stderr.split())
        assert "no board has a seq ID yet" in msg and "init" in msg, args


def test_info_count_list_after_init() -> None:
    r = ucom("info", "2", "--virtual", "armar3", "--init", "--bus", "CAN1", "--json")
    assert r.exit_code == 0
    (board,) = js(r)["boards"]
    assert (board["bus"], board["seq_id"], board["state"]) == ("CAN1", 2, "bootloader")
    r = ucom("info", "CAN2:3", "--virtual", "armar3", "--init")
    assert r.exit_code == 0 and "CAN2 board 3" in r.stdout
    r = ucom("count", "--virtual", "armar3", "--init", "--json")
    assert len(js(r)["boards"]) == 11
    r = ucom("list", "--virtual", "lauron4", "--init", "--json")
    assert [b["seq_id"] for b in js(r)["boards"]] == list(range(1, 8))
    r = ucom("info", "9", "--virtual", "armar3", "--init", "--bus", "CAN0")
    assert r.exit_code == 1 and "no board with seq ID 9" in r.stdout


def test_board_arguments_are_checked() -> None:
    r = ucom("info", "42", "--virtual", "armar3")
    assert r.exit_code == 3 and "out of range" in r.stderr
    r = ucom("set-init-out", "1", "sideways", "--virtual", "armar3")
    assert r.exit_code == 3 and "LEVEL" in r.stderr
    r = ucom("info", "1", "--virtual", "armar3", "--bus", "CAN7")
    assert r.exit_code == 3 and "no bus 'CAN7'" in r.stderr


def test_flash_json_every_board_verified_and_started() -> None:
    r = ucom("flash", IMAGE, "--virtual", "armar3", "--start", "--autostart", "--json")
    assert r.exit_code == 0, r.stderr
    data = js(r)
    assert data["all_verified"] and data["progid"] == PROGID
    assert len(data["boards"]) == 11
    for b in data["boards"]:
        assert b["outcome"] == "verified" and b["verified_progid"] == PROGID
        assert b["started"] and b["autostart"]
        assert any("running" in m for m in b["messages"])
    assert {b["bus"] for b in data["boards"]} == {"CAN0", "CAN1", "CAN2", "CAN3"}


def test_flash_selected_boards_on_one_bus() -> None:
    r = ucom("flash", IMAGE, "--virtual", "armar3", "--bus", "CAN1", "--boards", "1,3",
             "--json")
    assert r.exit_code == 0
    assert [(b["bus"], b["seq_id"]) for b in js(r)["boards"]] == [("CAN1", 1), ("CAN1", 3)]
    r = ucom("flash", IMAGE, "--virtual", "armar3", "--bus", "CAN1", "--boards", "2,7")
    assert r.exit_code == 1
    assert "CAN1:7" in r.stderr
    r = ucom("flash", IMAGE, "--virtual", "armar3", "--boards", "x")
    assert r.exit_code == 3


def test_flash_refuses_a_faulty_chain_and_names_the_boards() -> None:
    r = ucom("flash", IMAGE, "--virtual", str(DATA / "arm_broken_line.toml"), "--json")
    assert r.exit_code == 1
    data = js(r)
    assert not data["all_verified"]
    assert all("init chain is faulty" in b["detail"] for b in data["boards"])


def test_state_dir_carries_flash_across_invocations(tmp_path: Path) -> None:
    common = ["--virtual", "armar3", "--state", str(tmp_path), "--bus", "CAN3"]
    assert ucom("flash", IMAGE, *common).exit_code == 0
    r = ucom("start", "2", *common, "--init", "--json")
    assert r.exit_code == 0
    (row,) = js(r)["results"]
    assert row["state"] == "running (flash)"
    r = ucom("autostart", "all", *common, "--init")
    assert r.exit_code == 0
    # every invocation powers the fleet up anew: AutoStart programs run at once
    r = ucom("count", *common, "--init", "--json")
    assert [b["state"] for b in js(r)["boards"]] == ["running (flash)"] * 2
    assert all(b["autostart"] for b in js(r)["boards"])
    # XReset reaches boards without a number too (they act, but cannot answer)
    r = ucom("xreset", *common, "--json")
    assert r.exit_code == 0 and js(r)["results"] == []
    r = ucom("count", *common, "--init", "--json")
    assert [(b["state"], b["autostart"]) for b in js(r)["boards"]] == [("bootloader", False)] * 2


def test_program_prog_enable_extram_and_start_in_one_session_via_state(tmp_path: Path) -> None:
    common = ["--virtual", "rosi", "--state", str(tmp_path)]
    r = ucom("program", "1", "firmware_images/rosi.fl.S", *common, "--init", "--json")
    assert r.exit_code == 0 and js(r)["boards"][0]["outcome"] == "verified"
    r = ucom("extram-load", "1", "firmware_images/rosi.fl.S", *common, "--init", "--json")
    assert r.exit_code == 0 and js(r)["target"] == "extram"
    r = ucom("start", "1", "--extram", *common, "--init")
    assert r.exit_code == 1 and "no complete, verified program" in r.stdout  # ExtRAM is gone
    r = ucom("prog-enable", "all", *common, "--init", "--json")
    assert r.exit_code == 0 and js(r)["results"][0]["ok"]
    r = ucom("prog-enable", "all", "--off", *common, "--init")
    assert r.exit_code == 0


def test_init_pins_seqid_and_reset_one() -> None:
    r = ucom("set-init-out", "2", "set", "--virtual", "armar3", "--bus", "CAN0", "--init",
             "--json")
    assert r.exit_code == 0
    assert js(r)["status"][0]["leds"] & 0b010  # yellow: drives its init output
    r = ucom("set-init-in", "2", "set", "--virtual", "armar3", "--bus", "CAN0", "--init")
    assert "LEDs red+green" in r.stdout
    r = ucom("set-seqid", "3", "9", "--virtual", "armar3", "--bus", "CAN0", "--init", "--json")
    assert r.exit_code == 0 and js(r)["results"][0]["seq_id"] == 9
    r = ucom("reset-one", "2", "--virtual", "armar3", "--bus", "CAN0", "--init", "--json")
    assert r.exit_code == 0 and js(r)["results"][0]["seq_id"] == 2


def test_options_from_environment() -> None:
    r = ucom("init", "--json", env={"UCOM_VIRTUAL": "odete"})
    assert r.exit_code == 0 and js(r)["buses"][0]["found"] == 3


def test_bus_that_cannot_be_opened_gives_one_line_and_exit_4() -> None:
    r = ucom("init", "-i", "socketcand", "--host", "127.0.0.1", "--port", "1", "-c", "CAN0")
    assert r.exit_code == 4
    assert "cannot connect to socketcand 127.0.0.1:1: Connection refused" in r.stderr
    assert "Traceback" not in r.stderr
    r = ucom("init", "-i", "no-such-interface", "-c", "x")
    assert r.exit_code == 4
    r = ucom("init")
    assert r.exit_code == 3 and "--virtual" in r.stderr


def test_flash_on_real_time_buses_waits_for_the_bus() -> None:
    """With --pace the host cannot queue frames faster than 1 Mbit/s carries them."""
    r = ucom("flash", "firmware_images/bench64k.fl.S", "--virtual", "armar3", "--pace",
             "--bus", "CAN3", "--json")
    assert r.exit_code == 0, r.stdout + r.stderr
    assert [b["outcome"] for b in js(r)["boards"]] == ["verified", "verified"]
