"""The programming transfer, as pure data: image words -> blocks -> ProgID and frames.

An image is a mapping ``(space, word address) -> word``.  It is cut into *blocks*: the
used words of one 256-word flash page, widened to whole 4-word data frames, gaps filled
with 0xFFFF (erased flash).  Blocks are numbered in order (P before X, ascending
addresses).  The ProgID is CRC-32 (ISO-HDLC, as zlib.crc32) over every block's header
``space (1 byte) | address (2 bytes, big endian) | word count (2 bytes, big endian)``
followed by its words, low byte first.  See ``man/ucom-protocol.7``.
"""

from __future__ import annotations

import binascii
import itertools
import sys
import zlib
from array import array
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from datetime import UTC, datetime

from ucom_tools.wire.codes import NAME_CHUNKS, MetaField, Space, Target
from ucom_tools.wire.messages import (
    ProgramBegin,
    ProgramBlock,
    ProgramData,
    ProgramErase,
    ProgramMeta,
    ProgramPrepare,
)

PAGE_WORDS = 256
WORDS_PER_FRAME = 4
FRAMES_PER_PAGE = PAGE_WORDS // WORDS_PER_FRAME
ERASED = 0xFFFF
VECTOR_WORDS = range(0x0000, 0x0004)
"""P:0000-0003 belong to the bootloader: an image's own words there are not transferred."""
DATE_EPOCH = datetime(2000, 1, 1, tzinfo=UTC)


def words_to_bytes(words: Iterable[int]) -> bytes:
    """16-bit words as CAN data bytes, low byte first."""
    raw = array("H", words)
    if sys.byteorder == "big":
        raw.byteswap()
    return raw.tobytes()


def bytes_to_words(data: bytes) -> array:
    """CAN data bytes (low byte first) as 16-bit words."""
    words = array("H")
    words.frombytes(data)
    if sys.byteorder == "big":
        words.byteswap()
    return words


@dataclass(frozen=True, slots=True)
class Block:
    """One unit of the transfer: ``len(words)`` words from ``space:address``."""

    index: int
    space: Space
    address: int
    words: tuple[int, ...]

    @property
    def page(self) -> int:
        return self.address // PAGE_WORDS

    @property
    def frames(self) -> int:
        return len(self.words) // WORDS_PER_FRAME

    def payload(self) -> bytes:
        """The block's words as CAN data bytes, low byte first."""
        return words_to_bytes(self.words)

    def header(self) -> ProgramBlock:
        return ProgramBlock(self.space, self.address, self.frames, self.index,
                            block_crc(self.payload()))

    def data_frames(self, slots: Iterable[int] | None = None) -> list[ProgramData]:
        """The block's data frames (all, or those at ``slots``), each knowing its slot."""
        raw = self.payload()
        chosen = range(self.frames) if slots is None else sorted(slots)
        return [ProgramData(raw[8 * i:8 * i + 8], i) for i in chosen]


def block_crc(payload: bytes) -> int:
    """CRC-16/CCITT-FALSE (polynomial 0x1021, initial value 0xFFFF, no reflection) of a
    block's data bytes, carried in its BLOCK frame."""
    return binascii.crc_hqx(payload, 0xFFFF)


