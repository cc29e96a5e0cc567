"""The broken-tree corpus (tests/data/trees/*.tree): one defect per file, each reported at
the right FILE:LINE:COL with the right message, by the library and by ``ucom tree check``.

Most files are this small tree with one line changed (line numbers refer to it)::

     1 DSP{                                   12       4:MotorA P ==> Pan P
     2   0{                                   13     }MappingTable
     3     Prefix : Mini                      14     Parameter {
     4     MappingTable{                      15       Max PWM:14000
     5       # CI                             16       Pan P:50
     6       0:MotorA Command ==> Pan Command 17     }Parameter
     7       1:MotorA Target ==> Pan Target   18     ControllerInput{
     8       # SO                             19       Pan Command:0
     9       2:Encoder 0 ==> Pan Joint Sensor 20     }ControllerInput
    10       # PAR                            21   }0
    11       3:Max PWM ==> Max PWM            22 }DSP
"""

from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner

from ucom_tools.cli.main import cli
from ucom_tools.config.attrtree import load, parse
from ucom_tools.errors import TreeError

CORPUS = Path(__file__).parent / "data" / "trees"

MINI = """DSP{
  0{
    Prefix : Mini
    MappingTable{
      # CI
      0:MotorA Command ==> Pan Command
      1:MotorA Target ==> Pan Target
      # SO
      2:Encoder 0 ==> Pan Joint Sensor
      # PAR
      3:Max PWM ==> Max PWM
      4:MotorA P ==> Pan P
    }MappingTable
    Parameter {
      Max PWM:14000
      Pan P:50
    }Parameter
    ControllerInput{
      Pan Command:0
    }ControllerInput
  }0
}DSP
"""

