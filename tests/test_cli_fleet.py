"""``ucom fleet show``: tables, JSON and errors."""

from __future__ import annotations

import json
from pathlib import Path

from click.testing import CliRunner

from ucom_tools.cli.main import cli


def run(*args: str) -> tuple[int, str, str]:
    r = CliRunner().invoke(cli, list(args))
    return r.exit_code, r.stdout, r.stderr


def test_show_armar3_json_has_11_boards_on_4_buses() -> None:
    code, out, _ = run("fleet", "show", "armar3", "--json")
    assert code == 0
    data = json.loads(out)
    assert [b["name"] for b in data["buses"]] == ["CAN0", "CAN1", "CAN2", "CAN3"]
    assert sum(len(b["boards"]) for b in data["buses"]) == 11
    first = data["buses"][0]["boards"][0]
    assert {"position", "placement", "board", "seq_id", "state", "leds"} <= set(first)
    assert first["leds"] == {"red": "off", "yellow": "on", "green": "off"}
    assert data["buses"][0]["boards"][1]["leds"]["green"] == "on"
    assert data["buses"][0]["bitrate"] == 1_000_000


def test_show_table_lists_every_placement() -> None:
    code, out, _ = run("fleet", "show", "armar3")
    assert code == 0
    for placement in ("neck", "head left", "right belly", "torso base joint"):
        assert placement in out
    assert "11 boards on 4 buses" in out


def test_show_an_own_topology_with_a_fault(tmp_path: Path) -> None:
    path = tmp_path / "arm.toml"
    path.write_text('name = "arm"\n[[bus]]\nname = "A"\nbitrate = 500000\n'
                    '[[bus.board]]\nplacement = "x"\nboard = "Valve"\n'
                    '[[bus.board]]\nplacement = "y"\nboard = "Sensor"\ninit_link = "broken"\n')
    code, out, _ = run("fleet", "show", str(path), "--json")
    assert code == 0
    bus = json.loads(out)["buses"][0]
    assert bus["broken_init_links"] == [2]
    assert [b["leds"]["green"] for b in bus["boards"]] == ["off", "off"]


def test_bad_topology_exits_3_with_one_line(tmp_path: Path) -> None:
    path = tmp_path / "arm.toml"
    path.write_text('name = "arm"\n[[bus]]\nname = "A"\n[[bus.board]]\nplacement = 1\n')
    code, out, err = run("fleet", "show", str(path))
    assert code == 3
    assert out == ""
    assert f"{path}:5: bus[1].board[1].placement: expected a string" in err
    assert "Traceback" not in err


def test_unknown_bundled_name_exits_3() -> None:
    code, _, err = run("fleet", "show", "armar4")
    assert code == 3 and "armar3" in err


def test_user_text_is_printed_verbatim_not_as_markup_or_emoji(tmp_path: Path) -> None:
    path = tmp_path / "arm.toml"
    path.write_text('name = "[bold]arm :x:"\n[[bus]]\nname = "A"\n'
                    '[[bus.board]]\nplacement = "[red]elbow[/red] :x:"\nboard = "3M"\n')
    code, out, _ = run("fleet", "show", str(path))
    assert code == 0
    assert "[bold]arm :x:" in out and "[red]elbow[/red] :x:" in out
    bad = tmp_path / "bad.S"
    bad.write_text("root:x:0:0:[red]root\n")
    code, _, err = run("srec", "info", str(bad))
    assert code == 3 and "root:x:0:0:[red]root" in err


def test_show_run_brings_up_autostart_programs_with_their_run_mode_leds(tmp_path: Path) -> None:
    """A robot flashed with AutoStart: after --run the programs run (stopped exchange: no
    PC yet), green blinks at 2 Hz (1 ms cycle / 500), yellow and red are dark."""
    state = tmp_path / "state"
    code, _, err = run("flash", "firmware_images/armar3.fl.S", "--virtual", "armar3",
                       "--state", str(state), "--autostart", "--bus", "CAN0")
    assert code == 0, err
    code, out, _ = run("fleet", "show", "armar3", "--state", str(state), "--json")
    neck = json.loads(out)["buses"][0]["boards"][0]
    assert neck["runtime"] is None  # power-on: the program is not up yet
    code, out, _ = run("fleet", "show", "armar3", "--state", str(state), "--run", "1500",
                       "--json")
    assert code == 0
    can0, can1 = json.loads(out)["buses"][:2]
    for b in can0["boards"]:
        assert b["runtime"]["state"] == "STOPPED" and b["runtime"]["cycle_us"] == 1000
        assert b["runtime"]["program"] == "armar3 cascaded PID"
        assert 0.09 < b["runtime"]["load"] < 0.12  # 5.4.2: about 10 % with controllers off
        assert (b["leds"]["red"], b["leds"]["yellow"], b["leds"]["green"],
                b["leds"]["green_hz"]) == ("off", "off", "blink", "2.0")
    assert all(b["runtime"] is None for b in can1["boards"])  # not flashed
    code, out, _ = run("fleet", "show", "armar3", "--state", str(state), "--run", "1500")
    assert "STOPPED 1 ms 10%" in out and "2.0 Hz" in out
