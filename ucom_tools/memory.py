"""The DSP56F803 memory map as the UCoM uses it (16-bit word addresses).

Shared by the image checks on the host and the virtual board: one table says which
words an image may contain and which the bootloader refuses.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

from ucom_tools.wire.codes import Space


class RegionKind(Enum):
    """What a region of the memory map holds (its value: the words that say so)."""

    VECTORS = "reset/COP vectors (owned by the bootloader)"
    PROGRAM_FLASH = "program flash"
    PROGRAM_RAM = "program RAM"
    BOOT_FLASH = "boot flash (holds the bootloader)"
    DATA_RAM = "data RAM"
    PERIPHERALS = "peripheral registers"
    DATA_FLASH = "data flash"
    BOOT_RECORD = "bootloader record (last data-flash page)"
    EXTERNAL = "external memory"
    FPGA = "FPGA registers"
    UNMAPPED = "unmapped"


@dataclass(frozen=True, slots=True)
class Region:
    space: Space
    start: int
    end: int  # inclusive
    kind: RegionKind

    @property
    def programmable(self) -> bool:
        return self.kind in (RegionKind.PROGRAM_FLASH, RegionKind.DATA_FLASH)

    def __str__(self) -> str:
        return f"{self.space.name}:{self.start:04X}-{self.end:04X} {self.kind.value}"


REGIONS: tuple[Region, ...] = (
    Region(Space.P, 0x0000, 0x0003, RegionKind.VECTORS),
    Region(Space.P, 0x0004, 0x7DFF, RegionKind.PROGRAM_FLASH),
    Region(Space.P, 0x7E00, 0x7FFF, RegionKind.PROGRAM_RAM),
    Region(Space.P, 0x8000, 0x87FF, RegionKind.BOOT_FLASH),
    Region(Space.X, 0x0000, 0x07FF, RegionKind.DATA_RAM),
    Region(Space.X, 0x0C00, 0x0FFF, RegionKind.PERIPHERALS),
    Region(Space.X, 0x1000, 0x1EFF, RegionKind.DATA_FLASH),
    Region(Space.X, 0x1F00, 0x1FFF, RegionKind.BOOT_RECORD),
    Region(Space.X, 0x2000, 0x3FFF, RegionKind.EXTERNAL),
    Region(Space.X, 0x4000, 0x403F, RegionKind.FPGA),
    Region(Space.X, 0x4040, 0xFF7F, RegionKind.EXTERNAL),
)

P_FLASH_END = 0x7DFF
X_FLASH_START = 0x1000
X_FLASH_END = 0x1FFF
PAGE_WORDS = 256


def region_of(space: Space, address: int) -> Region | None:
    for r in REGIONS:
        if r.space is space and r.start <= address <= r.end:
            return r
    return None


def kind_of(space: Space, address: int) -> RegionKind:
    r = region_of(space, address)
    return r.kind if r else RegionKind.UNMAPPED


def is_fpga_address(address: int) -> bool:
    """B.1: the FPGA decodes every X: access whose upper 10 address bits are 0100000000."""
    return (address >> 6) == 0b0100000000


def first_unprogrammable(space: Space, start: int,
                         count: int) -> tuple[int, RegionKind] | None:
    """The first word of ``space:start`` .. ``start+count-1`` that may not be programmed."""
    addr = start
    end = start + count - 1
    while addr <= end:
        r = region_of(space, addr)
        if r is None or not r.programmable:
            return addr, (r.kind if r else RegionKind.UNMAPPED)
        addr = r.end + 1
    return None


PROTECTED_KINDS = frozenset({RegionKind.VECTORS, RegionKind.BOOT_FLASH,
                             RegionKind.BOOT_RECORD})


def page_refusal(space: Space, page: int) -> tuple[int, RegionKind] | None:
    """Why flash page ``page`` of ``space`` may not be erased (None if it may).

    P page 0 may be erased: the bootloader restores its reset vectors right after."""
    start = page * PAGE_WORDS
    if space is Space.P and page == 0:
        return first_unprogrammable(space, 4, PAGE_WORDS - 4)
    return first_unprogrammable(space, start, PAGE_WORDS)
