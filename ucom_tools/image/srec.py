"""Read S-record images in the CodeWarrior 56800 convention, and check them completely.

CodeWarrior writes an S0 header ("PROGRAM&DATA"), S3 data records and an S7 entry record.
Record addresses are WORD addresses; P: and X: share the file, X: at 0x00200000 + word
address; each 16-bit word is stored low byte first (bytes ``84 E9`` = word 0xE984).
Plain files with S1/S2 records and S5/S6 count records are read the same way; files
whose addresses count bytes (``addressing="byte"``, or detected by ``"auto"``) have
their addresses halved.

Files are read as a stream, line by line, each line at most :data:`MAX_LINE_CHARS` long and
the whole at most :data:`MAX_FILE_BYTES`, so that a device, a FIFO or a huge file that is
no S-record file is rejected at its first bad line without reading the rest.  Each record's
structure is checked here (type, hex digits, the length byte against what the line holds:
a record cut short names where it ends), its checksum by bincopy; a termination record
(S7, S8 or S9) must end the file, so a truncated file is never taken for a short image.
Everything else that can make a programming fail is checked too, so that nothing reaches
the bus from a bad file.
"""

from __future__ import annotations

import functools
import io
import itertools
import os
import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import TextIO

import bincopy

from ucom_tools import fileio
from ucom_tools.errors import FrameError, ImageError
from ucom_tools.memory import Kind, kind_of
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
MAX_FILE_BYTES = 16 * 1024 * 1024
"""Largest file accepted (line ends included), counted while reading."""
MAX_RECORD_CHARS = 2 + 2 * (1 + 255)
"""Longest S-record: ``S``, the type, then the length byte and up to 255 bytes in hex."""
MAX_LINE_CHARS = MAX_RECORD_CHARS + 64
"""Longest line accepted (without its line end): a record and some blanks around it."""

_ADDRESS_BYTES = {"0": 2, "1": 2, "2": 3, "3": 4, "5": 2, "6": 3, "7": 4, "8": 3, "9": 2}
_TERMINATION = "789"
_NOT_TEXT = re.compile(r"[^\t\x20-\x7e]")
_NOT_HEX = re.compile(r"[^0-9A-Fa-f]")


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


def load_image(path: str | Path, *, addressing: str = "auto") -> Image:
    """Read and check an S-record file; raises :class:`ImageError` naming file and line.

    The file is read line by line and checked as it is read: reading stops at the first
    bad line, or once more than :data:`MAX_FILE_BYTES` have come (devices, FIFOs)."""
    source = str(path)
    _check_addressing(addressing, source)
    def refuse(text: str) -> ImageError:
        return ImageError(text, file=source)

    binary = fileio.open_input(path, limit=1 << 62, what="an S-record file", error=refuse)
    try:
        st = os.fstat(binary.fileno())
        too_big = st.st_size > MAX_FILE_BYTES
        with io.TextIOWrapper(binary, encoding="latin-1", newline="") as stream:  # byte = char
            records = _records(_lines(stream, source, too_big=too_big), source)
    except OSError as err:
        raise ImageError(f"cannot read: {fileio.reason(err)}", file=source) from None
    finally:
        binary.close()
    return _image(records, source, addressing)


def parse_image(text: str, source: str = "<image>", *, addressing: str = "auto") -> Image:
    """Check S-record text and return the image it describes (the checks of load_image)."""
    _check_addressing(addressing, source)
    records = _records(_lines(io.StringIO(text, newline=""), source), source)
    return _image(records, source, addressing)


def _check_addressing(addressing: str, source: str) -> None:
    if addressing not in ("auto", "word", "byte"):
        raise ImageError(f"addressing must be auto, word or byte, not {addressing!r}",
                         file=source)


def _lines(stream: TextIO, source: str, *, too_big: bool = False) -> Iterator[tuple[int, str]]:
    """The numbered lines of ``stream``, without line ends (LF, CR LF or CR), each checked
    to be printable ASCII and at most MAX_LINE_CHARS long; the whole stream at most
    MAX_FILE_BYTES, counted while reading since devices and FIFOs report no size.

    ``too_big``: the file's size is known to exceed the limit; it is refused after its
    first line, so that a file that is no S-record file at all is named as such."""
    total = 0
    for no in itertools.count(1):
        line = stream.readline(MAX_LINE_CHARS + 3)  # a whole line with CR LF, or one more
        if not line:
            return
        total += len(line)
        if total > MAX_FILE_BYTES:
            raise ImageError(f"file is larger than {_amount(MAX_FILE_BYTES)}; not an "
                             "S-record image for a DSP56F803", file=source, line=no)
        body = line.rstrip("\r\n")
        bad = _NOT_TEXT.search(body)
        if bad:
            raise ImageError(f"not an S-record file: {_describe(bad.group())}", file=source,
                             line=no, column=bad.start() + 1)
        if len(body) > MAX_LINE_CHARS:
            raise ImageError(f"not an S-record: the line is longer than {MAX_LINE_CHARS} "
                             f"characters (a record has at most {MAX_RECORD_CHARS})",
                             file=source, line=no)
        yield no, body
        if too_big:
            raise ImageError(f"file is larger than {_amount(MAX_FILE_BYTES)}; not an "
                             "S-record image for a DSP56F803", file=source)


