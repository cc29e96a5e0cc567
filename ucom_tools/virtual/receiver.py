"""Board side of the programming transfer: erase, receive blocks, pace, verify.

One :class:`Reception` lives from Program BEGIN to END (or ABORT / reset).  It owns the
receive-buffer model that drives flow control: every data frame costs the board
``4 * word_program_us + frame_overhead_us`` to program; frames wait in a ring of
``rx_capacity`` frames.  At ``high_water`` buffered frames the board sends Ready(PAUSE),
at ``low_water`` Ready(RESUME); a frame that finds the ring full is lost (overrun) and its
block is reported missing at END.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ucom_tools.config.topology import Timing
from ucom_tools.memory import PROTECTED_KINDS, Kind, first_unprogrammable, page_refusal
from ucom_tools.virtual.nvmem import Memory
from ucom_tools.wire.codes import ErrorCode, MetaField, ResultStatus, Space, Target
from ucom_tools.wire.messages import ProgramBlock, ProgramErase, ProgramMissing, ProgramResult
from ucom_tools.wire.transfer import PAGE_WORDS, WORDS_PER_FRAME, Block, progid_of_blocks


class RejectedBlock(Exception):
    def __init__(self, code: ErrorCode, detail: int) -> None:
        super().__init__(code.name)
        self.code = code
        self.detail = detail


def refusal_code(kind: Kind) -> ErrorCode:
    return ErrorCode.PROTECTED_ADDRESS if kind in PROTECTED_KINDS else ErrorCode.UNMAPPED_ADDRESS


@dataclass
class Reception:
    """State of one transfer on one board."""

    target: Target
    blocks_total: int
    entry: int
    timing: Timing
    meta: dict[int, bytes] = field(default_factory=dict)
    erase_pages: list[tuple[Space, int]] = field(default_factory=list)
    erased: bool = False
    received: dict[int, tuple[Space, int, int]] = field(default_factory=dict)
    current: ProgramBlock | None = None
    skip_current: bool = False
    buffer: bytearray = field(default_factory=bytearray)
    free_at: float = 0.0
    paused: bool = False
    overruns: int = 0
    failed_words: int = 0
    extram: dict[Space, Memory] = field(default_factory=dict)
    frame_cost: float = field(init=False, default=0.0)
    """Microseconds the board needs to store one data frame."""

    # ---------------------------------------------------------------- erase list
    def add_erase(self, frame: ProgramErase) -> None:
        for page in range(frame.first_page, frame.first_page + frame.count):
            bad = page_refusal(frame.space, page)
            if bad is not None:
                raise RejectedBlock(refusal_code(bad[1]), (frame.space << 16) | bad[0])
            self.erase_pages.append((frame.space, page))

    def erase_time(self) -> float:
        if self.target is Target.EXTRAM:
            return 0.0
        return len(self.erase_pages) * self.timing.page_erase_us

    def __post_init__(self) -> None:
        t = self.timing
        self.frame_cost = (t.extram_frame_us if self.target is Target.EXTRAM
                           else WORDS_PER_FRAME * t.word_program_us + t.frame_overhead_us)

    # ---------------------------------------------------------------- blocks
    def open_block(self, block: ProgramBlock) -> None:
        """Start a block; raises :class:`RejectedBlock` for a block the board refuses."""
        self.current = None
        self.buffer = bytearray()
        words = block.frames * WORDS_PER_FRAME
        detail = (block.space << 16) | block.address
        if block.index >= self.blocks_total:
            raise RejectedBlock(ErrorCode.BAD_VALUE, block.index)
        if block.address // PAGE_WORDS != (block.address + words - 1) // PAGE_WORDS:
            raise RejectedBlock(ErrorCode.BAD_VALUE, detail)
        bad = first_unprogrammable(block.space, block.address, words)
        if bad is not None:
            raise RejectedBlock(refusal_code(bad[1]), (block.space << 16) | bad[0])
        if self.target is Target.FLASH and (block.space, block.address // PAGE_WORDS) not in \
                self.erase_pages:
            raise RejectedBlock(ErrorCode.SEQUENCE, detail)
        self.current = block
        self.skip_current = block.index in self.received

    def take_data(self, data: bytes, t: float) -> tuple[bool, bytes | None]:
        """Buffer one data frame at time ``t``.

        Returns (accepted, completed block payload or None).  A frame that overruns the
        receive ring is dropped and spoils its block."""
        cost = self.frame_cost
        start = self.free_at if self.free_at > t else t
        backlog = (start - t) / cost
        if backlog >= self.timing.rx_capacity:
            self.overruns += 1
            self.current = None  # block incomplete -> missing at END
            return False, None
        self.free_at = start + cost
        block = self.current
        if block is None:
            return True, None
        self.buffer += data
        if len(self.buffer) == block.frames * 8:
            payload = bytes(self.buffer)
            self.buffer = bytearray()
            return True, payload
        return True, None

    def size_hint(self) -> int:
        """Words received so far (the amount END has to read back and checksum)."""
        return sum(n for _, _, n in self.received.values())

    def backlog(self, t: float) -> float:
        """Data frames waiting in the receive ring at time ``t``."""
        return (self.free_at - t) / self.frame_cost if self.free_at > t else 0.0

    # ---------------------------------------------------------------- end
    def missing_runs(self) -> list[ProgramMissing]:
        runs: list[ProgramMissing] = []
        i = 0
        while i < self.blocks_total:
            if i in self.received:
                i += 1
                continue
            j = i
            while j < self.blocks_total and j not in self.received:
                j += 1
            runs.append(ProgramMissing(i, j - i))
            i = j
        return runs

    def expected_progid(self) -> int:
        raw = self.meta.get(MetaField.PROGID)
        return int.from_bytes(raw, "big") if raw else -1

    def result(self, memory: dict[Space, Memory]) -> tuple[ProgramResult, list[ProgramMissing]]:
        """Verify what was stored: read every block back from ``memory`` and compute its
        ProgID the way the host did (:func:`~ucom_tools.wire.transfer.progid_of_blocks`)."""
        missing = self.missing_runs()
        if missing:
            n = sum(r.count for r in missing)
            return ProgramResult(ResultStatus.MISSING, min(n, 0xFFFF), 0), missing[:8]
        if self.failed_words:
            return ProgramResult(ResultStatus.FLASH_FAILURE, 0, 0), []
        stored = []
        for index in range(self.blocks_total):
            space, address, nwords = self.received[index]
            stored.append(Block(index, space, address,
                                tuple(memory[space].read(address, nwords))))
        progid = progid_of_blocks(stored)
        status = (ResultStatus.VERIFIED if progid == self.expected_progid()
                  else ResultStatus.PROGID_MISMATCH)
        return ProgramResult(status, 0, progid), []
