"""``ucom tree check|show|format|diff``: exit codes, JSON shapes, tables, atomic writes."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner, Result

from ucom_tools.cli.main import cli
from ucom_tools.config import attrtree
from ucom_tools.errors import WriteError

ROOT = Path(__file__).resolve().parent.parent
TREES = ROOT / "attribute_trees"
EYES = TREES / "armar3" / "head_right.tree"
CORPUS = Path(__file__).parent / "data" / "trees"


def ucom(*args: str, env: dict[str, str] | None = None) -> Result:
    return CliRunner().invoke(cli, list(args), env=env)


def js(r: Result) -> object:
    assert r.stdout, r.stderr
    return json.loads(r.stdout)


# ----------------------------------------------------------------------------- check
def test_check_one_file_prints_a_summary() -> None:
    r = ucom("tree", "check", str(EYES))
    assert r.exit_code == 0, r.stderr
    assert "board 0 'Eyes': 71 edges (13 CI, 20 SO, 38 PAR), 35 PAR + 6 CI defaults" in r.stdout


def test_check_json_of_one_file_is_an_object_with_every_edge() -> None:
    data = js(ucom("tree", "check", str(EYES), "--json"))
    assert isinstance(data, dict)
    assert data["file"] == str(EYES)
    (board,) = data["boards"]
    assert (board["number"], board["prefix"]) == (0, "Eyes")
    edges = board["edges"]
    assert len(edges) == 71
    assert edges[0] == {"index": 0, "kind": "CI", "generic": "MotorA Command",
                        "unique": "Right Eye Command", "default": 0, "default_text": "0"}
    assert edges[2]["default"] is None and edges[2]["default_text"] is None
    assert edges[37]["default"] == 1092 and edges[37]["default_text"] == "0x444"
    assert edges[39]["default"] == 0.0005 and edges[39]["default_text"] == "0.0005"
    assert edges[13] == {"index": 13, "kind": "SO", "generic": "Encoder 0",
                         "unique": "Right Eye Joint Sensor", "default": None,
                         "default_text": None}
    assert sum(e["default"] is not None for e in edges) == 41


def test_check_json_of_several_files_is_a_list() -> None:
    files = sorted((TREES / "armar3").glob("*.tree"))
    data = js(ucom("tree", "check", *map(str, files), "--json"))
    assert isinstance(data, list)
    assert [d["file"] for d in data] == list(map(str, files))
    assert all(len(d["boards"][0]["edges"]) == 71 for d in data)


def test_check_reports_every_broken_file_and_exits_3() -> None:
    bad1, bad2 = CORPUS / "index_gap.tree", CORPUS / "bad_close.tree"
    r = ucom("tree", "check", str(EYES), str(bad1), str(bad2), "--json")
    assert r.exit_code == 3
    report = json.loads(r.stdout)  # --json: a document even so, every mistake in it
    assert [(e["file"], e["line"]) for e in report["errors"]] == [(str(bad1), 7),
                                                                  (str(bad2), 13)]
    assert report["error"]["exit_code"] == 3
    lines = r.stderr.splitlines()
    assert lines[0].startswith(f"ucom: bad input: {bad1}:7:7: index 2 out of sequence")
    assert lines[1].startswith(f"ucom: bad input: {bad2}:13:5: ")
    assert len(lines) == 2


def test_check_without_files_or_topology_is_a_usage_error() -> None:
    r = ucom("tree", "check")
    assert r.exit_code == 2


def test_check_missing_file_exits_3() -> None:
    r = ucom("tree", "check", "no/such.tree")
    assert r.exit_code == 3
    assert "no/such.tree: no such attribute tree file" in r.stderr


@pytest.mark.parametrize("robot, boards", [("armar3", 11), ("lauron4", 7)])
def test_check_topology_of_bundled_robots_passes(robot: str, boards: int) -> None:
    r = ucom("tree", "check", "--topology", robot)
    assert r.exit_code == 0, r.stderr
    assert f"ok {boards} boards, {boards} tree files" in r.stdout
    data = js(ucom("tree", "check", "--topology", robot, "--json"))
    assert isinstance(data, dict)
    assert len(data["boards"]) == boards == len(data["trees"])
    assert len({b["prefix"] for b in data["boards"]}) == boards


def test_check_topology_json_binds_the_eyes_board_to_b5() -> None:
    data = js(ucom("tree", "check", "--topology", "armar3", "--json"))
    assert isinstance(data, dict)
    assert data["topology"] == "ARMAR-III"
    head_right = next(b for b in data["boards"] if b["placement"] == "head right")
    assert head_right == {"bus": "CAN0", "position": 3, "placement": "head right",
                          "tree": str(EYES), "block": 0, "prefix": "Eyes", "edges": 71,
                          "defaults": 41}


def _topology(tmp: Path, boards: list[str]) -> Path:
    text = 'name = "t"\n[[bus]]\nname = "CAN0"\n'
    for i, extra in enumerate(boards):
        text += f'\n[[bus.board]]\nplacement = "slot {i + 1}"\nboard = "3M"\n{extra}\n'
    path = tmp / "robot.toml"
    path.write_text(text)
    return path


def test_check_topology_names_every_board_without_a_tree(tmp_path: Path) -> None:
    shutil.copy(EYES, tmp_path / "eyes.tree")
    topo = _topology(tmp_path, ['tree = "eyes.tree"', "", ""])
    r = ucom("tree", "check", "--topology", str(topo))
    assert r.exit_code == 3
    assert r.stdout == ""
    lines = r.stderr.splitlines()
    assert len(lines) == 2
    assert lines[0].startswith(f"ucom: bad input: {topo}:10: CAN0 board 2 (slot 2) has no "
                               "attribute tree")
    assert lines[1].startswith(f"ucom: bad input: {topo}:15: CAN0 board 3 (slot 3) has no "
                               "attribute tree")


def _two_blocks(tmp: Path) -> Path:
    eyes = attrtree.load(EYES).boards[0]
    other = attrtree.BoardBlock(5, "Other", eyes.edges)
    path = tmp / "two.tree"
    attrtree.save(attrtree.Tree((eyes, other)), path)
    return path


@pytest.mark.parametrize("a, b, code, message", [
    ("", "", 3, "two.tree has 2 board blocks (0, 5); set tree_block"),
    ("tree_block = 0", "tree_block = 5", 0, None),
    ("tree_block = 0", "tree_block = 7", 3, "tree_block 7 is not in"),
    ("tree_block = 0", "tree_block = 0", 3, "prefix 'Eyes' of CAN0 board 2 (slot 2) is also "
                                            "CAN0 board 1 (slot 1)'s"),
])
def test_check_topology_tree_block(tmp_path: Path, a: str, b: str, code: int,
                                   message: str | None) -> None:
    _two_blocks(tmp_path)
    topo = _topology(tmp_path, [f'tree = "two.tree"\n{a}', f'tree = "two.tree"\n{b}'])
    r = ucom("tree", "check", "--topology", str(topo), "--json")
    assert r.exit_code == code, r.stderr
    if message is None:
        data = js(r)
        assert isinstance(data, dict)
        assert [(x["block"], x["prefix"]) for x in data["boards"]] == [(0, "Eyes"),
                                                                      (5, "Other")]
        assert len(data["trees"]) == 1
    else:
        assert message in r.stderr


def test_check_topology_reports_a_broken_tree(tmp_path: Path) -> None:
    shutil.copy(CORPUS / "second_default.tree", tmp_path / "x.tree")
    topo = _topology(tmp_path, ['tree = "x.tree"'])
    r = ucom("tree", "check", "--topology", str(topo))
    assert r.exit_code == 3
    assert f"{tmp_path / 'x.tree'}:16:7: a second default for 'Max PWM'" in r.stderr


# ----------------------------------------------------------------------------- show
def test_show_prints_every_name_in_full_grouped_by_kind() -> None:
    r = ucom("tree", "show", str(EYES))
    assert r.exit_code == 0, r.stderr
    board = attrtree.load(EYES).boards[0]
    for e in board.edges:
        assert e.unique in r.stdout and e.generic in r.stdout
    assert r.stdout.index("MotorC Target Vel") < r.stdout.index("Right Eye Joint Sensor") < \
        r.stdout.index("LoopTime(ms)")
    assert "0x444" in r.stdout and "-12725" in r.stdout


def test_show_on_a_narrow_terminal_folds_but_never_truncates() -> None:
    r = ucom("tree", "show", str(EYES), env={"COLUMNS": "60"})
    assert r.exit_code == 0
    assert "…" not in r.stdout
    assert max(len(line) for line in r.stdout.splitlines()) <= 60
    rows: list[list[str]] = []  # per edge: the generic and unique cells, joined over lines
    for line in r.stdout.splitlines():
        cells = line.split("│")
        if len(cells) != 7:
            continue
        if cells[1].strip():
            rows.append(["", ""])
        rows[-1][0] += "".join(cells[3].split())
        rows[-1][1] += "".join(cells[4].split())
    board = attrtree.load(EYES).boards[0]
    by_kind = [e for k in attrtree.TreeEdgeKind for e in board.of_kind(k)]
    assert rows == [["".join(e.generic.split()), "".join(e.unique.split())] for e in by_kind]
    assert any(len(e.unique) > 20 for e in board.edges)  # so some cells had to fold


def test_show_board_that_is_not_there_exits_3() -> None:
    r = ucom("tree", "show", str(EYES), "--board", "1")
    assert r.exit_code == 3
    assert "no board 1 (its boards: 0)" in r.stderr


# ----------------------------------------------------------------------------- format
def test_format_to_stdout_gives_the_same_json() -> None:
    r = ucom("tree", "format", str(EYES))
    assert r.exit_code == 0
    assert r.stdout.startswith("DSP{\n  0{\n    Prefix : Eyes\n    MappingTable{\n      # CI\n")
    assert "      56:MotorA Max Velocity (x1000) ==> RightEye Max Velocity (x1000)\n" in r.stdout
    assert attrtree.parse(r.stdout, "x") == attrtree.load(EYES)


def test_format_output_checks_to_the_same_json(tmp_path: Path) -> None:
    out = tmp_path / "eyes.tree"
    assert ucom("tree", "format", str(EYES), "-o", str(out)).exit_code == 0
    a = js(ucom("tree", "check", str(EYES), "--json"))
    b = js(ucom("tree", "check", str(out), "--json"))
    assert isinstance(a, dict) and isinstance(b, dict)
    assert a["boards"] == b["boards"]
    assert out.read_text() == ucom("tree", "format", str(EYES)).stdout


def test_format_in_place_keeps_the_file_mode(tmp_path: Path) -> None:
    path = tmp_path / "eyes.tree"
    shutil.copy(EYES, path)
    path.chmod(0o640)
    assert ucom("tree", "format", str(path), "-o", str(path)).exit_code == 0
    assert attrtree.load(path) == attrtree.load(EYES)
    assert path.read_text() != EYES.read_text()
    assert path.stat().st_mode & 0o777 == 0o640
    assert os.listdir(tmp_path) == ["eyes.tree"]


def test_format_of_a_broken_tree_writes_nothing(tmp_path: Path) -> None:
    out = tmp_path / "out.tree"
    out.write_text("old\n")
    r = ucom("tree", "format", str(CORPUS / "index_gap.tree"), "-o", str(out))
    assert r.exit_code == 3
    assert out.read_text() == "old\n"


def test_format_into_a_missing_directory_exits_3(tmp_path: Path) -> None:
    r = ucom("tree", "format", str(EYES), "-o", str(tmp_path / "no" / "x.tree"))
    assert r.exit_code == 3
    assert "cannot write" in r.stderr


def test_save_is_atomic_when_the_rename_fails(tmp_path: Path,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "t.tree"
    path.write_text("before\n")

    def boom(src: str, dst: str) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(WriteError, match="No space left"):
        attrtree.save(attrtree.load(EYES), path)
    assert path.read_text() == "before\n"
    assert os.listdir(tmp_path) == ["t.tree"]


@pytest.mark.parametrize("robot", ["armar3", "lauron4"])
def test_bundled_trees_other_than_b5_are_canonical(robot: str) -> None:
    for path in sorted((TREES / robot).glob("*.tree")):
        if path == EYES:
            continue
        r = ucom("tree", "format", str(path))
        assert r.stdout == path.read_text(), path


# ----------------------------------------------------------------------------- diff
def test_diff_of_equal_trees_exits_0(tmp_path: Path) -> None:
    out = tmp_path / "eyes.tree"
    ucom("tree", "format", str(EYES), "-o", str(out))
    r = ucom("tree", "diff", str(EYES), str(out))
    assert r.exit_code == 0
    assert "no differences" in r.stdout
    data = js(ucom("tree", "diff", str(EYES), str(out), "--json"))
    assert data == {"a": str(EYES), "b": str(out), "equal": True, "changes": []}


def test_diff_lists_renames_and_defaults(tmp_path: Path) -> None:
    text = EYES.read_text()
    text = text.replace("==> Right Eye Target\n", "==> Right Eye Goal\n")
    text = text.replace("    Right Eye Target:0\n", "    Right Eye Goal:0\n")
    text = text.replace("  Max PWM:14000", "  Max PWM:12000")
    text = text.replace("RightEye D:0\n", "")
    text = text.replace("}MappingTable\n\nParameter {\n",
                        "}MappingTable\n\nParameter {\nMotorC P:5\n")
    b = tmp_path / "b.tree"
    b.write_text(text)
    r = ucom("tree", "diff", str(EYES), str(b), "--json")
    assert r.exit_code == 1
    data = js(r)
    assert isinstance(data, dict) and data["equal"] is False
    assert data["changes"] == [
        {"change": "renamed", "board": 0, "index": 3, "name": "Right Eye Goal",
         "old": "Right Eye Target", "new": "Right Eye Goal"},
        {"change": "default-changed", "board": 0, "index": 34, "name": "Max PWM",
         "old": "14000", "new": "12000"},
        {"change": "default-removed", "board": 0, "index": 40, "name": "RightEye D",
         "old": "0", "new": None},
        {"change": "default-added", "board": 0, "index": 44, "name": "MotorC P",
         "old": None, "new": "5"},
    ]
    table = ucom("tree", "diff", str(EYES), str(b))
    assert table.exit_code == 1
    words = " ".join(table.stdout.split())  # the title wraps with the length of tmp_path
    assert "4 change(s)" in words and "Right Eye Goal" in table.stdout


def test_diff_boards_added_and_removed(tmp_path: Path) -> None:
    two = _two_blocks(tmp_path)
    r = ucom("tree", "diff", str(EYES), str(two), "--json")
    assert r.exit_code == 1
    data = js(r)
    assert isinstance(data, dict)
    assert data["changes"] == [{"change": "board-added", "board": 5, "index": None,
                                "name": "Other", "old": None, "new": "Other"}]
    back = js(ucom("tree", "diff", str(two), str(EYES), "--json"))
    assert isinstance(back, dict)
    assert [c["change"] for c in back["changes"]] == ["board-removed"]


def test_diff_with_a_broken_tree_exits_3() -> None:
    r = ucom("tree", "diff", str(EYES), str(CORPUS / "nul_byte.tree"))
    assert r.exit_code == 3
    assert ":1:1: NUL byte" in r.stderr