def _amount(size: int) -> str:
    return f"{size // 2**20} MiB" if size % 2**20 == 0 else f"{size} bytes"


def _describe(char: str) -> str:
    code = ord(char)
    if code == 0:
        return "NUL byte (binary data)"
    if code > 0xFF:
        return f"non-ASCII character U+{code:04X}"
    if code > 0x7F:
        return f"non-ASCII byte 0x{code:02X}"
    return f"control character 0x{code:02X}"


@dataclass
class _Record:
    line: int
    type: str
    address: int
    data: bytes


def _records(lines: Iterable[tuple[int, str]], source: str) -> list[_Record]:
    out = []
    for no, raw in lines:
        rec = raw.strip(" \t")
        if rec:
            indent = len(raw) - len(raw.lstrip(" \t"))
            out.append(_record(rec, source, no, indent))
    return out


def _record(rec: str, source: str, no: int, indent: int) -> _Record:
    """One record, its structure checked before bincopy unpacks it and checks its sum."""
    if not rec.startswith("S") or len(rec) < 2 or not rec[1].isdigit():
        raise ImageError(f"not an S-record: {_clip(rec)}", file=source, line=no)
    type_ = rec[1]
    if type_ not in _ADDRESS_BYTES:
        raise ImageError(f"unknown record type S{type_}", file=source, line=no)
    digits = rec[2:]
    bad = _NOT_HEX.search(digits)
    if bad:
        raise ImageError(f"malformed record: {bad.group()!r} is not a hex digit", file=source,
                         line=no, column=indent + 3 + bad.start())
    if len(digits) < 2:
        where = "inside" if digits else "before"
        raise ImageError(f"record cut short: the S{type_} record ends {where} its length byte",
                         file=source, line=no)
    length = int(digits[:2], 16)
    width = _ADDRESS_BYTES[type_]
    if length < width + 1:
        raise ImageError(f"malformed record: length byte {length:02X} is too small for an "
                         f"S{type_} record, whose {width} address bytes and checksum need "
                         f"{width + 1}", file=source, line=no)
    held = len(digits) - 2  # hex digits after the length byte
    n_data = length - width - 1
    promise = (f"its length byte {digits[:2]} promises {length} bytes ({width} address, "
               + (f"{n_data} data, " if n_data else "")
               + f"1 checksum), {2 * length} hex digits")
    if held < 2 * length:
        where = ("inside the address" if held < 2 * width else
                 "inside the data" if held < 2 * (length - 1) else
                 "before the checksum" if held == 2 * (length - 1) else
                 "inside the checksum")
        raise ImageError(f"record cut short: {promise}, the line has only {held}; it "
                         f"ends {where}", file=source, line=no)
    if held > 2 * length:
        raise ImageError(f"malformed record: {promise}, the line has {held}", file=source,
                         line=no)
    try:  # bincopy knows no S6; S2 has the same 24-bit address, the type is not summed
        _, address, _, data = bincopy.unpack_srec("S2" + digits if type_ == "6" else rec)
    except bincopy.Error as err:
        raise ImageError(_bincopy_reason(str(err)), file=source, line=no) from None
    except (ValueError, IndexError):
        raise ImageError("malformed record: bad hex digits or length", file=source,
                         line=no) from None
    return _Record(no, type_, address, bytes(data))


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


def _image(records: list[_Record], source: str, addressing: str) -> Image:
    """The image the records describe, checked as a whole."""
    if not records:
        raise ImageError("empty file: no S-records", file=source)
    if not any(r.type in _TERMINATION for r in records):
        last = records[-1].line
        raise ImageError(f"no termination record (S7, S8 or S9): the file ends after line "
                         f"{last}; is it truncated?", file=source, line=last)
    mode = _detect_addressing(records) if addressing == "auto" else addressing
    header = ""
    entry = 0
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
    if not (0x0004 <= entry <= 0x7DFF):
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