def make_blocks(words: Mapping[tuple[Space, int], int]) -> list[Block]:
    """Cut image words into blocks; the reset-vector words P:0000-0003 are left out."""
    keys = sorted(k for k in words if not (k[0] is Space.P and k[1] in VECTOR_WORDS))
    blocks: list[Block] = []
    for (space, _page), group in itertools.groupby(keys, lambda k: (k[0], k[1] // PAGE_WORDS)):
        addrs = [a for _, a in group]
        lo = addrs[0] // WORDS_PER_FRAME * WORDS_PER_FRAME
        hi = (addrs[-1] // WORDS_PER_FRAME + 1) * WORDS_PER_FRAME
        if hi - lo == len(addrs):
            values = tuple(words[(space, a)] for a in addrs)
        else:
            values = tuple(words.get((space, a), ERASED) for a in range(lo, hi))
        blocks.append(Block(len(blocks), space, lo, values))
    return blocks


def progid_of_blocks(blocks: Iterable[Block]) -> int:
    """The ProgID (CRC-32) of a sequence of blocks."""
    crc = 0
    for b in blocks:
        head = bytes((b.space,)) + b.address.to_bytes(2, "big") + len(b.words).to_bytes(2, "big")
        crc = zlib.crc32(head + b.payload(), crc)
    return crc & 0xFFFFFFFF


def erase_ranges(blocks: Iterable[Block]) -> list[ProgramErase]:
    """The ERASE frames covering every page the blocks touch, as contiguous runs."""
    pages = sorted({(b.space, b.page) for b in blocks})
    out: list[ProgramErase] = []
    for space, page in pages:
        last = out[-1] if out else None
        if last and last.space is space and last.first_page + last.count == page:
            out[-1] = ProgramErase(space, last.first_page, last.count + 1)
        else:
            out.append(ProgramErase(space, page, 1))
    return out


def encode_date(when: datetime) -> int:
    """Programming date as seconds since 2000-01-01 UTC (META field DATE)."""
    return max(0, int((when - DATE_EPOCH).total_seconds())) & 0xFFFFFFFF


def decode_date(value: int) -> datetime:
    return datetime.fromtimestamp(DATE_EPOCH.timestamp() + value, tz=UTC)


def meta_frames(progid: int, size_words: int, when: datetime, name: str) -> list[ProgramMeta]:
    raw = name.encode("latin-1", "replace")[: 4 * NAME_CHUNKS].ljust(4 * NAME_CHUNKS, b"\0")
    frames = [
        ProgramMeta(MetaField.PROGID, progid.to_bytes(4, "big")),
        ProgramMeta(MetaField.SIZE, size_words.to_bytes(4, "big")),
        ProgramMeta(MetaField.DATE, encode_date(when).to_bytes(4, "big")),
    ]
    frames += [ProgramMeta(MetaField.NAME_0 + i, raw[4 * i:4 * i + 4]) for i in range(NAME_CHUNKS)]
    return frames


@dataclass(frozen=True, slots=True)
class TransferPlan:
    """Everything the host sends for one image, computed once."""

    target: Target
    entry: int
    blocks: tuple[Block, ...]
    progid: int
    size_words: int
    name: str
    when: datetime

    @classmethod
    def build(cls, words: Mapping[tuple[Space, int], int], *, entry: int, name: str,
              when: datetime, target: Target = Target.FLASH) -> TransferPlan:
        return cls.of_blocks(tuple(make_blocks(words)), entry=entry, name=name, when=when,
                             target=target)

    @classmethod
    def of_blocks(cls, blocks: tuple[Block, ...], *, entry: int, name: str, when: datetime,
                  target: Target = Target.FLASH, progid: int | None = None) -> TransferPlan:
        """A plan from blocks already cut (an image cuts its words once)."""
        size = sum(len(b.words) for b in blocks)
        return cls(target, entry, blocks, progid_of_blocks(blocks) if progid is None
                   else progid, size, name, when)

    def begin(self) -> ProgramBegin:
        return ProgramBegin(self.target, len(self.blocks), self.entry)

    def meta(self) -> list[ProgramMeta]:
        return meta_frames(self.progid, self.size_words, self.when, self.name)

    def erases(self) -> list[ProgramErase]:
        return erase_ranges(self.blocks) if self.target is Target.FLASH else []

    def prepare(self) -> ProgramPrepare:
        return ProgramPrepare(sum(e.count for e in self.erases()))

    def block_frames(self, indices: Iterable[int] | None = None) -> Iterator[
            ProgramBlock | ProgramData]:
        chosen = self.blocks if indices is None else (self.blocks[i] for i in indices)
        for b in chosen:
            yield b.header()
            yield from b.data_frames()
