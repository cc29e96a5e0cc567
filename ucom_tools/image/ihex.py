"""Read and write Intel HEX images for the DSP56F803, checked as strictly as S-records.

Intel HEX counts bytes, so its addresses are byte addresses, as in the byte-addressed
S-records :mod:`ucom_tools.image.srec` reads: the word at P:a is the bytes at 2a and 2a+1
(low byte first), the word at X:a the bytes at 0x00400000 + 2a (2 x X_OFFSET), and the
start address record (type 05, or 03 as CS:IP) holds 2 x the entry.  A word's two bytes
may come from different records, but both must be there.

The file is read as S-record files are (a regular file, at most 16 MiB, line by line,
printable ASCII) and every record is checked here before the ``intelhex`` package
decodes it: the ':', hex digits, the length byte against what the line holds, the record
type (00-05), the checksum, the form of the address and start records, and that its
bytes lie in programmable memory; ``intelhex`` then refuses bytes written twice.  An
end-of-file record (01) is required, so a truncated file is never taken for a short
image (``intelhex`` itself takes a file without one, and an empty file), and nothing but
blank lines may follow it.  Each error is :class:`ImageError` naming file and line.
"""

from __future__ import annotations

import bisect
import io
from collections.abc import Iterator
from dataclasses import dataclass
from typing import BinaryIO, TextIO

import intelhex

from ucom_tools.errors import ImageError
from ucom_tools.image import text
from ucom_tools.image.model import X_OFFSET, Image, finish_image, region_problem
from ucom_tools.memory import region_of
from ucom_tools.wire.codes import Space
from ucom_tools.wire.transfer import VECTOR_WORDS

SUFFIXES = (".hex", ".ihex", ".ihx")
"""File names read as Intel HEX whatever they hold (see
:func:`ucom_tools.image.formats.load_image`)."""
X_BYTES = 2 * X_OFFSET
"""Byte address of X:0000."""
MAX_RECORD_CHARS = 1 + 2 * (5 + 255)
"""Longest record: ':', then length, two address bytes, type, 255 data bytes, checksum."""
MAX_LINE_CHARS = MAX_RECORD_CHARS + 64
"""Longest line accepted (without its line end): a record and some blanks around it."""
BYTES_PER_RECORD = 16
"""Data bytes per record that ucom writes (as objcopy and most toolchains do)."""

_TYPES = {0: "data", 1: "end-of-file", 2: "extended segment address",
          3: "start segment address", 4: "extended linear address",
          5: "start linear address"}
_KIND = "Intel HEX"
_RECORD = "Intel HEX record"


@dataclass(frozen=True)
class _Data:
    """Where a data record's bytes went: for errors that name the line of a byte."""

    line: int
    start: int
    length: int


class _State:
    """What the pre-check knows while the records stream to ``intelhex``."""

    def __init__(self) -> None:
        self.offset = 0
        self.records = 0
        self.last_line = 0
        self.eof_line = 0
        self.start_line = 0
        self.data: list[_Data] = []

    def line_of(self, address: int) -> int | None:
        """The line of the data record that holds byte ``address`` (the first one)."""
        for d in self.data:
            if d.start <= address < d.start + d.length:
                return d.line
        return None


def load_stream(binary: BinaryIO, source: str) -> Image:
    """Read and check the Intel HEX file open as ``binary`` (closed afterwards)."""
    return text.read_stream(binary, source,
                            lambda stream, too_big: _read(stream, source, too_big))


def parse_ihex(text: str, source: str = "<image>") -> Image:
    """Check Intel HEX text and return the image it describes (the checks of
    :func:`~ucom_tools.image.formats.load_image`)."""
    return _read(io.StringIO(text, newline=""), source, False)


class _Feed:
    """The checked records, line by line, as the file object ``IntelHex.loadhex`` reads
    (it iterates; its ``read`` is only looked for)."""

    def __init__(self, lines: Iterator[str]) -> None:
        self._lines = lines

    def read(self) -> str:  # pragma: no cover - loadhex only checks it exists
        raise NotImplementedError

    def __iter__(self) -> Iterator[str]:
        return self._lines


def _read(stream: TextIO, source: str, too_big: bool) -> Image:
    state = _State()
    lines = text.numbered_lines(stream, source, too_big=too_big, kind=_KIND, record=_RECORD,
                                max_record=MAX_RECORD_CHARS, max_line=MAX_LINE_CHARS)
    checked = _checked(lines, source, state)
    ih = intelhex.IntelHex()
    try:
        ih.loadhex(_Feed(checked))  # stops after the end-of-file record
    except intelhex.AddressOverlapError as err:
        raise _overlap(err.address, err.line, source, state) from None
    except intelhex.IntelHexError as err:  # the pre-check leaves none of these
        raise ImageError(f"malformed record: {err}", file=source,
                         line=getattr(err, "line", None)) from None
    for _ in checked:  # after the end-of-file record: blank lines only (checked there)
        pass
    if not state.records:
        raise ImageError("empty file: no Intel HEX records", file=source)
    if not state.eof_line:
        raise ImageError(f"no end-of-file record (:00000001FF): the file ends after line "
                         f"{state.last_line}; is it truncated?", file=source,
                         line=state.last_line)
    return _image(ih, source, state)


