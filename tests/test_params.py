"""``ucom params dump|load`` and ``ucom flash --keep-params`` against the virtual ARMAR-III:
the real commands over the real buses, the values checked in the boards' own memory."""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import replace
from decimal import Decimal
from pathlib import Path

import click
import pytest
from click.testing import CliRunner, Result

from ucom_tools.cli import output
from ucom_tools.cli import params as params_cli
from ucom_tools.cli.main import UcomGroup, cli
from ucom_tools.config import attrtree
from ucom_tools.config.attrtree import TreeEdgeKind
from ucom_tools.config.attrtree.robot import bind
from ucom_tools.config.topology import SOURCE_ROOT, load
from ucom_tools.edgelists import armar3
from ucom_tools.edgelists.model import EdgeKind, EdgeSpec
from ucom_tools.ops.edges import spec_of
from ucom_tools.ops.params import value_text
from ucom_tools.ops.remote import RemotePart
from ucom_tools.ops.robot import ConnectSpec, open_robot
from ucom_tools.virtual.board.runtime import McaRuntime
from ucom_tools.virtual.fleet import release_shared, shared_fleet
from ucom_tools.wire import mca
from ucom_tools.wire.ids import seq

IMAGE = str(SOURCE_ROOT / "firmware_images" / "armar3.fl.S")
TREES = SOURCE_ROOT / "attribute_trees"
ARMAR3 = sorted((TREES / "armar3").glob("*.tree"))
EYES = TREES / "armar3" / "head_right.tree"
WIRE = {TreeEdgeKind.CI: mca.Kind.CI, TreeEdgeKind.PAR: mca.Kind.PAR}
FIRST = {TreeEdgeKind.CI: 0, TreeEdgeKind.PAR: 33}
"""Tree index of the first edge of each kind in armar3.fl.S (CI 0-12, SO 13-32, PAR 33-70)."""


@click.group(cls=UcomGroup)
@click.pass_context
def ucom(ctx: click.Context) -> None:
    """The commands under test, behind the root's error boundary (exit codes)."""
    output.reset()
    ctx.ensure_object(dict)


ucom.add_command(params_cli.params)
ucom.add_command(cli.commands["flash"])
ucom.add_command(cli.commands["tree"])


def run(*args: str | Path) -> Result:
    return CliRunner().invoke(ucom, [str(a) for a in args])


