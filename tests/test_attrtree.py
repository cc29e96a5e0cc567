"""The attribute tree parser and model on the dissertation's example (B.5), byte for byte."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest

from ucom_tools.config.attrtree import (
    BoardBlock,
    Edge,
    Tree,
    TreeEdgeKind,
    Value,
    dumps,
    load,
    parse,
)
from ucom_tools.errors import InputError, TreeError

ROOT = Path(__file__).resolve().parent.parent
EYES = ROOT / "attribute_trees" / "armar3" / "head_right.tree"
SEED = Path("/work/shared/seeds/000_e7080552dcd52608.txt")

# Every edge of B.5: index, kind, generic name, unique name, default text (None = none).
B5 = [
    (0, "CI", "MotorA Command", "Right Eye Command", "0"),
    (1, "CI", "MotorB Command", "Left Eye Command", "0"),
    (2, "CI", "MotorC Command", "MotorC Command", None),
    (3, "CI", "MotorA Target", "Right Eye Target", "0"),
    (4, "CI", "MotorB Target", "Left Eye Target", "0"),
    (5, "CI", "MotorC Target", "MotorC Target", None),
    (6, "CI", "MotorA Reset Offset", "Right Eye Reset Offset", "-12725"),
    (7, "CI", "MotorB Reset Offset", "Left Eye Reset Offset", "-11457"),
    (8, "CI", "MotorC Reset Offset", "MotorC Reset Offset", None),
    (9, "CI", "Send Command via serial", "Send Command via serial", None),
    (10, "CI", "MotorA TargetVel", "Right Eye Target Vel", None),
    (11, "CI", "MotorB TargetVel", "Left Eye Target Vel", None),
    (12, "CI", "MotorC TargetVel", "MotorC Target Vel", None),
    (13, "SO", "Encoder 0", "Right Eye Joint Sensor", None),
    (14, "SO", "Encoder 1", "Right Eye Motor Encoder", None),
    (15, "SO", "Encoder 2", "Left Eye Joint Sensor", None),
    (16, "SO", "Encoder 3", "Left Eye Motor Encoder", None),
    (17, "SO", "Encoder 4", "Encoder 4", None),
    (18, "SO", "Encoder 5", "Encoder 5", None),
    (19, "SO", "Voltage A", "Right Eye Voltage", None),
    (20, "SO", "Voltage B", "Left Eye Voltage", None),
    (21, "SO", "Voltage C", "Voltage C", None),
    (22, "SO", "AD Channel 6", "AD Channel 6", None),
    (23, "SO", "AD Channel 7", "AD Channel 7", None),
    (24, "SO", "MotorA Reset Answer", "Right Eye Reset Answer", None),
    (25, "SO", "MotorB Reset Answer", "Left Eye Reset Answer", None),
    (26, "SO", "MotorC Reset Answer", "MotorC Reset Answer", None),
    (27, "SO", "Velocity A", "Right Eye Velocity", None),
    (28, "SO", "Velocity B", "Left Eye Velocity", None),
    (29, "SO", "Velocity C", "MotorC Velocity", None),
    (30, "SO", "Motor A Settled", "Right Eye Axis Settled", None),
    (31, "SO", "Motor B Settled", "Left Eye Axis Settled", None),
    (32, "SO", "Motor C Settled", "MotorC Axis Settled", None),
    (33, "PAR", "LoopTime(ms)", "LoopTime(ms)", "1"),
    (34, "PAR", "Max PWM", "Max PWM", "14000"),
    (35, "PAR", "Revert Encoder CountDir(BitMask)", "Revert Encoder CountDir(BitMask)", "0x0"),
    (36, "PAR", "Set Joint Moving Direction(BitMask)", "Set Joint Moving Direction(BitMask)",
     "0x3"),
    (37, "PAR", "Encoder Prescaler(BitMask)", "Encoder Prescaler(BitMask)", "0x444"),
    (38, "PAR", "MotorA P", "RightEye P", "50"),
    (39, "PAR", "MotorA I", "RightEye I", "0.0005"),
    (40, "PAR", "MotorA D", "RightEye D", "0"),
    (41, "PAR", "MotorB P", "LeftEye P", "50"),
    (42, "PAR", "MotorB I", "LeftEye I", "0.0005"),
    (43, "PAR", "MotorB D", "LeftEye D", "0"),
    (44, "PAR", "MotorC P", "MotorC P", None),
    (45, "PAR", "MotorC I", "MotorC I", None),
    (46, "PAR", "MotorC D", "MotorC D", None),
    (47, "PAR", "Reset A PWM", "Reset RightEye PWM", "-7000"),
    (48, "PAR", "Reset B PWM", "Reset LeftEye PWM", "-7000"),
    (49, "PAR", "Reset C PWM", "Reset MotorC PWM", "7000"),
    (50, "PAR", "MotorA feedforward gain", "RightEye feedforward gain", "1"),
    (51, "PAR", "MotorB feedforward gain", "LeftEye feedforward gain", "1"),
    (52, "PAR", "MotorC feedforward gain", "MotorC feedforward gain", "1"),
    (53, "PAR", "MotorA Velocity P", "RightEye Velocity P", "1"),
    (54, "PAR", "MotorA Velocity I", "RightEye Velocity I", "0.01"),
    (55, "PAR", "MotorA Velocity D", "RightEye Velocity D", "0"),
    (56, "PAR", "MotorA Max Velocity (x1000)", "RightEye Max Velocity (x1000)", "500"),
    (57, "PAR", "MotorB Velocity P", "LeftEye Velocity P", "1"),
    (58, "PAR", "MotorB Velocity I", "LeftEye Velocity I", "0.01"),
    (59, "PAR", "MotorB Velocity D", "LeftEye Velocity D", "0"),
    (60, "PAR", "MotorB Max Velocity (x1000)", "LeftEye Max Velocity (x1000)", "500"),
    (61, "PAR", "MotorC Velocity P", "MotorC Velocity P", "0"),
    (62, "PAR", "MotorC Velocity I", "MotorC Velocity I", "0"),
    (63, "PAR", "MotorC Velocity D", "MotorC Velocity D", "0"),
    (64, "PAR", "MotorC Max Velocity (x1000)", "MotorC Max Velocity (x1000)", "1"),
    (65, "PAR", "MotorA Max Position", "RightEye Max Position", "10000"),
    (66, "PAR", "MotorA Min Position", "RightEye Min Position", "-10000"),
    (67, "PAR", "MotorB Max Position", "LeftEye Max Position", "10000"),
    (68, "PAR", "MotorB Min Position", "LeftEye Min Position", "-10000"),
    (69, "PAR", "MotorC Max Position", "MotorC Max Position", "30000"),
    (70, "PAR", "MotorC Min Position", "MotorC Min Position", "-30000"),
]

PARAMETER_ORDER = [
    "LoopTime(ms)", "Max PWM", "Revert Encoder CountDir(BitMask)",
    "Set Joint Moving Direction(BitMask)", "Encoder Prescaler(BitMask)", "Reset RightEye PWM",
    "Reset LeftEye PWM", "Reset MotorC PWM", "RightEye P", "RightEye I", "RightEye D",
    "LeftEye P", "LeftEye I", "LeftEye D", "RightEye feedforward gain",
    "LeftEye feedforward gain", "MotorC feedforward gain", "RightEye Velocity P",
    "RightEye Velocity I", "RightEye Velocity D", "RightEye Max Velocity (x1000)",
    "LeftEye Velocity P", "LeftEye Velocity I", "LeftEye Velocity D",
    "LeftEye Max Velocity (x1000)", "MotorC Velocity P", "MotorC Velocity I",
    "MotorC Velocity D", "MotorC Max Velocity (x1000)", "RightEye Max Position",
    "RightEye Min Position", "LeftEye Max Position", "LeftEye Min Position",
    "MotorC Max Position", "MotorC Min Position",
]
CI_ORDER = ["Right Eye Command", "Left Eye Command", "Right Eye Target", "Left Eye Target",
            "Right Eye Reset Offset", "Left Eye Reset Offset"]


def eyes_text() -> str:
    return EYES.read_text(encoding="utf-8")


def test_bundled_eyes_tree_is_the_printed_example() -> None:
    """Lines 2276-2415 of the dissertation text without the six fence lines and the six
    blank lines of the two page breaks: 128 lines, nothing else changed."""
    data = EYES.read_bytes()
    assert data.count(b"\n") == 128 and data.endswith(b"}DSP\n")
    assert hashlib.sha256(data).hexdigest() == (
        "a16e4ba782b77e6f113a757ef1d71fdeee045d5aa1c950ea533d97185cfe63a3")
    if SEED.exists():
        dropped = {2276, 2309, 2311, 2374, 2376, 2415, 2310, 2312, 2373, 2375, 2377, 2414}
        seed = SEED.read_text(encoding="utf-8").split("\n")
        kept = [seed[n - 1] for n in range(2276, 2416) if n not in dropped]
        assert data.decode("utf-8") == "\n".join(kept) + "\n"


def test_example_irregularities_are_in_the_file() -> None:
    lines = eyes_text().split("\n")
    assert lines[2] == "    Prefix : Eyes"
    assert lines[80] == "Parameter {"
    assert lines[63] == "56:MotorA Max Velocity (x1000)==> RightEye Max Velocity (x1000)"
    assert lines[79] == lines[117] == ""


def test_b5_counts() -> None:
    (board,) = load(EYES).boards
    assert (board.number, board.prefix) == (0, "Eyes")
    assert len(board.edges) == 71
    assert [len(board.of_kind(k)) for k in TreeEdgeKind] == [13, 20, 38]
    assert [e.index for e in board.of_kind(TreeEdgeKind.CI)] == list(range(13))
    assert [e.index for e in board.of_kind(TreeEdgeKind.SO)] == list(range(13, 33))
    assert [e.index for e in board.of_kind(TreeEdgeKind.PAR)] == list(range(33, 71))
    assert len(board.defaults(TreeEdgeKind.PAR)) == 35
    assert len(board.defaults(TreeEdgeKind.CI)) == 6
    assert len(board.defaults()) == 41
    assert sum(e.generic == e.unique for e in board.edges) == 25


@pytest.mark.parametrize("index, kind, generic, unique, default", B5)
def test_b5_every_edge(index: int, kind: str, generic: str, unique: str,
                       default: str | None) -> None:
    board = load(EYES).boards[0]
    e = board.edges[index]
    assert (e.index, e.kind.value, e.generic, e.unique) == (index, kind, generic, unique)
    assert (e.default.text if e.default else None) == default
    assert e.line == index + (6 if index <= 12 else 7 if index <= 32 else 8)
    assert board.edge(unique) is e and board.generic(generic) is e


def test_b5_default_numbers_and_lines() -> None:
    board = load(EYES).boards[0]
    numbers = {e.unique: e.default.number for e in board.edges if e.default}
    assert numbers["Encoder Prescaler(BitMask)"] == 0x444 == 1092
    assert numbers["Set Joint Moving Direction(BitMask)"] == 3
    assert numbers["RightEye I"] == 0.0005 and isinstance(numbers["RightEye I"], float)
    assert numbers["Max PWM"] == 14000 and isinstance(numbers["Max PWM"], int)
    assert numbers["Right Eye Reset Offset"] == -12725
    assert numbers["MotorC Min Position"] == -30000
    by_line = sorted((e.default_line, e.unique) for e in board.edges if e.kind is TreeEdgeKind.PAR
                     and e.default)
    assert [u for _, u in by_line] == PARAMETER_ORDER
    assert [n for n, _ in by_line] == list(range(82, 117))
    ci = sorted((e.default_line, e.unique) for e in board.edges if e.kind is TreeEdgeKind.CI
                and e.default)
    assert ci == list(zip(range(120, 126), CI_ORDER, strict=True))


@pytest.mark.parametrize("variant", ["crlf", "tabs", "trailing", "bom", "no_final_newline",
                                     "shuffled_defaults", "noise_comments"])
def test_example_variants_parse_the_same(variant: str) -> None:
    text = eyes_text()
    lines = text.split("\n")[:-1]
    if variant == "crlf":
        text = text.replace("\n", "\r\n")
    elif variant == "tabs":
        text = "\n".join("\t" * (len(x) - len(x.lstrip(" "))) + x.lstrip(" ")
                         for x in lines) + "\n"
    elif variant == "trailing":
        text = "\n".join(x + " \t " for x in lines) + "\n"
    elif variant == "bom":
        text = "\ufeff" + text
    elif variant == "no_final_newline":
        text = text.rstrip("\n")
    elif variant == "shuffled_defaults":
        text = "\n".join(lines[:81] + lines[81:116][::-1] + lines[116:]) + "\n"
    elif variant == "noise_comments":
        text = "\n".join(f"# note {i}\n{x}\n\n  #CIx" for i, x in enumerate(lines)) + "\n"
    assert parse(text.encode("utf-8"), "v") == load(EYES)
    assert parse(text, "v") == load(EYES)


@pytest.mark.parametrize("old, new, line, column, fragment", [
    ("(x1000)==> RightEye", "(x1000)=> RightEye", 64, 4, "missing '==>'"),
    ("RightEye I:0.0005", "RightEye I:0,0005", 91, 14, "bad value '0,0005'"),
    ("}Parameter", "}Parameters", 117, 1, "'}Parameters' does not close"),
    ("  Max PWM:14000", "  Max PWM:14000 # x", 83, 11, "no inline comments"),
    ("\n# PAR\n", "\n", 81, 3, "'LoopTime(ms)' is a SO edge (index 33)"),
    ("    Left Eye Reset Offset:-11457", "    Left Eye Command:1", 125, 5,
     "a second default for 'Left Eye Command' (first at line 121)"),
    ("  0{", "  0 {", 0, 0, None),
    ("}0\n}DSP", "}0\n}DSP\n}DSP", 129, 1, "'}DSP' closes no open block"),
])
def test_broken_example_names_file_line_column(old: str, new: str, line: int, column: int,
                                               fragment: str | None) -> None:
    text = eyes_text()
    assert text.count(old) == 1
    if fragment is None:  # not broken: 'Name {' opens a block like 'Name{'
        assert parse(text.replace(old, new), "eyes.tree") == load(EYES)
        return
    with pytest.raises(TreeError) as exc:
        parse(text.replace(old, new), "eyes.tree")
    err = exc.value
    assert (err.line, err.column) == (line, column)
    assert fragment in err.reason
    assert str(err).startswith(f"eyes.tree:{line}:{column}: ")
    assert isinstance(err, InputError)


def test_a_ci_default_may_be_added_for_any_ci_edge() -> None:
    text = eyes_text().replace("    Left Eye Reset Offset:-11457", "    Left Eye Target Vel:0")
    board = parse(text, "eyes").boards[0]
    assert board.edge("Left Eye Target Vel").default == Value.parse("0")
    assert board.edge("Left Eye Reset Offset").default is None
    assert len(board.defaults(TreeEdgeKind.CI)) == 6


# ----------------------------------------------------------------------------- values
@pytest.mark.parametrize("text, number", [
    ("0", 0), ("-7000", -7000), ("14000", 14000), ("007", 7), ("0.0005", 0.0005),
    ("-0.5", -0.5), ("0x0", 0), ("0x444", 0x444), ("0xfF", 255), ("-0x10", -16),
    ("1" + "0" * 300, 10 ** 300),
])
def test_value_grammar_accepts(text: str, number: int | float) -> None:
    v = Value.parse(text)
    assert v.text == text and v.number == number and type(v.number) is type(number)


@pytest.mark.parametrize("text", [
    "", "0,0005", "1e3", "1E3", "abc", "+5", ".5", "5.", "0X1F", "0x", "0x1.8", "14 000",
    "--5", "- 5", "\"5\"", "14000 # x", "inf", "nan", "١٢", "1_000", "0b101", "1" + "0" * 400,
    "0x1" + "0" * 260, "1" * 400 + ".0",
])
def test_value_grammar_refuses(text: str) -> None:
    with pytest.raises(ValueError):
        Value.parse(text)


@pytest.mark.parametrize("number, text", [
    (5, "5"), (-3, "-3"), (0.5, "0.5"), (1e-05, "0.00001"), (1e20, "100000000000000000000.0"),
    (-2.0, "-2.0"),
])
def test_value_of_number_writes_no_exponent(number: float, text: str) -> None:
    v = Value.of(number)
    assert v.text == text and v.number == number and type(v.number) is type(number)


def test_value_of_refuses_what_a_tree_cannot_hold() -> None:
    for bad in (float("inf"), float("nan")):
        with pytest.raises(ValueError):
            Value.of(bad)
    with pytest.raises(TypeError):
        Value.of(True)


def test_values_compare_by_text() -> None:
    assert Value.parse("0x3") != Value.parse("3")
    assert Value.parse("0x3").number == Value.parse("3").number


# ----------------------------------------------------------------------------- model
def test_kind_sections() -> None:
    assert [k.section for k in TreeEdgeKind] == ["ControllerInput", None, "Parameter"]


def test_lookups_raise_key_error() -> None:
    tree = load(EYES)
    with pytest.raises(KeyError):
        tree.board(1)
    with pytest.raises(KeyError):
        tree.boards[0].edge("MotorA Target")  # a generic name, not a unique one


def test_several_boards_keep_file_order_and_names_may_repeat_across_boards() -> None:
    eyes = load(EYES).boards[0]
    other = BoardBlock(7, "Other", eyes.edges)
    tree = parse(dumps(Tree((other, eyes))), "two")
    assert tree.numbers == (7, 0)
    assert tree.board(7).edges == tree.board(0).edges
    assert tree.board(7).prefix == "Other"


def test_missing_file_is_a_tree_error(tmp_path: Path) -> None:
    with pytest.raises(TreeError, match="no such attribute tree file"):
        load(tmp_path / "nope.tree")


def test_edges_compare_without_lines() -> None:
    a = Edge(0, TreeEdgeKind.CI, "g", "u", Value.parse("1"), line=3, default_line=9)
    assert a == Edge(0, TreeEdgeKind.CI, "g", "u", Value.parse("1"))
