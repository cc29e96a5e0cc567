"""Identifier layout (Tab. B.3) and function codes (Tab. B.4)."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from ucom_tools.errors import FrameError
from ucom_tools.wire.ids import (
    ALL,
    Address,
    Direction,
    Function,
    IdType,
    decode_id,
    encode_id,
    function_direction,
)


@given(st.integers(0, 31), st.sampled_from(IdType), st.integers(0, 31))
def test_identifier_round_trip(function: int, id_type: IdType, number: int) -> None:
    ident = encode_id(function, Address(id_type, number))
    assert 0 <= ident <= 0x7FF
    assert decode_id(ident) == (function, Address(id_type, number))


def test_identifier_bit_layout() -> None:
    # function in bits 10-6, type in bit 5, number in bits 4-0
    assert encode_id(Function.INFO, Address(IdType.SEQUENTIAL, 3)) == 0b00101_0_00011
    assert encode_id(Function.MCA_DSP_CI, Address(IdType.FIXED, 31)) == 0b11011_1_11111
    assert encode_id(Function.RESET, ALL) == 0


def test_reset_has_the_highest_priority() -> None:
    ids = {f: encode_id(f, Address(IdType.SEQUENTIAL, 31)) for f in Function}
    assert min(ids, key=ids.__getitem__) is Function.RESET


@pytest.mark.parametrize("bad", [-1, 32, 99])
def test_board_number_range_is_checked(bad: int) -> None:
    with pytest.raises(FrameError, match="board number"):
        Address(IdType.SEQUENTIAL, bad)


def test_function_range_is_checked() -> None:
    with pytest.raises(FrameError, match="function"):
        encode_id(32, ALL)
    with pytest.raises(FrameError, match="identifier"):
        decode_id(0x800)


def test_directions_follow_table_b4() -> None:
    from_pc = {0, 1, 7, 8, 9, 10, 11, 12, 13, 15, 21, 22, 24, 25, 26}
    from_dsp = {2, 3, 4, 5, 6, 14, 16, 17, 18, 19, 20, 23, 27}
    assert from_pc | from_dsp == set(range(28))
    for code in from_pc:
        assert Function(code).direction is Direction.HOST_TO_BOARD
    for code in from_dsp:
        assert Function(code).direction is Direction.BOARD_TO_HOST
    for code in range(28, 32):
        assert function_direction(code) is Direction.UNASSIGNED


def test_report_functions_are_100xx() -> None:
    assert [Function.report(c) for c in range(4)] == [16, 17, 18, 19]
    assert all(f >> 2 == 0b100 for f in (16, 17, 18, 19))
    with pytest.raises(FrameError):
        Function.report(4)


def test_labels_match_table() -> None:
    assert Function.XRESET.label == "XReset"
    assert Function.MCA_DUMPIO_DESCR_REQUEST.label == "MCA DumpIO Descr Request"
    assert Function.INIT_ACK.label == "Init Ack"