def _checked(lines: Iterator[tuple[int, str]], source: str, state: _State) -> Iterator[str]:
    """Every line, checked, for ``intelhex`` to number as we do (a blank line stays one)."""
    for no, raw in lines:
        rec = raw.strip(" \t")
        if not rec:
            yield ""
            continue
        if state.eof_line:
            raise ImageError(f"record after the end-of-file record of line {state.eof_line}",
                             file=source, line=no)
        indent = len(raw) - len(raw.lstrip(" \t"))
        _check(rec, source, no, indent, state)
        state.records += 1
        state.last_line = no
        yield rec


def _check(rec: str, source: str, no: int, indent: int, state: _State) -> None:
    """One record's structure, checksum and placement, before ``intelhex`` decodes it."""
    if not rec.startswith(":"):
        hint = ("; this line is an S-record (ucom reads a file named .hex, .ihex or .ihx as "
                "Intel HEX: rename it, e.g. to .S)" if rec[:1] == "S" and rec[1:2].isdigit()
                else "")
        raise ImageError(f"not an Intel HEX record: the line does not begin with ':': "
                         f"{text.clip(rec)}{hint}", file=source, line=no)
    digits = rec[1:]
    bad = text.NOT_HEX.search(digits)
    if bad:
        raise ImageError(f"malformed record: {bad.group()!r} is not a hex digit", file=source,
                         line=no, column=indent + 2 + bad.start())
    if len(digits) < 2:
        where = "inside" if digits else "before"
        raise ImageError(f"record cut short: the record ends {where} its length byte",
                         file=source, line=no)
    length = int(digits[:2], 16)
    need = 2 * (5 + length)  # length, address (2), type, data, checksum
    held = len(digits)
    promise = (f"its length byte {digits[:2]} promises {length} data bytes, {need} hex "
               "digits after ':'")
    if held < need:
        where = ("inside the address" if held < 6 else
                 "inside the record type" if held < 8 else
                 "inside the data" if held < need - 2 else
                 "before the checksum" if held == need - 2 else
                 "inside the checksum")
        raise ImageError(f"record cut short: {promise}, the line has only {held}; it ends "
                         f"{where}", file=source, line=no)
    if held > need:
        raise ImageError(f"wrong record length: {promise}, the line has {held}", file=source,
                         line=no)
    raw = bytes.fromhex(digits)
    address = int.from_bytes(raw[1:3], "big")
    kind = raw[3]
    data = raw[4:-1]
    if kind not in _TYPES:
        raise ImageError(f"unknown record type {kind:02X} (Intel HEX has 00 data, 01 "
                         "end-of-file, 02-05 address records)", file=source, line=no)
    if sum(raw) & 0xFF:
        given = raw[-1]
        expected = (given - sum(raw)) & 0xFF
        raise ImageError(f"checksum mismatch: the record ends in {given:02X}, its bytes give "
                         f"{expected:02X}", file=source, line=no)
    if kind == 0:
        _place(state.offset + address, len(data), source, no, state)
        return
    size = {1: 0, 2: 2, 3: 4, 4: 2, 5: 4}[kind]
    if length != size or (kind != 1 and address != 0):
        raise ImageError(f"malformed {_TYPES[kind]} record ({kind:02X}): it has {length} data "
                         f"bytes" + (f" at address {address:04X}" if kind != 1 else "")
                         + f"; it must have {size}" + (" at address 0000" if kind != 1 else ""),
                         file=source, line=no)
    if kind == 1:
        state.eof_line = no
    elif kind == 2:
        state.offset = int.from_bytes(data, "big") * 16
    elif kind == 4:
        state.offset = int.from_bytes(data, "big") << 16
    else:
        if state.start_line:
            raise ImageError(f"a second start address record; the first is on line "
                             f"{state.start_line}", file=source, line=no)
        state.start_line = no


def _word(byte_address: int) -> tuple[Space, int]:
    """The space and word address of a byte address (X: from 0x00400000 on)."""
    word = byte_address // 2
    return (Space.X, word - X_OFFSET) if word >= X_OFFSET else (Space.P, word)


