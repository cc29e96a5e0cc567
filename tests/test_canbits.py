"""CAN frame length accounting against Tab. B.2 and a bit-by-bit reference."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from tests import canref
from ucom_tools.wire import canbits

# Tab. B.2: effective payload rate at 1 Mbit/s with standard identifiers, in kbit/s
TABLE_B2 = {0: 0, 1: 145, 2: 254, 3: 338, 4: 405, 5: 460, 6: 505, 7: 544, 8: 577}


@pytest.mark.parametrize("dlc, kbits", TABLE_B2.items())
def test_unstuffed_rate_reproduces_table_b2(dlc: int, kbits: int) -> None:
    assert round(canbits.payload_rate(dlc) / 1000) == kbits


def _reference_bits(arb: int, data: bytes) -> int:
    return canref.standard(arb, data)


@given(st.integers(0, 0x7FF), st.binary(max_size=8))
def test_frame_bits_match_bit_by_bit_reference(arb: int, data: bytes) -> None:
    assert canbits.frame_bits(arb, data) == _reference_bits(arb, data)


@given(st.integers(1, 120).flatmap(lambda n: st.tuples(st.just(n), st.integers(0, 2**n - 1))))
def test_table_crc_equals_bitwise_crc(args: tuple[int, int]) -> None:
    n, value = args
    assert canbits.crc15(value, n) == canbits._crc15_bitwise(value, n)


def test_stuffing_bounds() -> None:
    # all-zero payload stuffs heavily, alternating bits not at all in the data field
    assert canbits.frame_bits(0x000, bytes(8)) > 111 + 15
    assert canbits.frame_bits(0x2C0, b"\x55" * 8) >= 111
    assert canbits.frame_bits(0x2C0, b"\x55" * 8) <= 111 + 24  # ISO 11898 worst case