@pytest.fixture(scope="module")
def state(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One persistent virtual ARMAR-III with armar3.fl.S in every board's flash."""
    d = tmp_path_factory.mktemp("armar3-state")
    r = run("flash", IMAGE, "--virtual", "armar3", "--state", d)
    assert r.exit_code == 0, r.stderr
    return d


class Held:
    """The shared fleet of ``state``, held by the test so that live values survive from
    one command to the next (each command alone would power it up anew)."""

    def __init__(self, state: Path) -> None:
        self.state = state
        self.fleet = shared_fleet("armar3", state)

    def power_cycle(self) -> None:
        release_shared(self.fleet)
        self.fleet = shared_fleet("armar3", self.state)

    def runtime(self, bus: str, n: int) -> McaRuntime:
        app = self.fleet.boards[bus][n - 1].application
        assert app is not None and app.runtime is not None, f"{bus} board {n} runs nothing"
        return app.runtime

    def raw(self, bus: str, n: int, kind: TreeEdgeKind, unique: str) -> int:
        """What the board holds, from its own memory (not over the bus)."""
        block = attrtree.load(TREES / "armar3" / _TREE[(bus, n)]).boards[0]
        e = block.edge(unique)
        values = self.runtime(bus, n)._values[WIRE[kind]]
        return values[e.index - FIRST[kind]]

    def snapshot(self, bus: str, n: int) -> tuple[list[int], list[int]]:
        model = self.runtime(bus, n).model
        return list(model.par), list(model.ci)

    def set_live(self, changes: dict[tuple[str, int], dict[str, str]],
                 only: set[tuple[str, int]] | None = None) -> None:
        """Start the programs (of the boards ``only`` names, default all) and write values
        (by unique name, as text) the way a PC at run time does: MCA writes, acknowledged."""
        robot = open_robot(ConnectSpec(virtual="armar3", state_dir=self.state))
        try:
            trees = bind(robot.topology)
            if only is not None:
                trees = replace(trees, boards=tuple(
                    b for b in trees.boards if (b.bus, b.spec.position + 1) in only))
            with RemotePart(robot, trees) as part:
                assert part.check().ok
                for (bus, n), values in changes.items():
                    block = trees.board(bus, n - 1)
                    edges = part.described(bus, n)
                    assert edges is not None
                    for unique, text in values.items():
                        e = block.edge(unique)
                        kind = WIRE[e.kind]
                        i = e.index - FIRST[e.kind]
                        raw = spec_of(kind, edges.of(kind)[i]).raw(text)
                        part.exchanges[bus].mca.write(seq(n), kind, i, [raw], edges.of(kind))
        finally:
            robot.close()


_TREE = {(b.bus, b.spec.position + 1): b.file.name for b in bind(load("armar3")).boards}
"""Every board of ARMAR-III and the base name of its tree."""


@pytest.fixture
def held(state: Path) -> Iterator[Held]:
    h = Held(state)
    yield h
    release_shared(h.fleet)


CHANGES = {
    ("CAN0", 3): {"RightEye P": "0.123456", "Encoder Prescaler(BitMask)": "0x123",
                  "LoopTime(ms)": "2.5", "Right Eye Reset Offset": "-1234"},
    ("CAN2", 1): {"Max PWM": "12345"},
}


def _spec(e: attrtree.Edge) -> EdgeSpec:
    return armar3.SPEC.of(EdgeKind(WIRE[e.kind]))[e.index - FIRST[e.kind]]


def _where(tree: Path, unique: str) -> int:
    """The line of ``unique``'s default in ``tree``."""
    return next(n for n, line in enumerate(tree.read_text().splitlines(), 1)
                if line.strip().startswith(f"{unique}:"))


# ----------------------------------------------------------------------------- dump
def test_dump_writes_trees_that_tree_check_accepts_with_the_live_values(
        held: Held, tmp_path: Path) -> None:
    held.set_live(CHANGES)
    out = tmp_path / "live"
    r = run("params", "dump", "armar3", "-o", out, "--virtual", "armar3",
            "--state", held.state, "--json")
    assert r.exit_code == 0, r.stderr
    assert sorted(p.name for p in out.iterdir()) == sorted(p.name for p in ARMAR3)
    check = run("tree", "check", *sorted(out.iterdir()))
    assert check.exit_code == 0, check.stderr
    for bus, n in _TREE:
        dumped = attrtree.load(out / _TREE[(bus, n)]).boards[0]
        bundled = attrtree.load(TREES / "armar3" / _TREE[(bus, n)]).boards[0]
        assert dumped.prefix == bundled.prefix
        assert [(e.index, e.kind, e.generic, e.unique) for e in dumped.edges] == \
            [(e.index, e.kind, e.generic, e.unique) for e in bundled.edges]
        for e in dumped.edges:
            if e.kind is TreeEdgeKind.SO:
                assert e.default is None
                continue
            assert e.default is not None, e.unique
            assert _spec(e).raw(e.default.text) == held.raw(bus, n, e.kind, e.unique), e.unique
    eyes = {e.unique: e.default.text for e in attrtree.load(out / "head_right.tree").boards[0]
            .edges if e.default is not None}
    assert (eyes["RightEye P"], eyes["Encoder Prescaler(BitMask)"], eyes["LoopTime(ms)"],
            eyes["Right Eye Reset Offset"]) == ("0.123456", "0x123", "2.5", "-1234")
    assert held.raw("CAN2", 1, TreeEdgeKind.PAR, "Max PWM") == 12345
    data = json.loads(r.stdout)
    assert data["ok"] and len(data["written"]) == 11 and len(data["boards"]) == 11
    board = next(b for b in data["boards"] if b["prefix"] == "Eyes")
    assert (board["bus"], board["seq_id"], board["tree"]) == ("CAN0", 3, str(EYES))
    gain = next(v for v in board["values"] if v["unique"] == "RightEye P")
    assert gain == {"kind": "PAR", "index": 38, "generic": "MotorA P", "unique": "RightEye P",
                    "raw": 123456, "value": 0.123456, "text": "0.123456", "unit": "",
                    "default": 50, "default_text": "50", "changed": True}


def test_dump_load_dump_gives_byte_identical_files(held: Held, tmp_path: Path) -> None:
    held.set_live(CHANGES)
    first, second = tmp_path / "first", tmp_path / "second"
    spec = ("--virtual", "armar3", "--state", held.state)
    r = run("params", "dump", "armar3", "-o", first, *spec)
    assert r.exit_code == 0, r.stderr
    held.power_cycle()  # every board back to its program's power-on values
    held.set_live({})
    assert held.raw("CAN0", 3, TreeEdgeKind.PAR, "RightEye P") == 0
    r = run("params", "load", "armar3", *sorted(first.iterdir()), *spec)
    assert r.exit_code == 0, r.stderr
    assert "loaded, read back" in r.stdout
    assert held.raw("CAN0", 3, TreeEdgeKind.PAR, "RightEye P") == 123456
    assert held.raw("CAN2", 1, TreeEdgeKind.PAR, "Max PWM") == 12345
    r = run("params", "dump", "armar3", "-o", second, *spec)
    assert r.exit_code == 0, r.stderr
    for f in sorted(first.iterdir()):
        assert (second / f.name).read_bytes() == f.read_bytes(), f.name


def test_dump_keeps_the_trees_own_text_where_the_live_value_is_the_same_number(
        held: Held, tmp_path: Path) -> None:
    own = tmp_path / "eyes.tree"  # texts the canonical form would write otherwise
    own.write_text(EYES.read_text().replace("Max PWM:14000", "Max PWM:0x36B0")
                   .replace("RightEye I:0.0005", "RightEye I:0.000500")
                   .replace("Encoder Prescaler(BitMask):0x444", "Encoder Prescaler(BitMask):1092"))
    robot = _can0(tmp_path, own)
    spec = ("--virtual", "armar3", "--state", held.state)
    r = run("params", "load", robot, *spec)  # the trees' defaults
    assert r.exit_code == 0, r.stderr
    out = tmp_path / "out"
    r = run("params", "dump", robot, "-o", out, *spec)
    assert r.exit_code == 0, r.stderr
    assert sorted(p.name for p in out.iterdir()) == ["eyes.tree", "head_left.tree", "neck.tree"]
    for f in out.iterdir():
        dumped = attrtree.load(f).boards[0]
        mine = attrtree.load(own if f.name == "eyes.tree" else TREES / "armar3" / f.name)
        for e in mine.boards[0].edges:
            if e.default is not None:
                assert dumped.edge(e.unique).default == e.default, (f.name, e.unique)
    eyes = attrtree.load(out / "eyes.tree").boards[0]
    assert eyes.edge("Max PWM").default.text == "0x36B0"
    assert eyes.edge("RightEye I").default.text == "0.000500"
    assert eyes.edge("Encoder Prescaler(BitMask)").default.text == "1092"
    assert eyes.edge("MotorC P").default.text == "0"  # no default in the tree: the live one
    held.set_live({("CAN0", 3): {"Max PWM": "14001", "RightEye I": "0.0006",
                                 "Encoder Prescaler(BitMask)": "0x445"}})
    r = run("params", "dump", robot, "-o", out, "--force", *spec)
    assert r.exit_code == 0, r.stderr
    eyes = attrtree.load(out / "eyes.tree").boards[0]  # another number: canonical text
    assert (eyes.edge("Max PWM").default.text, eyes.edge("RightEye I").default.text,
            eyes.edge("Encoder Prescaler(BitMask)").default.text) == ("14001", "0.0006", "0x445")


def test_value_text_is_the_exact_decimal_or_hex_for_a_bit_mask() -> None:
    gain = EdgeSpec(EdgeKind.PAR, "MotorA P", width=4, exponent=-6, minimum=-10**9,
                    maximum=10**9)
    mask = EdgeSpec(EdgeKind.PAR, "Encoder Prescaler(BitMask)", signed=False, minimum=0,
                    maximum=0xFFF)
    assert value_text(500, gain) == "0.0005"
    assert value_text(-7_000_000_000 // 1000, gain) == "-7"
    assert value_text(123_456_000, gain) == "123.456"
    assert value_text(0, gain) == "0"
    assert value_text(1092, mask) == "0x444"
    assert value_text(1092, mask, attrtree.Value.parse("1092")) == "1092"
    assert value_text(50_000_000, gain, attrtree.Value.parse("50")) == "50"
    assert value_text(50_000_001, gain, attrtree.Value.parse("50")) == "50.000001"
    assert Decimal(value_text(1, gain)) == Decimal("0.000001")


def test_dump_refuses_existing_files_unless_force_and_a_file_for_several_trees(
        state: Path, tmp_path: Path) -> None:
    existing = tmp_path / "head_right.tree"
    existing.write_text("mine\n")
    r = run("params", "dump", "armar3", "-o", tmp_path, "--virtual", "armar3", "--bus", "CAN0")
    assert r.exit_code == 3
    # one file: "replaces it" (the operation says the fact, the CLI names --force)
    assert "-o: " in r.stderr and "head_right.tree exists; --force replaces it" in r.stderr
    assert existing.read_text() == "mine\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["head_right.tree"]
    r = run("params", "dump", "armar3", "-o", existing, "--virtual", "armar3", "--force")
    assert r.exit_code == 3 and "11 tree files are dumped" in r.stderr
    r = run("params", "dump", "armar3", "-o", tmp_path, "--virtual", "armar3", "--bus", "CAN0",
            "--state", state, "--force")
    assert r.exit_code == 0, r.stderr
    assert attrtree.load(existing).boards[0].prefix == "Eyes"


# ----------------------------------------------------------------------------- load
def test_load_of_an_out_of_range_value_is_exit_3_with_file_and_line_and_sends_nothing(
        held: Held, tmp_path: Path) -> None:
    held.set_live({})
    before = {n: held.snapshot("CAN0", n) for n in (1, 2, 3)}
    text = EYES.read_text()
    bad = tmp_path / "eyes.tree"
    bad.write_text(text.replace("Max PWM:14000", "Max PWM:12000")  # fits, before the bad one
                   .replace("MotorC Min Position:-30000", "MotorC Min Position:-40000"))
    line = _where(bad, "MotorC Min Position")
    r = run("params", "load", "armar3", bad, "--virtual", "armar3", "--state", held.state)
    assert r.exit_code == 3, r.stdout
    assert f"{bad}:{line}: " in r.stderr
    assert "-40000 is outside -32768..32767" in r.stderr
    assert {n: held.snapshot("CAN0", n) for n in (1, 2, 3)} == before
    # the same file with the value that fits is taken: the check above could see a write
    bad.write_text(text.replace("Max PWM:14000", "Max PWM:12000"))
    r = run("params", "load", "armar3", bad, "--virtual", "armar3", "--state", held.state)
    assert r.exit_code == 0, r.stderr
    assert held.raw("CAN0", 3, TreeEdgeKind.PAR, "Max PWM") == 12000
    assert held.snapshot("CAN0", 1) == before[1]  # no file for the neck: left alone


def test_load_of_a_tree_with_a_prefix_no_board_has_is_exit_3(tmp_path: Path) -> None:
    other = tmp_path / "other.tree"
    other.write_text(EYES.read_text().replace("Prefix : Eyes", "Prefix : Ears"))
    r = run("params", "load", "armar3", other, "--virtual", "armar3")
    assert r.exit_code == 3
    assert f"{other}:3:14: no board of ARMAR-III has prefix 'Ears'" in r.stderr


def _can0(tmp_path: Path, eyes: Path) -> Path:
    """CAN0 of ARMAR-III as a robot of its own, with ``eyes`` as the head right tree."""
    text = 'name = "head"\n[[bus]]\nname = "CAN0"\n'
    for placement, tree in (("neck", TREES / "armar3" / "neck.tree"),
                            ("head left", TREES / "armar3" / "head_left.tree"),
                            ("head right", eyes)):
        text += f'[[bus.board]]\nplacement = "{placement}"\nboard = "3M"\ntree = "{tree}"\n'
    path = tmp_path / "head.toml"
    path.write_text(text)
    return path


def _mixed(tmp_path: Path, extra: str = "") -> Path:
    """CAN0 of ARMAR-III with a LAURON-IV leg tree bound to the head right board."""
    trees = [TREES / "armar3" / "neck.tree", TREES / "armar3" / "head_left.tree",
             TREES / "lauron4" / "front_left_leg.tree"]
    text = 'name = "mixed"\n[[bus]]\nname = "CAN0"\n'
    for placement, tree in zip(("neck", "head left", "head right"), trees, strict=True):
        text += (f'[[bus.board]]\nplacement = "{placement}"\nboard = "3M"\n'
                 f'tree = "{tree}"\n{extra}\n')
    path = tmp_path / "mixed.toml"
    path.write_text(text)
    return path


def test_a_tree_that_does_not_match_the_boards_program_is_exit_1_and_nothing_is_done(
        held: Held, tmp_path: Path) -> None:
    mixed = _mixed(tmp_path)
    out = tmp_path / "out"
    spec = ("--virtual", "armar3", "--state", held.state)
    r = run("params", "dump", mixed, "-o", out, *spec)
    assert r.exit_code == 1
    err = " ".join(r.stderr.split())
    assert "CAN0 board 3 (head right): its program's edges differ from its tree" in err
    assert "first: index 0: the tree maps CI 'Leg Mode', the board has CI 'MotorA " \
           "Command' there" in err
    assert "front_left_leg.tree:" in err and "nothing written" in err
    assert not out.exists()
    before = {n: held.snapshot("CAN0", n) for n in (1, 2)}
    r = run("params", "load", mixed, *spec, "--json")
    assert r.exit_code == 1
    data = json.loads(r.stdout)
    assert (data["ok"], data["sent"]) == (False, False)
    assert [b["ok"] for b in data["boards"]] == [False, False, False]
    assert data["boards"][2]["error"].startswith("its program's edges differ")
    assert data["boards"][0]["held"] == "not written: another board failed its check"
    assert {n: held.snapshot("CAN0", n) for n in (1, 2)} == before


# ----------------------------------------------------------------------------- flash
def test_flash_keep_params_keeps_a_changed_gain_across_a_reflash(held: Held) -> None:
    held.set_live(CHANGES)
    old = held.fleet.boards["CAN0"][2].application
    spec = ("--virtual", "armar3", "--state", held.state, "--bus", "CAN0")
    r = run("flash", IMAGE, "--keep-params", *spec)
    assert r.exit_code == 0, r.stderr
    out = " ".join(r.stdout.split())
    assert "3 of 3 board(s) verified" in out
    assert "params kept: CAN0 board 3 (head right): 51 values loaded back and read back" in out
    assert held.fleet.boards["CAN0"][2].application is not old  # reprogrammed and restarted
    assert held.raw("CAN0", 3, TreeEdgeKind.PAR, "RightEye P") == 123456
    assert held.raw("CAN0", 3, TreeEdgeKind.PAR, "Encoder Prescaler(BitMask)") == 0x123
    assert held.raw("CAN0", 3, TreeEdgeKind.CI, "Right Eye Reset Offset") == -1234
    # without --keep-params the reflash loses them: the check above can fail
    r = run("flash", IMAGE, "--start", *spec, "--json")
    assert r.exit_code == 0, r.stderr
    assert "keep_params" not in json.loads(r.stdout)
    assert held.raw("CAN0", 3, TreeEdgeKind.PAR, "RightEye P") == 0


def test_flash_keep_params_json_and_a_board_without_a_program(held: Held) -> None:
    held.set_live({("CAN0", 1): {"Max PWM": "9000"}}, only={("CAN0", 1), ("CAN0", 2)})
    r = run("flash", IMAGE, "--keep-params", "--virtual", "armar3", "--state", held.state,
            "--bus", "CAN0", "--json")
    assert r.exit_code == 0, r.stderr
    data = json.loads(r.stdout)
    assert data["all_verified"]
    kept = data["keep_params"]
    assert kept["ok"] and kept["directory"] is None
    assert [(b["seq_id"], b["outcome"], b["values"]) for b in kept["boards"]] == [
        (1, "kept", 51), (2, "kept", 51), (3, "skipped", 0)]
    assert kept["boards"][2]["detail"] == "nothing to keep: runs no program (bootloader)"
    assert kept["boards"][0]["detail"] == "51 values loaded back and read back"
    assert held.raw("CAN0", 1, TreeEdgeKind.PAR, "Max PWM") == 9000
    assert held.raw("CAN0", 3, TreeEdgeKind.PAR, "Max PWM") == armar3.PWM_FULL  # power-on value


def test_flash_keep_params_stops_before_programming_when_a_board_cannot_be_read(
        tmp_path: Path) -> None:
    mixed = str(_mixed(tmp_path, f'program = "{IMAGE}"\nautostart = true'))
    fleet = shared_fleet(mixed)
    try:
        fleet.run_for(1.0)  # AutoStart: every program comes up
        apps = [b.application for b in fleet.boards["CAN0"]]
        assert all(a is not None for a in apps)
        r = run("flash", IMAGE, "--keep-params", "--virtual", mixed)
        assert r.exit_code == 1
        err = " ".join(r.stderr.split())
        assert "nothing programmed: the values of CAN0 board 3 (head right) could not be " \
               "read (--force programs anyway)" in err
        assert "params failed: CAN0 board 3 (head right)" in " ".join(r.stdout.split())
        assert [b.application for b in fleet.boards["CAN0"]] == apps  # still running
        r = run("flash", IMAGE, "--keep-params", "--force", "--virtual", mixed)
        assert r.exit_code == 1  # programmed, but board 3's values were not kept
        out = " ".join(r.stdout.split())
        assert "3 of 3 board(s) verified" in out
        assert "params kept: CAN0 board 1 (neck)" in out
        assert "params failed: CAN0 board 3 (head right): not read before programming" in out
        assert "params not kept: CAN0 board 3 (head right)" in " ".join(r.stderr.split())
    finally:
        release_shared(fleet)
