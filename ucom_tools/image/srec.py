"""Read S-record images in the CodeWarrior 56800 convention, and check them completely.

CodeWarrior writes an S0 header ("PROGRAM&DATA"), S3 data records and an S7 entry record.
Record addresses are WORD addresses; P: and X: share the file, X: at 0x00200000 + word
address; each 16-bit word is stored low byte first (bytes ``84 E9`` = word 0xE984).
Plain files with S1/S2 records and S5/S6 count records are read the same way; files
whose addresses count bytes (``addressing="byte"``, or detected by ``"auto"``) have
their addresses halved.

Records are parsed with bincopy (syntax, lengths, checksums); everything that can make a
programming fail is checked here, so that nothing reaches the bus from a bad file.
"""

from __future__ import annotations

import itertools
import os
import re
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import bincopy

from ucom_tools.errors import FrameError, ImageError
from ucom_tools.memory import Kind, kind_of
from ucom_tools.wire.codes import Space, Target
from ucom_tools.wire.descriptor import DESCRIPTOR_ADDRESS, ImageDescriptor
from ucom_tools.wire.transfer import VECTOR_WORDS, TransferPlan

X_OFFSET = 0x0020_0000
MAX_FILE_BYTES = 16 * 1024 * 1024


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
        return TransferPlan.build(self.words, entry=self.entry, name=self.name, when=when,
                                  target=target)

    @property
    def progid(self) -> int:
        return self.plan(when_epoch=0).progid


def load_image(path: str | Path, *, addressing: str = "auto") -> Image:
    """Read and check an S-record file; raises :class:`ImageError` naming file and line."""
    p = Path(path)
    try:
        if p.stat().st_size > MAX_FILE_BYTES:
            raise ImageError(f"file is larger than {MAX_FILE_BYTES // 2**20} MiB; not an "
                             "S-record image for a DSP56F803", file=str(path))
        raw = p.read_bytes()
    except FileNotFoundError:
        raise ImageError("no such file", file=str(path)) from None
    except IsADirectoryError:
        raise ImageError("is a directory, not an S-record file", file=str(path)) from None
    except OSError as err:
        raise ImageError(f"cannot read: {err.strerror}", file=str(path)) from None
    try:
        text = raw.decode("ascii")
    except UnicodeDecodeError as err:
        line = raw[:err.start].count(b"\n") + 1
        raise ImageError("not an S-record file: non-ASCII byte", file=str(path),
                         line=line) from None
    return parse_image(text, str(path), addressing=addressing)


@dataclass
class _Record:
    line: int
    type: str
    address: int
    data: bytes


def _records(text: str, source: str) -> list[_Record]:
    out = []
    for no, raw in enumerate(text.splitlines(), 1):
        rec = raw.strip()
        if not rec:
            continue
        if not rec.startswith("S") or len(rec) < 2:
            raise ImageError(f"not an S-record: {_clip(rec)}", file=source, line=no)
        if rec[1] not in "01235789":
            raise ImageError(f"unknown record type S{rec[1]}", file=source, line=no)
        try:
            type_, address, size, data = bincopy.unpack_srec(rec)
        except bincopy.Error as err:
            raise ImageError(_bincopy_reason(str(err)), file=source, line=no) from None
        except (ValueError, IndexError):
            raise ImageError("malformed record: bad hex digits or length", file=source,
                             line=no) from None
        if len(data) != size:
            raise ImageError(f"record length says {size} data bytes, found {len(data)}",
                             file=source, line=no)
        out.append(_Record(no, type_, address, bytes(data)))
    return out


def _bincopy_reason(msg: str) -> str:
    crc = re.search(r"expected crc '([0-9A-Fa-f]+)'.*but got '([0-9A-Fa-f]+)'", msg)
    if crc:
        return (f"checksum mismatch: the record ends in {crc.group(2).upper()}, its bytes "
                f"give {crc.group(1).upper()}")
    return "malformed record: " + msg


def _clip(s: str) -> str:
    return s if len(s) <= 40 else s[:37] + "..."


