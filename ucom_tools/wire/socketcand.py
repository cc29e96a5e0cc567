"""The socketcand elements (raw mode) as pure code: cutting a byte stream into elements
``< ... >``, and writing and reading the ``< frame ... >`` and ``< send ... >`` elements.

One copy for both ends: the client (:mod:`ucom_tools.transport.socketcand`) and the server
of ``ucom fleet serve`` (:mod:`ucom_tools.virtual.serve.socketcand`).  The rules are those of
``ucom-protocol(7)``, SOCKETCAND (and socketcand's own ``doc/protocol.md``):

- an element is ``<`` ... ``>``, at most :data:`MAX_ELEMENT` bytes with both brackets;
  bytes outside elements are skipped, and an unfinished element that a new ``<``
  interrupts is skipped with them (no element contains ``<``);
- ``< frame ID SEC.USEC DATA >``: ID 3 hex digits (an 11-bit identifier) or 8 (29-bit),
  DATA contiguous hex digits, as socketcand writes it (:data:`FRAME_STD`,
  :data:`FRAME_EXT`); read also with DATA as blank-separated hex bytes;
- ``< send ID DLC B0 B1 ... >``: ID 1-3 hex digits (0..7FF) or exactly 8 (0..1FFFFFFF,
  extended), DLC one hex digit 0..8, exactly DLC data bytes of 1-2 hex digits each.

An identifier that is extended carries :data:`CAN_EFF_FLAG` here, as SocketCAN's
``can_id`` does (what socketcand passes to the kernel).  Nothing here does I/O; the
functions on the per-frame paths are written for speed: one regular-expression match, or
one scan byte by byte (:func:`plain_send`, :meth:`ElementSplitter.plain_data` where the
module is compiled), and hardly an object beyond the result.
"""

from __future__ import annotations

import binascii
import re
from collections.abc import Callable
from typing import TYPE_CHECKING, Final

if TYPE_CHECKING:  # i64 annotations (see compiled.py)
    from mypy_extensions import i64

MAX_ELEMENT = 4096
"""Longest element accepted from the other end, ``<`` and ``>`` included, in bytes."""
CAN_EFF_FLAG = 0x80000000
"""Marks an extended frame's identifier, as in SocketCAN's ``can_id``."""
CAN_EFF_MASK = 0x1FFFFFFF
CAN_SFF_MASK = 0x7FF

FRAME_STD_HEAD = b"< frame %03X "
"""``< frame ID `` of a standard frame, ``%`` with its identifier (:data:`FRAME_STD`'s
head: the serving path puts elements together from it, :mod:`~ucom_tools.virtual.
serve.outbox`)."""
FRAME_EXT_HEAD = b"< frame %08X "
"""The same for an extended frame (the identifier without :data:`CAN_EFF_FLAG`)."""
FRAME_STD = FRAME_STD_HEAD + b"%.6f %s >"
"""``< frame ID SEC.USEC DATA >`` of a standard frame, ``%`` with identifier, time in
seconds and the data as upper-case hex digits (:func:`frame_element`)."""
FRAME_EXT = FRAME_EXT_HEAD + b"%.6f %s >"
"""The same for an extended frame (the identifier without :data:`CAN_EFF_FLAG`)."""
SEND_STD = b"< send %03X %d %s >"
"""``< send ID DLC B0 B1 ... >`` of a standard frame with data, ``%`` with identifier,
DLC and the bytes as upper-case hex digits separated by blanks (:func:`send_element`)."""
SEND_EMPTY = b"< send %03X 0 >"
"""The same without data (DLC 0)."""

