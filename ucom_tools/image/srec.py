"""Read S-record images in the CodeWarrior 56800 convention, and check them completely.

CodeWarrior writes an S0 header ("PROGRAM&DATA"), S3 data records and an S7 entry record.
Record addresses are WORD addresses; P: and X: share the file, X: at 0x00200000 + word
address; each 16-bit word is stored low byte first (bytes ``84 E9`` = word 0xE984).
Plain files with S1/S2 records and S5/S6 count records are read the same way; files
whose addresses count bytes (``addressing="byte"``, or detected by ``"auto"``) have
their addresses halved.

Files are read as a stream, line by line (:mod:`ucom_tools.image.text`), each line at
most :data:`MAX_LINE_CHARS` long and the whole at most 16 MiB, so that a device, a FIFO or
a huge file that is no S-record file is rejected at its first bad line without reading
the rest.  Each record's
structure is checked here (type, hex digits, the length byte against what the line holds:
a record cut short names where it ends), its checksum by bincopy; a termination record
(S7, S8 or S9) must end the file, so a truncated file is never taken for a short image.
Everything else that can make a programming fail is checked too, so that nothing reaches
the bus from a bad file.
"""

from __future__ import annotations

import io
import itertools
import re
from collections.abc import Iterable
from dataclasses import dataclass
from typing import BinaryIO, TextIO

from ucom_tools.errors import ImageError
from ucom_tools.image import text
from ucom_tools.image.model import X_OFFSET, Image, finish_image, region_problem, runs
from ucom_tools.wire.codes import Space
from ucom_tools.wire.transfer import VECTOR_WORDS

CODEWARRIOR_HEADER = "PROGRAM&DATA"
"""The S0 header CodeWarrior writes (and ucom writes where an image has none)."""
WORDS_PER_RECORD = 16
"""Words per S3 record that ucom writes, as tools/make_firmware_images.py does."""
MAX_RECORD_CHARS = 2 + 2 * (1 + 255)
"""Longest S-record: ``S``, the type, then the length byte and up to 255 bytes in hex."""
MAX_LINE_CHARS = MAX_RECORD_CHARS + 64
"""Longest line accepted (without its line end): a record and some blanks around it."""

_ADDRESS_BYTES = {"0": 2, "1": 2, "2": 3, "3": 4, "5": 2, "6": 3, "7": 4, "8": 3, "9": 2}
_TERMINATION = "789"


def load_stream(binary: BinaryIO, source: str, *, addressing: str = "auto") -> Image:
    """Read and check the S-record file open as ``binary`` (closed afterwards)."""
    def read(stream: TextIO, too_big: bool) -> Image:
        check_addressing(addressing, source)
        return _image(_records(_lines(stream, source, too_big), source), source,
                      addressing)

    return text.read_stream(binary, source, read)


def parse_srec(source_text: str, source: str = "<image>", *, addressing: str = "auto"
               ) -> Image:
    """Check S-record text and return the image it describes (the checks of
    :func:`~ucom_tools.image.formats.load_image`)."""
    check_addressing(addressing, source)
    records = _records(_lines(io.StringIO(source_text, newline=""), source), source)
    return _image(records, source, addressing)


def _lines(stream: TextIO, source: str, too_big: bool = False) -> Iterable[tuple[int, str]]:
    return text.numbered_lines(stream, source, too_big=too_big, kind="S-record",
                               record="S-record", max_record=MAX_RECORD_CHARS,
                               max_line=MAX_LINE_CHARS)


def check_addressing(addressing: str, source: str) -> None:
    if addressing not in ("auto", "word", "byte"):
        raise ImageError(f"addressing must be auto, word or byte, not {addressing!r}",
                         file=source)


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
        raise ImageError(f"not an S-record: {text.clip(rec)}", file=source, line=no)
    type_ = rec[1]
    if type_ not in _ADDRESS_BYTES:
        raise ImageError(f"unknown record type S{type_}", file=source, line=no)
    digits = rec[2:]
    bad = text.NOT_HEX.search(digits)
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
