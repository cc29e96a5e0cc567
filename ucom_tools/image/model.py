"""A firmware image for the DSP56F803, whatever file it came from.

:class:`Image` is what the readers of :mod:`ucom_tools.image.srec` (S-records) and
:mod:`ucom_tools.image.ihex` (Intel HEX) return: its words by memory space and address,
its entry, its descriptor; :func:`finish_image` holds the checks every format shares (words
to program, an entry in program flash, a descriptor that can be read), and
:func:`region_problem` says which words an image may hold.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime

from ucom_tools.errors import FrameError, ImageError
from ucom_tools.memory import RegionKind, kind_of
from ucom_tools.wire.codes import Space, Target
from ucom_tools.wire.descriptor import DESCRIPTOR_ADDRESS, ImageDescriptor
from ucom_tools.wire.transfer import (
    VECTOR_WORDS,
    Block,
    TransferPlan,
    make_blocks,
    progid_of_blocks,
)

X_OFFSET = 0x0020_0000
"""X: word a is at word address X_OFFSET + a (at byte address 2 * (X_OFFSET + a))."""
FORMAT_NAMES = {"srec": "S-record", "ihex": "Intel HEX"}


@dataclass(frozen=True)
class Segment:
    """A contiguous run of words in one memory space."""

    space: Space
    start: int
    length: int

    @property
    def end(self) -> int:
        return self.start + self.length - 1

    def __str__(self) -> str:
        return f"{self.space.name}:{self.start:04X}-{self.end:04X}"


@dataclass(frozen=True)
class Image:
    """A checked firmware image."""

    path: str
    header: str
    entry: int
    words: dict[tuple[Space, int], int] = field(repr=False)
    vector_words: dict[int, int]
    records: int
    addressing: str
    descriptor: ImageDescriptor | None = None
    """What the program was built for (P:7DE0); None = no descriptor (flagged)."""
    format: str = "srec"
    """The file's format: "srec" (S-records) or "ihex" (Intel HEX)."""

    @property
    def format_name(self) -> str:
        return FORMAT_NAMES[self.format]

    @property
    def name(self) -> str:
        return os.path.basename(self.path)

    def segments(self) -> list[Segment]:
        out: list[Segment] = []
        for space, addr in sorted(self.words):
            last = out[-1] if out else None
            if last and last.space is space and last.end + 1 == addr:
                out[-1] = Segment(space, last.start, last.length + 1)
            else:
                out.append(Segment(space, addr, 1))
        return out

    def size(self, space: Space | None = None) -> int:
        if space is None:
            return len(self.words)
        return sum(1 for s, _ in self.words if s is space)

    def plan(self, *, target: Target = Target.FLASH, when: datetime | None = None,
             when_epoch: float | None = None) -> TransferPlan:
        """The transfer of this image (blocks, ProgID, frames)."""
        if when is None:
            when = (datetime.fromtimestamp(when_epoch, tz=UTC) if when_epoch is not None
                    else datetime.now(tz=UTC))
        return TransferPlan.of_blocks(self.blocks, entry=self.entry, name=self.name,
                                      when=when, target=target, progid=self.progid)

    @functools.cached_property
    def blocks(self) -> tuple[Block, ...]:
        """The image cut into transfer blocks (once: it takes every word)."""
        return tuple(make_blocks(self.words))

    @functools.cached_property
    def progid(self) -> int:
        """The image's ProgID (computed once: it needs every block)."""
        return progid_of_blocks(self.blocks)


def finish_image(source: str, *, header: str, entry: int, entry_line: int | None,
                 words: dict[tuple[Space, int], int], vectors: dict[int, int], records: int,
                 addressing: str, line_of: Callable[[tuple[Space, int]], int | None],
                 format: str = "srec") -> Image:
    """The checks on an image as a whole, for every format: words to program, an entry in
    program flash, a descriptor that can be read.  ``line_of`` gives a word's line."""
    if not words:
        raise ImageError("empty image: no data words to program" + (
            " (only reset-vector words, which the bootloader keeps)" if vectors else ""),
            file=source)
    if not (0x0004 <= entry <= 0x7DFF):
        raise ImageError(f"entry address P:{entry:04X} is not in program flash "
                         "(P:0004-7DFF)", file=source, line=entry_line)
    try:
        descriptor = ImageDescriptor.from_image(words)
    except FrameError as err:
        raise ImageError(f"image descriptor at P:{DESCRIPTOR_ADDRESS:04X}: {err.message}",
                         file=source, line=line_of((Space.P, DESCRIPTOR_ADDRESS))) from None
    return Image(source, header, entry, words, vectors, records, addressing, descriptor,
                 format)


def region_problem(space: Space, addr: int) -> str | None:
    """Why word ``space:addr`` cannot be in an image, or None: it may (program flash,
    data flash, or one of the reset-vector words P:0000-0003, which are kept aside)."""
    if space is Space.P and addr in VECTOR_WORDS:
        return None
    kind = kind_of(space, addr)
    if kind in (RegionKind.PROGRAM_FLASH, RegionKind.DATA_FLASH):
        return None
    return (f"word {space.name}:{addr:04X} lies in {kind.value}; only program flash "
            "P:0004-7DFF and data flash X:1000-1EFF can be programmed")


def runs(words: dict[tuple[Space, int], int]) -> list[tuple[Space, int, list[int]]]:
    """The words as runs of consecutive addresses, P: before X:, each (space, first
    address, values)."""
    out: list[tuple[Space, int, list[int]]] = []
    for space, addr in sorted(words):  # Space.P < Space.X
        last = out[-1] if out else None
        if last and last[0] is space and last[1] + len(last[2]) == addr:
            last[2].append(words[(space, addr)])
        else:
            out.append((space, addr, [words[(space, addr)]]))
    return out