_HEX = re.compile(r"[0-9A-Fa-f]+", re.ASCII)
_TIMESTAMP = re.compile(r"\d+(?:\.\d+)?", re.ASCII)
_FRAME = re.compile(rb" frame ([0-9A-Fa-f]{3}|[0-9A-Fa-f]{8}) (\d+\.\d+) ([0-9A-Fa-f]{0,16}) ?\Z")
"""The usual frame element (contiguous data, single blanks), read in one match."""
_STD_RUN = re.compile(rb"(?:< frame [0-7][0-9A-Fa-f]{2} "
                      rb"\d{1,20}\.\d{1,15} (?:[0-9A-Fa-f]{2}){0,8} ?>)+")
"""Consecutive standard frame elements in the usual form, brackets included, each one
that :func:`plain_frame` reads (identifier in range, an even number of data digits), and
none longer than :data:`_STD_RUN_LONGEST` (:func:`_matched`)."""
_STD_RUN_LONGEST = 80
_FRAME_FIELDS = re.compile(rb"< frame ([0-9A-Fa-f]+) (\d+)\.(\d+) ([0-9A-Fa-f]*) ?>")
"""The fields of the elements :data:`_STD_RUN` took (it checked them already)."""
_NATIVE: Final = not __file__.endswith(".py")
"""This module runs compiled (:mod:`ucom_tools.compiled`): :meth:`ElementSplitter.
plain_data` scans byte by byte (:func:`_scanned`); from source the regular expressions are
faster (:func:`_matched`).  Both take the same frames (``tests/test_plain_data.py``)."""
_PLAIN_SEND = re.compile(rb" ?send ([0-9A-Fa-f]{1,3}) ([0-8])((?: [0-9A-Fa-f]{1,2}){0,8}) ?")
"""A ``send`` element as clients write it (single blanks): the form :func:`plain_send`
reads (without this expression; the tests hold the two to each other)."""


class ElementError(ValueError):
    """A malformed element (the server answers it with ``< error MESSAGE >``)."""


class ElementTooLong(ElementError):
    """An element longer than the limit: the stream cannot be trusted any more."""


class ElementSplitter:
    """Cuts a byte stream into elements ``< ... >``: they may arrive split across reads or
    several in one.  Holds at most ``limit`` bytes of an unfinished element.

    ``on_skip`` hears the bytes skipped outside elements (a log), if given.
    """

    def __init__(self, limit: int = MAX_ELEMENT,
                 on_skip: Callable[[bytes], None] | None = None) -> None:
        self.limit = limit
        self._on_skip = on_skip
        self._buffer = bytearray()
        self._pos = 0
        """Where the unread part of the buffer starts: the elements taken are dropped at
        the next :meth:`feed`, not one at a time (a chunk of many is cut in linear time)."""

    def feed(self, chunk: bytes | memoryview) -> None:
        if self._pos:
            del self._buffer[:self._pos]
            self._pos = 0
        self._buffer += chunk

    def next(self) -> bytes | None:
        """The text between ``<`` and ``>`` of the next complete element, or None until
        more data come; :class:`ElementTooLong` instead of holding more than ``limit``
        bytes of one."""
        buf = self._buffer
        pos = self._pos
        end = buf.find(b">", pos)
        if end >= 0 and buf.rfind(b"<", pos, end) == pos and end - pos < self.limit:
            self._pos = end + 1  # the usual case: an element where the last one ended
            return bytes(buf[pos + 1:end])
        return self._next_after_skipping()

    def plain_data(self, arrival: float, offset: float,
                   ) -> tuple[list[tuple[int, bytes, float]], float]:
        """The standard data frames of the frame elements in the usual form from where the
        unread part starts, up to the first other element (an extended frame's too, or an
        unfinished one): identifier, data and time stamp on the reader's clock, the
        reader's ``offset`` (``arrival`` minus the smallest difference between a frame's
        arrival and its time stamp seen so far) updated frame by frame; and that offset.
        Each frame's values are :func:`plain_frame`'s (the time stamp plus the offset);
        what is not one is left to :meth:`next`.  The run time's receiving path: one call
        per chunk, no ``can.Message``."""
        if self.limit <= _STD_RUN_LONGEST:  # the elements' length must be checked
            return [], offset
        if _NATIVE:
            frames, offset, self._pos = _scanned(self._buffer, self._pos, arrival, offset)
        else:
            frames, offset, self._pos = _matched(self._buffer, self._pos, arrival, offset)
        return frames, offset

    def unread(self) -> int:
        """Bytes fed and not yet returned as elements or skipped."""
        return len(self._buffer) - self._pos

    def _next_after_skipping(self) -> bytes | None:
        """:meth:`next` when bytes are to be skipped first, or there is no element yet."""
        buf = self._buffer
        pos = self._pos
        while True:
            end = buf.find(b">", pos)
            if end < 0:
                start = buf.rfind(b"<", pos)
                if start < 0:
                    self._skip(pos, len(buf))
                    return None
                self._skip(pos, start)
                if len(buf) - start >= self.limit:  # its ">" would make it too long
                    raise ElementTooLong(f"an element is longer than {self.limit} bytes")
                return None
            start = buf.rfind(b"<", pos, end)  # a "<" before it ends an unfinished one
            if start >= 0:
                break
            self._skip(pos, end + 1)  # a ">" outside an element
            pos = end + 1
        self._skip(pos, start)
        if end + 1 - start > self.limit:
            raise ElementTooLong(f"an element is longer than {self.limit} bytes")
        self._pos = end + 1
        return bytes(buf[start + 1:end])

    def rest(self) -> bytes:
        """The bytes fed and not yet returned as elements (and forget them): what a
        process that hands a connection over sends along."""
        rest = bytes(self._buffer[self._pos:])
        self._buffer.clear()
        self._pos = 0
        return rest

    def _skip(self, start: int, end: int) -> None:
        self._pos = end
        if self._on_skip is not None and start < end:
            self._on_skip(bytes(self._buffer[start:end]))