def _place(start: int, length: int, source: str, no: int, state: _State) -> None:
    """The bytes ``start`` .. ``start + length - 1`` of a data record on line ``no`` must
    be words of the 16-bit P: or X: memory that an image may hold (srec's regions)."""
    if not length:
        return
    first, last = _word(start), _word(start + length - 1)
    for space, addr in (first, last):
        if addr > 0xFFFF:
            raise ImageError(f"byte address 0x{start:X} is word {space.name}:{addr:X}, outside "
                             f"the 16-bit {space.name}: memory (X: starts at byte "
                             f"0x{X_BYTES:08X})", file=source, line=no)
    region = _allowed(*first)
    if region is None or first[0] is not last[0] or _allowed(*last) != region:
        for b in range(start, start + length):
            problem = region_problem(*_word(b))
            if problem:
                raise ImageError(f"byte 0x{b:X}: {problem}", file=source, line=no)
    state.data.append(_Data(no, start, length))


def _allowed(space: Space, addr: int) -> object | None:
    """The region word ``space:addr`` may be written in (one id per region), or None."""
    if space is Space.P and addr in VECTOR_WORDS:
        return "vectors"
    if region_problem(space, addr):
        return None
    return region_of(space, addr)


def _overlap(address: int, line: int, source: str, state: _State) -> ImageError:
    space, addr = _word(address)
    first = state.line_of(address)
    where = f"line {first}" if first is not None and first != line else "an earlier line"
    return ImageError(f"byte 0x{address:X} (word {space.name}:{addr:04X}) is also written "
                      f"on {where} (overlapping data); a word-addressed S-record file "
                      "(CodeWarrior) put through objcopy -O ihex as it is overlaps so, since "
                      "its addresses count words: convert it with 'ucom image convert FILE.S "
                      "FILE.hex' instead", file=source, line=line)


def _image(ih: intelhex.IntelHex, source: str, state: _State) -> Image:
    """The words of the bytes ``intelhex`` read, checked as a whole as srec's are."""
    content: dict[object, int] = ih.todict()  # the bytes, and "start_addr"
    buf = {a: v for a, v in content.items() if isinstance(a, int)}
    words: dict[tuple[Space, int], int] = {}
    vectors: dict[int, int] = {}
    for b in sorted(buf):
        if b % 2 and b - 1 in buf:
            continue  # the high byte of a word already taken
        partner = b + 1 if b % 2 == 0 else b - 1
        if partner not in buf:
            space, addr = _word(b)
            raise ImageError(f"byte 0x{b:X} has no partner at 0x{partner:X}: word "
                             f"{space.name}:{addr:04X} needs both (the DSP56F803 stores "
                             "16-bit words)", file=source, line=state.line_of(b))
        space, addr = _word(b)
        value = buf[b] | (buf[b + 1] << 8)
        if space is Space.P and addr in VECTOR_WORDS:
            vectors[addr] = value
        else:
            words[(space, addr)] = value
    entry, entry_line = _entry(ih.start_addr, source, state)
    index = sorted((d.start, d.line) for d in state.data)
    starts = [s for s, _ in index]

    def line_of(key: tuple[Space, int]) -> int | None:
        space, addr = key
        b = 2 * (addr + (X_OFFSET if space is Space.X else 0))
        i = bisect.bisect_right(starts, b) - 1
        return index[i][1] if i >= 0 else None

    return finish_image(source, header="", entry=entry, entry_line=entry_line,
                             words=words, vectors=vectors, records=state.records,
                             addressing="byte", line_of=line_of, format="ihex")


def _entry(start: dict[str, int] | None, source: str, state: _State) -> tuple[int, int]:
    if not start:
        raise ImageError("no start address record (05, or 03): the entry is unknown; it "
                         "holds 2 x the entry word address", file=source,
                         line=state.eof_line)
    if "EIP" in start:
        byte = start["EIP"]
    else:
        byte = start["CS"] * 16 + start["IP"]
    if byte % 2:
        raise ImageError(f"start address 0x{byte:X} is odd: it holds 2 x the entry word "
                         "address", file=source, line=state.start_line)
    return byte // 2, state.start_line


def dumps(img: Image) -> str:
    """``img`` as Intel HEX text that ``intelhex`` (and ucom) read as it is: the words,
    reset-vector words included, at byte addresses (P:a at 2a, X:a at 0x00400000 + 2a,
    low byte first), :data:`BYTES_PER_RECORD` bytes a record, extended linear address
    records (04) where needed, a start linear address record (05) of 2 x the entry and the
    end-of-file record."""
    ih = intelhex.IntelHex()
    every = dict(img.words)
    every.update({(Space.P, a): v for a, v in img.vector_words.items()})
    for (space, addr), value in every.items():
        b = 2 * (addr + (X_OFFSET if space is Space.X else 0))
        ih[b] = value & 0xFF
        ih[b + 1] = value >> 8
    ih.start_addr = {"EIP": 2 * img.entry}
    out = io.StringIO()
    ih.write_hex_file(out, byte_count=BYTES_PER_RECORD)
    return out.getvalue().replace("\r\n", "\n")