def _detect_addressing(records: list[_Record]) -> str:
    word = byte = 0
    data = [r for r in records if r.type in "123"]
    for a, b in itertools.pairwise(data):
        if b.address == a.address + len(a.data) // 2:
            word += 1
        elif b.address == a.address + len(a.data):
            byte += 1
    return "byte" if byte > word else "word"


def parse_image(text: str, source: str = "<image>", *, addressing: str = "auto") -> Image:
    """Check S-record text and return the image it describes."""
    if addressing not in ("auto", "word", "byte"):
        raise ImageError(f"addressing must be auto, word or byte, not {addressing!r}",
                         file=source)
    records = _records(text, source)
    if not records:
        raise ImageError("empty file: no S-records", file=source)
    mode = _detect_addressing(records) if addressing == "auto" else addressing
    header = ""
    entry: int | None = None
    end_line = 0
    data_records = 0
    words: dict[tuple[Space, int], int] = {}
    lines: dict[tuple[Space, int], int] = {}
    vectors: dict[int, int] = {}
    for r in records:
        if end_line:
            raise ImageError(f"record after the termination record of line {end_line}",
                             file=source, line=r.line)
        if r.type == "0":
            header = r.data.rstrip(b"\0").decode("latin-1")
        elif r.type in "123":
            data_records += 1
            _add_words(r, mode, source, words, lines, vectors)
        elif r.type in "56":
            if r.address != data_records:
                raise ImageError(f"count record says {r.address} data records, the file has "
                                 f"{data_records} before it", file=source, line=r.line)
        else:
            entry = r.address // 2 if mode == "byte" else r.address
            end_line = r.line
    if not words:
        raise ImageError("empty image: no data words to program" + (
            " (only reset-vector words, which the bootloader keeps)" if vectors else ""),
            file=source)
    if entry is None:
        entry = min(a for s, a in words if s is Space.P) if any(
            s is Space.P for s, _ in words) else 0
    elif not (0x0004 <= entry <= 0x7DFF):
        raise ImageError(f"entry address P:{entry:04X} is not in program flash "
                         "(P:0004-7DFF)", file=source, line=end_line)
    try:
        descriptor = ImageDescriptor.from_image(words)
    except FrameError as err:
        raise ImageError(f"image descriptor at P:{DESCRIPTOR_ADDRESS:04X}: {err.message}",
                         file=source, line=lines.get((Space.P, DESCRIPTOR_ADDRESS))) from None
    return Image(source, header, entry, words, vectors, len(records), mode, descriptor)


def _add_words(r: _Record, mode: str, source: str, words: dict[tuple[Space, int], int],
               lines: dict[tuple[Space, int], int], vectors: dict[int, int]) -> None:
    if len(r.data) % 2:
        raise ImageError(f"odd number of data bytes ({len(r.data)}): the DSP56F803 stores "
                         "16-bit words", file=source, line=r.line)
    address = r.address
    if mode == "byte":
        if address % 2:
            raise ImageError(f"odd byte address 0x{address:X} in a byte-addressed file",
                             file=source, line=r.line)
        address //= 2
    if address >= X_OFFSET:
        space, start = Space.X, address - X_OFFSET
    else:
        space, start = Space.P, address
    count = len(r.data) // 2
    if start + count - 1 > 0xFFFF:
        raise ImageError(f"address 0x{r.address:X} is outside the 16-bit {space.name}: "
                         "memory", file=source, line=r.line)
    data = r.data
    for i in range(count):
        addr = start + i
        value = data[2 * i] | (data[2 * i + 1] << 8)
        key = (space, addr)
        if key in lines or (space is Space.P and addr in vectors):
            first = lines.get(key) or "an earlier line"
            raise ImageError(f"word {space.name}:{addr:04X} is also written on line {first} "
                             "(overlapping data)", file=source, line=r.line)
        if space is Space.P and addr in VECTOR_WORDS:
            vectors[addr] = value
            continue
        kind = kind_of(space, addr)
        if kind not in (Kind.PROGRAM_FLASH, Kind.DATA_FLASH):
            raise ImageError(f"word {space.name}:{addr:04X} lies in {kind.value}; only "
                             "program flash P:0004-7DFF and data flash X:1000-1EFF can be "
                             "programmed", file=source, line=r.line)
        words[key] = value
        lines[key] = r.line