def element_words(element: bytes) -> list[str]:
    """The words of an element's text; non-ASCII or empty elements are errors."""
    try:
        words = element.decode("ascii").split()
    except UnicodeDecodeError:
        raise ElementError("non-ASCII bytes in element") from None
    if not words:
        raise ElementError("empty element")
    return words


def quote(text: str, limit: int = 16) -> str:
    """``text`` safe to echo inside an element: printable ASCII, no ``<``, short."""
    shown = "".join(c if "!" <= c <= "~" and c != "<" else "?" for c in text[:limit])
    return shown + ("..." if len(text) > limit else "")


def error_element(text: str, raw: bool = False) -> str:
    """A server's answer to a malformed element: ``< error TEXT >``, in raw mode
    ``< error TEXT>``: there ``< error CLASS SEC.USEC >`` is an error frame, and
    python-can's client (4.6) fails on any other text in that form (see
    :mod:`ucom_tools.virtual.serve.socketcand`)."""
    return f"< error {text}>" if raw else f"< error {text} >"


# ---------------------------------------------------------------------- error frame
CAN_ERR_FLAG: Final = 0x20000000
"""Marks an error frame's ``can_id`` in SocketCAN; its low bits are the error's class."""
CAN_ERR_CRTL: Final = 0x004
"""Error class: the controller's problems (its details are in the data, which socketcand
does not pass on)."""
CAN_ERR_ACK: Final = 0x020
"""Error class: a frame this node sent was acknowledged by no other node (nobody on the
bus listens: a cut cable, every other node off or bus-off)."""
CAN_ERR_BUSOFF: Final = 0x040
"""Error class: this node's controller went bus-off."""
CAN_ERR_RESTARTED: Final = 0x100
"""Error class: the controller was restarted (error-active again)."""
_ERROR_FRAME = re.compile(rb" ?error ([0-9A-Fa-f]{1,8}) (\d+\.\d+) ?\Z")


