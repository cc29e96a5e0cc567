"""The Info record (function 5): what a board reports about itself and its program.

Sent as 8 Info frames, index 0-7, each with 7 body bytes (``man/ucom-protocol.7``).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from datetime import UTC, datetime

from ucom_tools.errors import FrameError
from ucom_tools.wire.codes import NAME_LENGTH, BoardState, Target
from ucom_tools.wire.descriptor import ImageDescriptor
from ucom_tools.wire.fpga import FpgaVersion
from ucom_tools.wire.messages import InfoFrame

INFO_FRAMES = 10

_F0 = struct.Struct(">BBBBBBx")
_F1 = struct.Struct(">I3s")
_F2 = struct.Struct(">HBBBBB")
_F3 = struct.Struct(">IHB")
_F8 = struct.Struct(">HHBBx")
_F9 = struct.Struct(">BBBBBBB")

FLAG_AUTOSTART = 0x01
FLAG_PROG_ENABLE = 0x02
FLAG_FLASH_VALID = 0x04
FLAG_EXTRAM_VALID = 0x08
FLAG_INIT_DONE = 0x10
FPGA_NEUTRAL = 0x01
DESC_PRESENT = 0x01
DESC_CORRUPT = 0x02


@dataclass(frozen=True, slots=True)
class BoardInfo:
    """Everything a board tells in one Info record."""

    state: BoardState
    autostart: bool
    prog_enable: bool
    flash_valid: bool
    extram_valid: bool
    seq_id: int
    fixed_id: int
    bootloader_version: tuple[int, int]
    progid: int
    size_words: int
    programmed: datetime | None
    serial: int
    entry: int
    target: Target
    name: str
    fpga_register1: int = 0
    fpga_register2: int = 0
    measured_board_id: int = 15
    fpga_neutral: bool = False
    descriptor: ImageDescriptor | None = None
    """What the program was built for (name not transferred: empty)."""
    descriptor_corrupt: bool = False

    @property
    def fpga(self) -> FpgaVersion | None:
        """The FPGA's identity, None when the registers do not decode (bit 4 set)."""
        try:
            return FpgaVersion.decode(self.fpga_register1, self.fpga_register2)
        except FrameError:
            return None

    @property
    def init_done(self) -> bool:
        return self.seq_id != 0

    def to_frames(self) -> list[InfoFrame]:
        flags = ((FLAG_AUTOSTART if self.autostart else 0)
                 | (FLAG_PROG_ENABLE if self.prog_enable else 0)
                 | (FLAG_FLASH_VALID if self.flash_valid else 0)
                 | (FLAG_EXTRAM_VALID if self.extram_valid else 0)
                 | (FLAG_INIT_DONE if self.seq_id else 0))
        d = self.programmed
        date = (d.year, d.month, d.day, d.hour, d.minute, d.second) if d else (0,) * 6
        name = self.name.encode("latin-1", "replace")[:NAME_LENGTH].ljust(NAME_LENGTH, b"\0")
        bodies = [
            _F0.pack(self.state, flags, self.seq_id, self.fixed_id, *self.bootloader_version),
            _F1.pack(self.progid, self.size_words.to_bytes(3, "big")),
            _F2.pack(*date),
            _F3.pack(self.serial, self.entry, self.target),
        ] + [name[i:i + 7] for i in range(0, NAME_LENGTH, 7)]
        desc = self.descriptor
        bodies.append(_F8.pack(self.fpga_register1, self.fpga_register2,
                               self.measured_board_id, FPGA_NEUTRAL if self.fpga_neutral else 0))
        bodies.append(_F9.pack(
            (DESC_PRESENT if desc else 0) | (DESC_CORRUPT if self.descriptor_corrupt else 0),
            *((desc.board_id, desc.app_id, desc.fpga_major, desc.fpga_minor, *desc.version)
              if desc else (0,) * 6)))
        return [InfoFrame(i, b) for i, b in enumerate(bodies)]

    @classmethod
    def from_frames(cls, frames: dict[int, bytes]) -> BoardInfo:
        """Assemble from Info bodies keyed by index; all 8 must be present."""
        missing = [i for i in range(INFO_FRAMES) if i not in frames]
        if missing:
            raise FrameError("Info index", f"frames {missing} missing")
        state, flags, sid, fid, blmaj, blmin = _F0.unpack(frames[0])
        progid, size = _F1.unpack(frames[1])
        year, mon, day, hour, minute, sec = _F2.unpack(frames[2])
        serial, entry, target = _F3.unpack(frames[3])
        name = b"".join(frames[i] for i in range(4, 8)).rstrip(b"\0").decode("latin-1")
        reg1, reg2, measured, fpga_flags = _F8.unpack(frames[8])
        dflags, *dvalues = _F9.unpack(frames[9])
        descriptor = None
        if dflags & DESC_PRESENT:
            b, a, fmaj, fmin, vmaj, vmin = dvalues
            try:
                descriptor = ImageDescriptor(b, a, fmaj, fmin, (vmaj, vmin), "")
            except FrameError as err:
                raise FrameError("Info descriptor", str(err)) from err
        try:
            programmed = (datetime(year, mon, day, hour, minute, sec, tzinfo=UTC)
                          if year else None)
        except ValueError as err:
            raise FrameError("Info date", str(err)) from err
        try:
            st, tgt = BoardState(state), Target(target)
        except ValueError as err:
            raise FrameError("Info state/target", str(err)) from err
        return cls(st, bool(flags & FLAG_AUTOSTART), bool(flags & FLAG_PROG_ENABLE),
                   bool(flags & FLAG_FLASH_VALID), bool(flags & FLAG_EXTRAM_VALID), sid, fid,
                   (blmaj, blmin), progid, int.from_bytes(size, "big"), programmed, serial,
                   entry, tgt, name, reg1, reg2, measured, bool(fpga_flags & FPGA_NEUTRAL),
                   descriptor, bool(dflags & DESC_CORRUPT))
