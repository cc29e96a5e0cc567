"""Cutting images into blocks, the ProgID algorithm and its published test vector."""

from __future__ import annotations

import zlib
from datetime import UTC, datetime

from ucom_tools.wire.codes import Space
from ucom_tools.wire.transfer import (
    ERASED,
    TransferPlan,
    erase_ranges,
    make_blocks,
    progid_of_blocks,
)

WHEN = datetime(2026, 1, 1, tzinfo=UTC)


def test_blocks_are_page_bounded_frame_aligned_and_gap_filled() -> None:
    words = {(Space.P, 0x0104): 0x1111, (Space.P, 0x0107): 0x2222, (Space.P, 0x0200): 0x3333}
    blocks = make_blocks(words)
    assert [(b.index, b.space, b.address, len(b.words)) for b in blocks] == [
        (0, Space.P, 0x0104, 4), (1, Space.P, 0x0200, 4)]
    assert blocks[0].words == (0x1111, ERASED, ERASED, 0x2222)
    assert blocks[0].payload() == bytes.fromhex("1111ffffffff2222")  # low byte first


def test_vector_words_are_not_transferred() -> None:
    words = {(Space.P, a): 0xE984 for a in range(0, 8)}
    blocks = make_blocks(words)
    assert blocks[0].address == 0x0004
    assert len(blocks[0].words) == 4


def test_p_blocks_come_before_x_blocks() -> None:
    words = {(Space.X, 0x1000): 1, (Space.P, 0x7000): 2}
    assert [b.space for b in make_blocks(words)] == [Space.P, Space.X]


def test_progid_test_vector() -> None:
    # man/ucom-protocol.7: P:0004-0007 = 0xE984 0x0004 0x1234 0xABCD -> 0x67228575
    words = {(Space.P, 4): 0xE984, (Space.P, 5): 0x0004, (Space.P, 6): 0x1234,
             (Space.P, 7): 0xABCD}
    blocks = make_blocks(words)
    raw = bytes.fromhex("00" "0004" "0004" "84e9" "0400" "3412" "cdab")
    assert progid_of_blocks(blocks) == zlib.crc32(raw) == 0x67228575


def test_erase_ranges_merge_contiguous_pages() -> None:
    words = {(Space.P, a): 0 for a in (0x0100, 0x0200, 0x0400)}
    words[(Space.X, 0x1000)] = 0
    ranges = [(e.space, e.first_page, e.count) for e in erase_ranges(make_blocks(words))]
    assert ranges == [(Space.P, 1, 2), (Space.P, 4, 1), (Space.X, 0x10, 1)]


def test_plan_frames_and_metadata() -> None:
    words = {(Space.P, a): a for a in range(0x0004, 0x0204)}
    plan = TransferPlan.build(words, entry=4, name="x.S", when=WHEN)
    frames = list(plan.block_frames())
    headers = [f for f in frames if f.__class__.__name__ == "ProgramBlock"]
    assert len(headers) == len(plan.blocks) == 3  # 0004-00FF, 0100-01FF, 0200-0203
    assert sum(len(b.words) for b in plan.blocks) == plan.size_words == 0x200
    assert len(plan.meta()) == 10