def error_frame_element(error_class: int, seconds: float) -> bytes:
    """``< error CLASS SEC.USEC >``: socketcand's element for an error frame of its bus
    (SocketCAN's ``can_id & CAN_EFF_MASK`` of it, three hex digits, and its time), as its
    raw mode writes it; without the error frame's data, which socketcand drops."""
    return b"< error %03X %.6f >" % (error_class & CAN_EFF_MASK, seconds)


def error_frame(element: bytes) -> tuple[int, float] | None:
    """The class and time of an error frame element (``error CLASS SEC.USEC`` between
    the brackets), or None: another ``< error ... >`` (a server's complaint in words)."""
    m = _ERROR_FRAME.match(element)
    if m is None:
        return None
    return int(m.group(1), 16), float(m.group(2))


# ---------------------------------------------------------------------- frame
def frame_element(can_id: int, seconds: float, data: bytes) -> bytes:
    """``< frame ID SEC.USEC DATA >`` as socketcand writes it; ``can_id`` with
    :data:`CAN_EFF_FLAG` for an extended frame (the server's per-frame path puts the
    same bytes together from :data:`FRAME_STD_HEAD` and :data:`FRAME_EXT_HEAD`:
    :func:`~ucom_tools.virtual.serve.outbox.encode_lines`)."""
    if can_id & CAN_EFF_FLAG:
        return FRAME_EXT % (can_id & CAN_EFF_MASK, seconds, binascii.hexlify(data).upper())
    return FRAME_STD % (can_id, seconds, binascii.hexlify(data).upper())


def plain_frame(element: bytes) -> tuple[int, float, bytes] | None:
    """``can_id`` (with :data:`CAN_EFF_FLAG` if extended), time and data of a frame
    element in the usual form (the text between the brackets: identifier of 3 or 8 hex
    digits, contiguous data), or None: then :func:`frame_words` decides."""
    m = _FRAME.match(element)
    if m is None:
        return None
    ident, data = m.group(1, 3)
    if len(data) % 2:
        return None
    can_id = int(ident, 16)
    if len(ident) == 8:
        if can_id > CAN_EFF_MASK:
            return None
        can_id |= CAN_EFF_FLAG
    elif can_id > CAN_SFF_MASK:
        return None
    return can_id, float(m.group(2)), binascii.unhexlify(data)


FRACTION_SCALES = {n: 10.0 ** n for n in range(1, 16)}
"""10 to the power of a fraction's digits, as a float (exact up to 10**22)."""
EXACT_FLOAT: Final = 1 << 53
"""Integers up to this are exact as floats."""


def seconds_of(seconds: bytes, fraction: bytes) -> float:
    """``float(b"SEC.FRACTION")``, the same value: an integer of the digits divided by a
    power of ten is rounded once, as the parse is, and this costs half as much as
    parsing the 16 digits of a time stamp (Python's float parser takes a slow path
    beyond 15)."""
    digits = int(seconds + fraction)
    scale = FRACTION_SCALES.get(len(fraction))
    if scale is None or digits > EXACT_FLOAT:
        return float(seconds + b"." + fraction)
    return digits / scale


def _matched(buf: bytearray, pos: int, arrival: float, offset: float,
             ) -> tuple[list[tuple[int, bytes, float]], float, int]:
    """:meth:`ElementSplitter.plain_data` of ``buf`` from ``pos`` by two passes of the
    regular-expression engine over it: the frames, the offset and where the run ends."""
    run = _STD_RUN.match(buf, pos)
    if run is None:
        return [], offset, pos
    end = run.end()
    out: list[tuple[int, bytes, float]] = []
    for ident, seconds, fraction, data in _FRAME_FIELDS.findall(buf, pos, end):
        stamp = seconds_of(seconds, fraction)
        if arrival - stamp < offset:
            offset = arrival - stamp
        out.append((int(ident, 16), binascii.unhexlify(data), stamp + offset))
    return out, offset, end


