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
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import BinaryIO, TextIO

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
"""X: word a is at word address X_OFFSET + a (at byte address 2 * (X_OFFSET + a))."""
FORMAT_NAMES = {"srec": "S-record", "ihex": "Intel HEX"}
CODEWARRIOR_HEADER = "PROGRAM&DATA"
"""The S0 header CodeWarrior writes (and ucom writes where an image has none)."""
WORDS_PER_RECORD = 16
"""Words per S3 record that ucom writes, as tools/make_firmware_images.py does."""
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


def load_image(path: str | Path, *, addressing: str = "auto") -> Image:
    """Read and check an S-record file; raises :class:`ImageError` naming file and line.

    The file is read line by line and checked as it is read: reading stops at the first
    bad line, or once more than :data:`MAX_FILE_BYTES` have come (devices, FIFOs)."""
    _check_addressing(addressing, str(path))
    return load_stream(open_image(path, "an S-record file"), str(path), addressing=addressing)


def load_stream(binary: BinaryIO, source: str, *, addressing: str = "auto") -> Image:
    """Read and check the S-record file open as ``binary`` (closed afterwards)."""
    def read(stream: TextIO, too_big: bool) -> Image:
        _check_addressing(addressing, source)
        return _image(_records(_lines(stream, source, too_big=too_big), source), source,
                      addressing)

    return read_stream(binary, source, read)


def open_image(path: str | Path, what: str) -> BinaryIO:
    """Image file ``path`` opened for reading (a regular file, :func:`fileio.open_input`);
    :class:`ImageError` naming it when it cannot be.  The size cap is applied as it is
    read (:func:`read_stream`), so that a huge file that is no image is named as such."""
    source = str(path)

    def refuse(text: str) -> ImageError:
        return ImageError(text, file=source)

    return fileio.open_input(path, limit=1 << 62, what=what, error=refuse)


def read_stream(binary: BinaryIO, source: str,
                reader: Callable[[TextIO, bool], Image]) -> Image:
    """``reader(text stream, too_big)`` applied to ``binary`` (one character per byte),
    which is closed afterwards; a failing read is :class:`ImageError`."""
    try:
        st = os.fstat(binary.fileno())
        too_big = st.st_size > MAX_FILE_BYTES  # a regular file (open_image)
        with io.TextIOWrapper(binary, encoding="latin-1", newline="") as stream:  # byte = char
            return reader(stream, too_big)
    except OSError as err:
        raise ImageError(f"cannot read: {fileio.reason(err)}", file=source) from None
    finally:
        binary.close()


def parse_image(text: str, source: str = "<image>", *, addressing: str = "auto") -> Image:
    """Check S-record text and return the image it describes (the checks of load_image)."""
    _check_addressing(addressing, source)
    records = _records(_lines(io.StringIO(text, newline=""), source), source)
    return _image(records, source, addressing)


def _check_addressing(addressing: str, source: str) -> None:
    if addressing not in ("auto", "word", "byte"):
        raise ImageError(f"addressing must be auto, word or byte, not {addressing!r}",
                         file=source)


def _lines(stream: TextIO, source: str, *, too_big: bool = False, kind: str = "S-record",
           record: str = "S-record", max_record: int = MAX_RECORD_CHARS,
           max_line: int = MAX_LINE_CHARS) -> Iterator[tuple[int, str]]:
    """The numbered lines of ``stream``, without line ends (LF, CR LF or CR), each checked
    to be printable ASCII and at most ``max_line`` long; the whole stream at most
    MAX_FILE_BYTES, counted while reading since devices and FIFOs report no size.

    ``too_big``: the file's size is known to exceed the limit; it is refused after its
    first line, so that a file that is no image file at all is named as such.  ``kind``
    and ``record`` name the format in messages ("Intel HEX", "Intel HEX record")."""
    total = 0
    for no in itertools.count(1):
        line = stream.readline(max_line + 3)  # a whole line with CR LF, or one more
        if not line:
            return
        total += len(line)
        if total > MAX_FILE_BYTES:
            raise ImageError(f"file is larger than {_amount(MAX_FILE_BYTES)}; not an "
                             f"{kind} image for a DSP56F803", file=source, line=no)
        body = line.rstrip("\r\n")
        bad = _NOT_TEXT.search(body)
        if bad:
            raise ImageError(f"not an {kind} file: {_describe(bad.group())}", file=source,
                             line=no, column=bad.start() + 1)
        if len(body) > max_line:
            raise ImageError(f"not an {record}: the line is longer than {max_line} "
                             f"characters (a record has at most {max_record})",
                             file=source, line=no)
        yield no, body
        if too_big:
            raise ImageError(f"file is larger than {_amount(MAX_FILE_BYTES)}; not an "
                             f"{kind} image for a DSP56F803", file=source)


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
    import bincopy  # here, not on top: with pyelftools it is a third of a command's start-up

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
    return finish_image(source, header=header, entry=entry, entry_line=end_line, words=words,
                        vectors=vectors, records=len(records), addressing=mode,
                        line_of=lines.get)


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
    if kind in (Kind.PROGRAM_FLASH, Kind.DATA_FLASH):
        return None
    return (f"word {space.name}:{addr:04X} lies in {kind.value}; only program flash "
            "P:0004-7DFF and data flash X:1000-1EFF can be programmed")


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
        problem = region_problem(space, addr)
        if problem:
            raise ImageError(problem, file=source, line=r.line)
        if space is Space.P and addr in VECTOR_WORDS:
            vectors[addr] = value
            continue
        words[key] = value
        lines[key] = r.line


def dumps(img: Image) -> str:
    """``img`` as S-record text in the CodeWarrior 56800 convention, which ucom and
    CodeWarrior read: an S0 header (the image's, else "PROGRAM&DATA"), S3 records of
    :data:`WORDS_PER_RECORD` words at WORD addresses (X: at 0x00200000 + address), each
    word low byte first, the reset-vector words included, and an S7 entry record."""
    import bincopy

    lines = [bincopy.pack_srec("0", 0, len(header), header)
             for header in [(img.header or CODEWARRIOR_HEADER).encode("latin-1")]]
    every = dict(img.words)
    every.update({(Space.P, a): v for a, v in img.vector_words.items()})
    for space, start, values in runs(every):
        base = X_OFFSET if space is Space.X else 0
        for i in range(0, len(values), WORDS_PER_RECORD):
            chunk = values[i:i + WORDS_PER_RECORD]
            data = b"".join(w.to_bytes(2, "little") for w in chunk)
            lines.append(bincopy.pack_srec("3", base + start + i, len(data), data))
    lines.append(bincopy.pack_srec("7", img.entry, 0, None))
    return "\n".join(lines) + "\n"


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
