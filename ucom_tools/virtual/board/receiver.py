"""Board side of the programming transfer as plain state: erase list, blocks, flow model.

One :class:`Reception` lives from Program BEGIN to the verified END (or ABORT, a new
BEGIN, a reset).  Blocks are known from their BLOCK frame; each data frame carries its
slot in the block, so a block fills in any order and a lost frame leaves exactly one
hole, which END reports (PARTIAL) and a resend fills.

The receive ring drives flow control: every data frame costs the board
``4 * word_program_us + frame_overhead_us`` (flash) or ``extram_frame_us`` (ExtRAM);
frames wait in a ring of ``rx_capacity`` frames.  At ``high_water`` buffered frames the
board sends Ready(PAUSE), at ``low_water`` Ready(RESUME); a frame that finds the ring
full is lost (overrun) and its slot stays empty.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Final

from ucom_tools.config.topology import Timing
from ucom_tools.memory import PROTECTED_KINDS, RegionKind, first_unprogrammable, page_refusal
from ucom_tools.virtual.board.nvmem import Memory
from ucom_tools.wire.answers import MAX_REPORTS
from ucom_tools.wire.codes import ErrorCode, MetaField, ResultStatus, Space, Target
from ucom_tools.wire.messages import (
    ProgramBlock,
    ProgramErase,
    ProgramMissing,
    ProgramPartial,
    ProgramResult,
)
from ucom_tools.wire.transfer import (
    PAGE_WORDS,
    WORDS_PER_FRAME,
    Block,
    block_crc,
    progid_of_blocks,
)

META_FIELDS: Final = frozenset(range(MetaField.NAME_0 + 7))
"""Every META field a transfer must carry before PREPARE (ProgID, size, date, name)."""


class RejectedBlock(Exception):
    def __init__(self, code: ErrorCode, detail: int) -> None:
        super().__init__(code.name)
        self.code = code
        self.detail = detail


def refusal_code(kind: RegionKind) -> ErrorCode:
    return ErrorCode.PROTECTED_ADDRESS if kind in PROTECTED_KINDS else ErrorCode.UNMAPPED_ADDRESS


@dataclass
class BlockState:
    """One block as the board knows it: where it goes and which frames arrived."""

    header: ProgramBlock
    data: bytearray
    got: int = 0
    """Bit i set = data frame i arrived."""
    stored: bool = False
    full: int = field(init=False, default=0)
    """``got`` when every frame arrived."""

    def __post_init__(self) -> None:
        self.full = (1 << self.header.frames) - 1

    @property
    def complete(self) -> bool:
        return self.got == self.full

    def holes(self) -> list[tuple[int, int]]:
        """Runs (first slot, count) of frames that did not arrive."""
        runs: list[tuple[int, int]] = []
        slot, n = 0, self.header.frames
        while slot < n:
            if self.got >> slot & 1:
                slot += 1
                continue
            end = slot
            while end < n and not self.got >> end & 1:
                end += 1
            runs.append((slot, end - slot))
            slot = end
        return runs


@dataclass
class Reception:
    """State of one transfer on one board."""

    target: Target
    blocks_total: int
    entry: int
    timing: Timing
    meta: dict[int, bytes] = field(default_factory=dict)
    erase_pages: list[tuple[Space, int]] = field(default_factory=list)
    prepared: bool = False
    erased: bool = False
    erase_start: float = 0.0
    """When PREPARE began the erase (board time, microseconds)."""
    pages_erased: int = 0
    """The pages of :attr:`erase_pages`, in order, erased so far (the erase goes page by
    page: :meth:`pages_begun`)."""
    blocks: dict[int, BlockState] = field(default_factory=dict)
    current: BlockState | None = None
    last_slot: int = -1
    """The slot of the last data frame since the current BLOCK frame (they rise)."""
    corrupt_blocks: int = 0
    """Blocks whose data did not match the CRC of their BLOCK frame (discarded)."""
    free_at: float = 0.0
    paused: bool = False
    overruns: int = 0
    failed_words: int = 0
    extram: dict[Space, Memory] = field(default_factory=dict)
    frame_cost: float = field(init=False, default=0.0)
    """Microseconds the board needs to store one data frame."""
    ring_time: float = field(init=False, default=0.0)
    """Microseconds of work a full receive ring holds (a frame beyond is lost)."""
    pause_time: float = field(init=False, default=0.0)
    """Microseconds of work at the high-water mark (PAUSE)."""

    def __post_init__(self) -> None:
        t = self.timing
        self.frame_cost = (t.extram_frame_us if self.target is Target.EXTRAM
                           else WORDS_PER_FRAME * t.word_program_us + t.frame_overhead_us)
        self.ring_time = t.rx_capacity * self.frame_cost
        self.pause_time = t.high_water * self.frame_cost

    # ---------------------------------------------------------------- preamble
    def add_erase(self, frame: ProgramErase) -> None:
        for page in range(frame.first_page, frame.first_page + frame.count):
            bad = page_refusal(frame.space, page)
            if bad is not None:
                raise RejectedBlock(refusal_code(bad[1]), (frame.space << 16) | bad[0])
            if (frame.space, page) not in self.erase_pages:
                self.erase_pages.append((frame.space, page))

    def meta_complete(self) -> bool:
        return self.meta.keys() >= META_FIELDS

    def meta_lacking(self) -> int:
        """The META fields not received, as a bit mask (bit i = field i)."""
        return sum(1 << f for f in META_FIELDS if f not in self.meta)

    def erase_time(self) -> float:
        if self.target is Target.EXTRAM:
            return 0.0
        return len(self.erase_pages) * self.timing.page_erase_us

    def pages_begun(self, t: float) -> int:
        """How many pages of :attr:`erase_pages` the erase has begun by board time ``t``
        (each takes ``page_erase_us``; a page begun is erased whole: a flash page erase
        cannot be cut)."""
        per_page = self.timing.page_erase_us
        total = len(self.erase_pages)
        if per_page <= 0:
            return total
        return min(total, int((t - self.erase_start) // per_page) + 1)

    # ---------------------------------------------------------------- blocks
    def open_block(self, header: ProgramBlock) -> None:
        """Make ``header``'s block the current one; raises :class:`RejectedBlock` for a
        block the board refuses.  A block met again (a resend) keeps what arrived."""
        self.current = None
        words = header.frames * WORDS_PER_FRAME
        detail = (header.space << 16) | header.address
        if header.index >= self.blocks_total:
            raise RejectedBlock(ErrorCode.BAD_VALUE, header.index)
        if header.address // PAGE_WORDS != (header.address + words - 1) // PAGE_WORDS:
            raise RejectedBlock(ErrorCode.BAD_VALUE, detail)
        bad = first_unprogrammable(header.space, header.address, words)
        if bad is not None:
            raise RejectedBlock(refusal_code(bad[1]), (header.space << 16) | bad[0])
        if self.target is Target.FLASH and (header.space, header.address // PAGE_WORDS) not in \
                self.erase_pages:
            raise RejectedBlock(ErrorCode.SEQUENCE, detail)
        known = self.blocks.get(header.index)
        if known is None or known.header != header:
            known = BlockState(header, bytearray(header.frames * 8))
            self.blocks[header.index] = known
        self.current = None if known.stored else known
        self.last_slot = -1

    def take_data(self, slot: int, data: bytes, t: float) -> BlockState | None:
        """Buffer one data frame at time ``t``; returns its block when this frame
        completed it.  A frame that overruns the receive ring is lost."""
        free = self.free_at
        start = free if free > t else t
        if start - t >= self.ring_time:
            self.overruns += 1
            return None
        self.free_at = start + self.frame_cost
        block = self.current
        if block is None:
            return None
        if slot <= self.last_slot:
            # slots rise after a BLOCK frame: this frame belongs to a block whose BLOCK
            # frame was lost, not to this one
            self.current = None
            return None
        self.last_slot = slot
        got = block.got
        if slot >= block.header.frames or got >> slot & 1:
            return None
        block.data[8 * slot:8 * slot + 8] = data
        block.got = got = got | 1 << slot
        if got != block.full:
            return None
        if block_crc(bytes(block.data)) != block.header.crc:
            block.got = 0  # some frame is not this block's: ask for all of it again
            self.corrupt_blocks += 1
            return None
        return block

    def stored_words(self) -> int:
        """Words stored so far (what END has to read back and checksum)."""
        return sum(b.header.frames * WORDS_PER_FRAME for b in self.blocks.values() if b.stored)

    def backlog(self, t: float) -> float:
        """Data frames waiting in the receive ring at time ``t``."""
        return (self.free_at - t) / self.frame_cost if self.free_at > t else 0.0

    # ---------------------------------------------------------------- end
    def reports(self) -> list[ProgramMissing | ProgramPartial]:
        """What is missing, in block order: runs of unknown blocks and the holes of known
        ones; at most :data:`MAX_REPORTS` (the rest is reported after the next END)."""
        out: list[ProgramMissing | ProgramPartial] = []
        i = 0
        while i < self.blocks_total and len(out) < MAX_REPORTS:
            b = self.blocks.get(i)
            if b is None:
                j = i
                while j < self.blocks_total and j not in self.blocks:
                    j += 1
                out.append(ProgramMissing(i, j - i))
                i = j
                continue
            if not b.stored:
                out += [ProgramPartial(i, first, count) for first, count in b.holes()]
            i += 1
        return out[:MAX_REPORTS]

    def expected_progid(self) -> int:
        raw = self.meta.get(MetaField.PROGID)
        return int.from_bytes(raw, "big") if raw else -1

    def result(self, memory: dict[Space, Memory]
               ) -> tuple[ProgramResult, list[ProgramMissing | ProgramPartial]]:
        """Verify what was stored: read every block back from ``memory`` and compute its
        ProgID the way the host did (:func:`~ucom_tools.wire.transfer.progid_of_blocks`)."""
        missing = self.reports()
        if missing:
            return ProgramResult(ResultStatus.MISSING, len(missing), 0), missing
        if self.failed_words:
            return ProgramResult(ResultStatus.FLASH_FAILURE, 0, 0), []
        stored = []
        for index in range(self.blocks_total):
            h = self.blocks[index].header
            nwords = h.frames * WORDS_PER_FRAME
            stored.append(Block(index, h.space, h.address,
                                tuple(memory[h.space].read(h.address, nwords))))
        progid = progid_of_blocks(stored)
        status = (ResultStatus.VERIFIED if progid == self.expected_progid()
                  else ResultStatus.PROGID_MISMATCH)
        return ProgramResult(status, 0, progid), []