def _scanned(buf: bytearray, pos: int, arrival: float, offset: float,
             ) -> tuple[list[tuple[int, bytes, float]], float, int]:
    """:func:`_matched` by one scan byte by byte (:func:`_std_data`) of a copy of the
    buffer as ``bytes`` (what the compiled code indexes natively), :data:`_STD_WINDOW`
    bytes at a time."""
    size = len(buf)
    start = pos
    out: list[tuple[int, bytes, float]] = []
    while True:
        stop = min(size, start + _STD_WINDOW)
        text = bytes(buf) if start == 0 and stop == size else bytes(buf[start:stop])
        taken, offset = _std_data(text, arrival, offset, out)
        start += taken
        if stop == size or stop - start >= _STD_LONGEST:
            break  # where the run stops is in the window (or no more bytes came)
    return out, offset, start


_FRACTION_SCALE: Final[tuple[float, ...]] = (1.0, *FRACTION_SCALES.values())
""":data:`FRACTION_SCALES` by the number of digits, as a tuple."""
_UNHEXLIFY: Final = binascii.unhexlify
_STD_LONGEST: Final = 67
"""The longest element :func:`_std_data` takes: ``< frame ID `` (12 bytes), 20 + 1 + 15
for the time stamp, a blank, 16 data digits and `` >``."""
_STD_WINDOW: Final = 4096
"""Bytes of the buffer :meth:`ElementSplitter.plain_data` copies at a time (the copy of a
long buffer for a short run would cost more than the run)."""


def _std_data(text: bytes, arrival: float, offset: float,
              out: list[tuple[int, bytes, float]]) -> tuple[int, float]:
    """:meth:`ElementSplitter.plain_data` of ``text``, its frames appended to ``out``:
    where the run of elements stops in ``text``, and the offset.

    The elements it takes, back to back from the start: ``< frame ``, an identifier of 3
    hex digits 000..7FF, a blank, 1-20 decimal digits, ``.``, 1-15 decimal digits, a
    blank, 0-8 pairs of hex digits, an optional blank and ``>``.  Read byte by byte in
    one scan (native in the compiled module: ``i64`` indices and digits), the time
    stamp's digits as they come; an element that ``text`` ends in is not taken (its
    reads run past the end: ``IndexError``)."""
    hex_value = _HEX_DIGIT
    n: i64 = len(text)
    i: i64 = 0
    try:
        while i < n:
            if text[i] != 60 or text[i + 1] != 32 or text[i + 2] != 102 \
                    or text[i + 3] != 114 or text[i + 4] != 97 or text[i + 5] != 109 \
                    or text[i + 6] != 101 or text[i + 7] != 32:
                break  # not "< frame "
            high: i64 = text[i + 8] - 48
            middle: i64 = hex_value[text[i + 9]]
            low: i64 = hex_value[text[i + 10]]
            if high < 0 or high > 7 or middle > 15 or low > 15 or text[i + 11] != 32:
                break  # not an identifier 000..7FF and a blank
            start: i64 = i + 12
            j: i64 = start
            digits: i64 = 0  # SEC and FRACTION's (beyond 18 of them wrong, and not used)
            c: i64 = text[j]
            while 48 <= c <= 57:
                digits = digits * 10 + c - 48
                j += 1
                c = text[j]
            point: i64 = j
            if j == start or j - start > 20 or c != 46:
                break  # not 1-20 digits and "."
            j += 1
            c = text[j]
            while 48 <= c <= 57:
                digits = digits * 10 + c - 48
                j += 1
                c = text[j]
            places: i64 = j - point - 1
            if places < 1 or places > 15 or c != 32:
                break  # not 1-15 digits and a blank
            blank: i64 = j
            j += 1
            while hex_value[text[j]] <= 15:
                j += 1
            last: i64 = j
            if (last - blank - 1) & 1 or last - blank - 1 > 16:
                break  # not 0-8 pairs of hex digits
            c = text[j]
            if c == 32:
                j += 1
                c = text[j]
            if c != 62:
                break  # not ">"
            if blank - start > 19 or digits > EXACT_FLOAT:  # more than 18 digits, or big
                stamp = seconds_of(text[start:point], text[point + 1:blank])
            else:
                stamp = float(digits) / _FRACTION_SCALE[places]  # seconds_of's value
            if arrival - stamp < offset:
                offset = arrival - stamp
            out.append((high << 8 | middle << 4 | low, _UNHEXLIFY(text[blank + 1:last]),
                        stamp + offset))
            i = j + 1
    except IndexError:
        pass  # text ends in the element at i
    return i, offset