# file name (without .tree), line, column, a fragment of the message
CASES = [
    ("bad_close", 13, 5, "'}Mapping' does not close the innermost open block 'MappingTable'"),
    ("bad_close_case", 13, 5, "does not close the innermost open block 'MappingTable'"),
    ("bad_close_outer", 21, 3, "'}DSP' does not close the innermost open block '0'"),
    ("bad_value_blank_inside", 15, 15, "bad value '14 000'"),
    ("bad_value_comma", 15, 15, "bad value '0,0005'"),
    ("bad_value_double_minus", 15, 15, "bad value '--5'"),
    ("bad_value_exponent", 15, 15, "bad value '1e3'"),
    ("bad_value_hex_capital_x", 15, 15, "bad value '0X1F'"),
    ("bad_value_hex_fraction", 15, 15, "bad value '0x1.8'"),
    ("bad_value_hex_no_digits", 15, 15, "bad value '0x'"),
    ("bad_value_no_leading_digit", 15, 15, "bad value '.5'"),
    ("bad_value_no_trailing_digit", 15, 15, "bad value '5.'"),
    ("bad_value_out_of_range", 15, 15, "out of range (not a finite double)"),
    ("bad_value_plus", 15, 15, "bad value '+5'"),
    ("bad_value_quoted", 15, 15, 'bad value \'"5"\''),
    ("bad_value_word", 15, 15, "bad value 'abc'"),
    ("blank_and_comments_only", 0, 0, 'empty attribute tree'),
    ("block_before_dsp", 1, 1, "expected 'DSP{' at the top level, got 'Robot{'"),
    ("block_in_parameter", 17, 7, "'Gains{' opens a block inside Parameter (opened at line 14)"),
    ("block_without_name", 14, 5, "'{' without a block name"),
    ("board_negative", 2, 3, 'a board block is named by its number'),
    ("board_not_a_number", 2, 3, 'a board block is named by its number'),
    ("close_without_name", 13, 5, "'}' without a name: expected '}MappingTable'"),
    ("close_without_open", 23, 1, "'}DSP' closes no open block"),
    ("colon_in_unique_name", 7, 30, "':' is not allowed in a name"),
    ("content_before_dsp", 1, 1, "expected 'DSP{' at the top level"),
    ("content_in_dsp", 2, 3, "expected a board block '<n>{'"),
    ("default_ci_in_parameter", 16, 7,
     "'Pan Command' is a CI edge (index 0); Parameter takes PAR edges only"),
    ("default_generic_name", 16, 7,
     "it is the generic name of edge 4, and defaults are keyed by unique names ('Pan P')"),
    ("default_par_in_controller_input", 19, 7,
     "'Pan P' is a PAR edge (index 4); ControllerInput takes CI edges only"),
    ("default_so_edge", 16, 7, 'SO edges take no defaults'),
    ("default_unknown_name", 16, 7, "'Tilt P' is not a unique name of board 0"),
    ("default_without_colon", 15, 7, "expected '<unique name>:<value>'"),
    ("dsp_without_board", 1, 1, 'DSP has no board block'),
    ("duplicate_board_number", 22, 3, 'board number 0 is used twice (first at line 2)'),
    ("duplicate_generic_name", 7, 9, "generic name 'MotorA Command' is also edge 0 (line 6)"),
    ("duplicate_prefix", 23, 14, "prefix 'Mini' is also board 0's"),
    ("duplicate_unique_across_kinds", 11, 21, "unique name 'Pan Target' is also edge 1 (line 7)"),
    ("duplicate_unique_name", 7, 27, "unique name 'Pan Command' is also edge 0 (line 6)"),
    ("edge_before_kind_marker", 5, 7, 'edge 0 comes before any kind marker'),
    ("empty", 0, 0, "empty attribute tree: no 'DSP{' block"),
    ("empty_generic_name", 7, 10, "empty generic name before '==>'"),
    ("empty_mapping_table", 4, 5, 'MappingTable of board 0 has no edge'),
    ("empty_prefix", 3, 13, 'Prefix without a name'),
    ("empty_unique_name", 7, 26, "empty unique name after '==>'"),
    ("index_arabic_digit", 7, 7, 'is not an index'),
    ("index_duplicate", 7, 7, 'index 0 out of sequence, expected 1'),
    ("index_gap", 7, 7, 'index 2 out of sequence, expected 1'),
    ("index_not_a_number", 7, 7, "'x' is not an index"),
    ("index_order", 6, 7, 'index 1 out of sequence, expected 0'),
    ("inline_comment", 15, 15, '(there are no inline comments)'),
    ("invalid_utf8", 1, 1, 'not UTF-8: byte 0xe4'),
    ("lone_carriage_return", 16, 15, 'a carriage return without a line feed'),
    ("marker_lowercase", 6, 7, 'edge 0 comes before any kind marker'),
    ("marker_twice", 8, 7, "a second '# CI' marker (first at line 5)"),
    ("markers_out_of_order", 10, 7, "'# SO' after '# PAR': kind markers come in the order"),
    ("missing_arrow", 7, 9, "missing '==>'"),
    ("missing_colon", 7, 7, "expected '<index>:<generic name> ==> <unique name>'"),
    ("missing_mapping_table", 2, 3, 'board 0 has no MappingTable'),
    ("missing_prefix", 2, 3, "board 0 has no 'Prefix : <name>' line"),
    ("missing_value", 15, 15, "no value after 'Max PWM:'"),
    ("nul_byte", 1, 1, 'NUL byte at byte offset'),
    ("parameter_before_mapping_table", 4, 5, 'Parameter before MappingTable in board 0'),
    ("second_arrow", 7, 31, "a second '==>'"),
    ("second_default", 16, 7, "a second default for 'Max PWM' (first at line 15)"),
    ("second_dsp", 23, 1, 'a second DSP block'),
    ("second_mapping_table", 14, 5, 'a second MappingTable block in board 0 (first at line 4)'),
    ("second_prefix", 4, 5, 'a second Prefix in board 0 (first at line 3)'),
    ("unclosed_block", 1, 1, "block 'DSP' is never closed: expected '}DSP'"),
    ("unclosed_inner", 13, 5,
     "opens a block inside MappingTable (opened at line 4); is '}MappingTable' missing?"),
    ("unique_name_hash", 7, 27, "a name must not begin with '#'"),
    ("unknown_block", 4, 5, "unknown block 'Mapping Table' in board 0"),
    ("unknown_key_in_board", 3, 5, "expected 'Prefix : <name>' or a MappingTable"),
]


def test_mini_tree_is_valid() -> None:
    board = parse(MINI, "mini").boards[0]
    assert [e.unique for e in board.edges] == ["Pan Command", "Pan Target", "Pan Joint Sensor",
                                               "Max PWM", "Pan P"]
    assert {k: v.text for k, v in board.defaults().items()} == {
        "Pan Command": "0", "Max PWM": "14000", "Pan P": "50"}


def test_every_corpus_file_has_an_expectation() -> None:
    assert sorted(p.stem for p in CORPUS.glob("*.tree")) == sorted(c[0] for c in CASES)


@pytest.mark.parametrize("name, line, column, fragment", CASES, ids=[c[0] for c in CASES])
def test_defect_is_reported_where_it_is(name: str, line: int, column: int,
                                        fragment: str) -> None:
    path = CORPUS / f"{name}.tree"
    with pytest.raises(TreeError) as exc:
        load(path)
    err = exc.value
    assert (err.line, err.column) == (line, column), str(err)
    assert fragment in err.reason
    assert str(err) == f"{path}:{line}:{column}: {err.reason}"


@pytest.mark.parametrize("name, line, column, fragment", CASES, ids=[c[0] for c in CASES])
def test_tree_check_exits_3_with_one_red_line(name: str, line: int, column: int,
                                              fragment: str) -> None:
    path = CORPUS / f"{name}.tree"
    r = CliRunner().invoke(cli, ["tree", "check", str(path)])
    assert r.exit_code == 3
    assert r.stdout == ""
    (err_line,) = r.stderr.splitlines()
    assert err_line.startswith(f"ucom: bad input: {path}:{line}:{column}: ")
    assert fragment in err_line
