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