def frame_words(words: list[str]) -> tuple[int, float, bytes]:
    """``can_id``, time and data of ``< frame ID SEC.USEC DATA >`` as words (``frame``
    first); ``ValueError`` if malformed.  ID has 3 hex digits (11-bit identifier) or 8
    (29-bit); DATA is contiguous hex digits (socketcand) or hex bytes separated by
    blanks; no data is a frame with DLC 0."""
    if len(words) < 3:
        raise ValueError("a frame needs an identifier and a timestamp")
    ident, stamp, data_words = words[1], words[2], words[3:]
    if len(ident) not in (3, 8) or not _HEX.fullmatch(ident):
        raise ValueError(f"identifier {ident!r} is not 3 or 8 hex digits")
    extended = len(ident) == 8
    can_id = int(ident, 16)
    if can_id > (CAN_EFF_MASK if extended else CAN_SFF_MASK):
        raise ValueError(f"identifier {ident} is out of range")
    if not _TIMESTAMP.fullmatch(stamp):
        raise ValueError(f"timestamp {stamp!r} is not SEC.USEC")
    if not all(_HEX.fullmatch(w) for w in data_words):
        raise ValueError("data are not hex digits")
    if len(data_words) == 1 and len(data_words[0]) % 2 == 0:
        data = bytes.fromhex(data_words[0])
    elif all(len(w) <= 2 for w in data_words):
        data = bytes(int(w, 16) for w in data_words)
    else:
        raise ValueError("data are neither contiguous hex digits nor hex bytes")
    if len(data) > 8:
        raise ValueError(f"{len(data)} data bytes, more than 8")
    return (can_id | CAN_EFF_FLAG if extended else can_id), float(stamp), data


# ---------------------------------------------------------------------- send
def send_element(can_id: int, data: bytes) -> bytes:
    """``< send ID DLC B0 B1 ... >`` for ``can_id`` (with :data:`CAN_EFF_FLAG` if
    extended) and up to 8 data bytes; ``ValueError`` with the reason otherwise."""
    if can_id & CAN_EFF_FLAG:
        ident = can_id & ~CAN_EFF_FLAG
        if not 0 <= ident <= CAN_EFF_MASK:
            raise ValueError(f"identifier 0x{ident:X}: more than 29 bits")
        text = b"%08X" % ident
    else:
        if not 0 <= can_id <= CAN_SFF_MASK:
            raise ValueError(f"identifier 0x{can_id:X}: more than 11 bits")
        if data and len(data) <= 8:
            return SEND_STD % (can_id, len(data), data.hex(" ").upper().encode())
        text = b"%03X" % can_id
    if len(data) > 8:
        raise ValueError(f"{len(data)} data bytes, more than 8")
    return b" ".join([b"< send", text, b"%d" % len(data), *(b"%02X" % b for b in data), b">"])


def parse_send(args: list[str]) -> tuple[int, bytes]:
    """``can_id`` (with :data:`CAN_EFF_FLAG` if extended) and data of ``< send ID DLC B0
    B1 .. >`` from the words after ``send``; :class:`ElementError` with the answer if
    malformed."""
    if len(args) < 2:
        raise ElementError("usage: send ID DLC DATA...")
    ident, dlc_text, *byte_words = args
    can_id = _identifier(ident)
    dlc = _dlc(dlc_text)
    if len(byte_words) != dlc:
        raise ElementError(f"DLC {dlc} but {len(byte_words)} data bytes")
    return can_id, bytes(_data_byte(w) for w in byte_words)


def _hex_values() -> list[int]:
    values = [-1] * 256
    for digit, char in enumerate(b"0123456789ABCDEF"):
        values[char] = digit
    for digit, char in enumerate(b"abcdef"):
        values[char] = 10 + digit
    return values


_HEX_VALUE: Final[list[int]] = _hex_values()
"""The value of each byte as a hex digit, -1 for the bytes that are none."""
_HEX_DIGIT: Final = bytes(value & 0xFF for value in _HEX_VALUE)
""":data:`_HEX_VALUE` as ``bytes``, 255 for the bytes that are no hex digit (the compiled
code indexes ``bytes`` natively, a list through its objects: :func:`_std_data`)."""


def plain_send(element: bytes) -> tuple[int, bytes] | None:
    """:func:`parse_send` of a well-formed standard ``send`` element in the form clients
    write (the text between the brackets, ``send 280 2 01 00``, single blanks), or None:
    then :func:`element_words` and :func:`parse_send` decide, which accept the same
    frames.

    What :data:`_PLAIN_SEND` matches (the form's definition), read byte by byte: one
    scan, no match object, no words (this runs for every frame a client sends)."""
    n = len(element)
    i = 1 if n and element[0] == 32 else 0  # " send ..."
    if n - i < 8 or element[i] != 115 or element[i + 1] != 101 or \
            element[i + 2] != 110 or element[i + 3] != 100 or element[i + 4] != 32:
        return None  # not "send ", or too short for "send I D"
    hex_value = _HEX_VALUE
    i += 5
    can_id = 0
    start = i
    while i < n and i - start < 4:
        digit = hex_value[element[i]]
        if digit < 0:
            break
        can_id = can_id << 4 | digit
        i += 1
    if i == start or i - start > 3 or i + 1 >= n or element[i] != 32:
        return None
    dlc = element[i + 1] - 48
    if dlc < 0 or dlc > 8 or can_id > CAN_SFF_MASK:
        return None
    i += 2
    values = bytearray(dlc)
    count = 0
    while i < n:  # " B" or " BB" per byte, then at most one blank
        if element[i] != 32:
            return None
        i += 1
        if i == n:
            break  # the one blank at the end
        high = hex_value[element[i]]
        if high < 0 or count == dlc:
            return None
        i += 1
        low = hex_value[element[i]] if i < n else -1
        if low >= 0:
            values[count] = high << 4 | low
            i += 1
        else:
            values[count] = high
        count += 1
    if count != dlc:
        return None
    return can_id, bytes(values)


def _identifier(text: str) -> int:
    """A standard identifier (1-3 hex digits) or an extended one (8, with the flag)."""
    if not _HEX.fullmatch(text) or len(text) not in (1, 2, 3, 8):
        raise ElementError(f"bad identifier {quote(text)}: 1-3 hex digits (11 bit) "
                           "or 8 (29 bit)")
    value = int(text, 16)
    if len(text) == 8:
        if value > CAN_EFF_MASK:
            raise ElementError(f"extended identifier {text} above 1FFFFFFF")
        return value | CAN_EFF_FLAG
    if value > CAN_SFF_MASK:
        raise ElementError(f"identifier {text} above 7FF")
    return value


def _dlc(text: str) -> int:
    if len(text) != 1 or not _HEX.fullmatch(text):
        raise ElementError(f"bad DLC {quote(text)}: one hex digit 0..8")
    value = int(text, 16)
    if value > 8:
        raise ElementError(f"DLC {text} above 8")
    return value


def _data_byte(text: str) -> int:
    if len(text) > 2 or not _HEX.fullmatch(text):
        raise ElementError(f"bad data byte {quote(text)}: 1-2 hex digits")
    return int(text, 16)
