"""Run-time (MCA) messages of the UCoM protocol, functions 13-15 and 20-27 (Tab. B.4), as
frozen dataclasses; byte layouts in ``man/ucom-protocol.7``, RUN TIME.

Two kinds of frames:

- *generic* frames, identifier type bit 0 and the board's seq ID (0 = broadcast where a
  message allows it): configuration, acknowledgements, descriptions, read-backs;
- *process data*, identifier type bit 1 and a map number 1-31 (per bus, assigned by the
  PC with Admin Data): header-less values, SO maps from the boards (function 14) and CI
  maps to them (function 13), for the cyclic exchange.

Values are raw integers of 2 or 4 bytes, big endian; which edge a value belongs to (its
width, sign and scale) comes from the program's edge list (:mod:`ucom_tools.edgelists`),
so the codecs here carry values as bytes and :func:`pack_values`/:func:`unpack_values`
convert them.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from enum import IntEnum
from typing import ClassVar, Final

from ucom_tools.errors import FrameError
from ucom_tools.wire.digest import DIGEST_KIND, DescrDigest, DigestRequest
from ucom_tools.wire.fields import check_enum, check_length, check_range
from ucom_tools.wire.ids import Address, Function, IdType, decode_id, encode_id

MAX_MAP: Final = 31
"""Process-data map numbers are 1..31 (the identifier's board-number field)."""
MAP_SLOTS: Final = 4
"""A CI map carries up to four 16-bit values; an SO map up to 8 bytes of values."""
NO_EDGE: Final = 0xFF
"""An unused slot in a map definition."""
PROCESS_DATA: Final = 0x80
"""Error function byte ``0x80 | 13``: the error is about a CI map frame (process data),
not a generic MCA Controller Input frame."""


class Kind(IntEnum):
    """Edge kinds as numbered on the wire (== ucom_tools.edgelists.EdgeKind)."""

    CI = 0
    SO = 1
    PAR = 2


class RunState(IntEnum):
    """Byte 0 of MCA Ready: where the board's exchange is."""

    STOPPED = 0
    """The program runs; the exchange is stopped, every motor off (after Start, STOP)."""
    RUNNING = 1
    """The cyclic exchange runs (after MCA Start START); the watchdog is armed."""
    LATCHED = 2
    """The watchdog stopped every motor; only MCA Start START releases it."""


class StartOp(IntEnum):
    QUERY = 0
    """Answer MCA Ready, change nothing."""
    START = 1
    """Start (or restart) the exchange: maps, watchdog, control; releases a latch."""
    STOP = 2
    """Stop the exchange: every motor off, PWM 0, controllers off."""


class AdminOp(IntEnum):
    ALIVE = 0x01
    """[timeout ms u16]: the watchdog time (10..60000)."""
    SO_MAP = 0x02
    """[map][period u16 in cycles][SO index]x1..4: what SO map ``map`` carries, how often
    (period 0 = off)."""
    CI_MAP = 0x03
    """[map][CI index or 0xFF]x4: which CI edge each 16-bit slot of map ``map`` feeds."""
    CLEAR_MAPS = 0x04
    """Forget every SO and CI map of this board."""


ALIVE_MIN_MS: Final = 10
ALIVE_MAX_MS: Final = 60000
ALIVE_DEFAULT_MS: Final = 50


# ----------------------------------------------------------------------------- values
def pack_values(specs: Sequence[tuple[int, bool]], values: Sequence[int]) -> bytes:
    """Raw values as bytes; ``specs`` gives (width, signed) of each."""
    if len(specs) != len(values):
        raise FrameError("values", f"{len(values)} values for {len(specs)} edges")
    out = bytearray()
    for (width, signed), v in zip(specs, values, strict=True):
        try:
            out += v.to_bytes(width, "big", signed=signed)
        except OverflowError:
            raise FrameError("value", f"{v} does not fit {'' if signed else 'un'}signed "
                             f"{8 * width} bit") from None
    return bytes(out)


_STRUCT_CODES: Final = {(1, True): "b", (1, False): "B", (2, True): "h", (2, False): "H",
                        (4, True): "i", (4, False): "I", (8, True): "q", (8, False): "Q"}


def values_struct(specs: Sequence[tuple[int, bool]]) -> struct.Struct | None:
    """A struct that packs and unpacks values of these (width, signed) as
    :func:`pack_values` and :func:`unpack_values` lay them out (big-endian, one after the
    other); None when a width has no struct code."""
    codes = [_STRUCT_CODES.get(spec) for spec in specs]
    if any(c is None for c in codes):
        return None
    return struct.Struct(">" + "".join([c for c in codes if c is not None]))


def unpack_values(specs: Sequence[tuple[int, bool]], data: bytes) -> list[int]:
    """Bytes as raw values; the lengths must add up exactly."""
    need = sum(w for w, _ in specs)
    if need != len(data):
        raise FrameError("values", f"expected {need} bytes for {len(specs)} values, "
                         f"got {len(data)}")
    out, pos = [], 0
    for width, signed in specs:
        out.append(int.from_bytes(data[pos:pos + width], "big", signed=signed))
        pos += width
    return out


# ----------------------------------------------------------------------------- generic
@dataclass(frozen=True, slots=True)
class EdgeWrite:
    """MCA Controller Input (13) or MCA Parameter (15), generic: raw values of consecutive
    edges of one kind from ``index``; acknowledged with MCA Ready."""

    kind: Kind
    index: int
    data: bytes

    def __post_init__(self) -> None:
        if self.kind is Kind.SO:
            raise FrameError("edge write kind", "SO edges are not written")
        check_range("edge index", self.index, 0, 0xFE)
        check_range("edge write values", len(self.data), 2, 7)

    @property
    def FUNCTION(self) -> Function:
        return Function.MCA_CONTROLLER_INPUT if self.kind is Kind.CI else \
            Function.MCA_PARAMETER

    def encode(self) -> bytes:
        return bytes((self.index,)) + self.data


@dataclass(frozen=True, slots=True)
class McaReady:
    """MCA Ready (20): the board's run state and what it answers (20 = unsolicited: the
    program is up; otherwise the function of the frame it acknowledges, with that frame's
    first two payload bytes), and its edge counts."""

    FUNCTION: ClassVar[Function] = Function.MCA_READY
    state: RunState
    answers: int
    echo: bytes
    ci: int
    so: int
    par: int
    flags: int = 0

    def __post_init__(self) -> None:
        check_range("MCA Ready answered function", self.answers, 0, 31)
        if len(self.echo) != 2:
            raise FrameError("MCA Ready echo", f"must be 2 bytes, got {len(self.echo)}")
        for name, n in (("CI", self.ci), ("SO", self.so), ("PAR", self.par)):
            check_range(f"MCA Ready {name} count", n, 0, 0xFF)
        check_range("MCA Ready flags", self.flags, 0, 0xFF)

    def encode(self) -> bytes:
        return bytes((self.state, self.answers)) + self.echo + bytes(
            (self.ci, self.so, self.par, self.flags))

    @classmethod
    def decode(cls, data: bytes) -> McaReady:
        check_length("MCA Ready", data, 8)
        return cls(check_enum(RunState, "MCA Ready state", data[0]), data[1], bytes(data[2:4]),
                   data[4], data[5], data[6], data[7])


FLAG_OVERRUN: Final = 0x01
"""McaReady.flags: a cycle overran since the last MCA Ready."""
FLAG_LATCHED_BY_WATCHDOG: Final = 0x02


@dataclass(frozen=True, slots=True)
class AppStatus:
    """Report channel 3 (APPLICATION) of a running program, asked with Report Request:
    [state][load u16 in 1/1000][cycle time u16 us][overruns u16][flags] (8 bytes)."""

    state: RunState
    load_permille: int
    cycle_us: int
    overruns: int
    flags: int = 0

    def __post_init__(self) -> None:
        for name, v in (("load", self.load_permille), ("cycle time", self.cycle_us),
                        ("overruns", self.overruns)):
            check_range(f"Application report {name}", v, 0, 0xFFFF)
        check_range("Application report flags", self.flags, 0, 0xFF)

    def encode(self) -> bytes:
        return struct.pack(">BHHHB", self.state, self.load_permille, self.cycle_us,
                           self.overruns, self.flags)

    @classmethod
    def decode(cls, data: bytes) -> AppStatus:
        check_length("Application report", data, 8)
        state, load, cycle, overruns, flags = struct.unpack(">BHHHB", data)
        return cls(check_enum(RunState, "Application report state", state), load, cycle,
                   overruns, flags)


@dataclass(frozen=True, slots=True)
class McaStart:
    """MCA Start (21): QUERY, START or STOP the exchange; acknowledged with MCA Ready."""

    FUNCTION: ClassVar[Function] = Function.MCA_START
    op: StartOp

    def encode(self) -> bytes:
        return bytes((self.op,))

    @classmethod
    def decode(cls, data: bytes) -> McaStart:
        check_length("MCA Start", data, 1)
        return cls(check_enum(StartOp, "MCA Start op", data[0]))


@dataclass(frozen=True, slots=True)
class DescrRequest:
    """MCA DumpIO Descr Request (22): every edge's description, or one edge's."""

    FUNCTION: ClassVar[Function] = Function.MCA_DUMPIO_DESCR_REQUEST
    kind: Kind | None = None
    index: int = 0

    def encode(self) -> bytes:
        return b"" if self.kind is None else bytes((self.kind, self.index))

    @classmethod
    def decode(cls, data: bytes) -> DescrRequest:
        check_length("MCA DumpIO Descr Request", data, 0, 2)
        if not data:
            return cls()
        return cls(check_enum(Kind, "DumpIO kind", data[0]), data[1])


_DESCR_HEAD: Final = struct.Struct(">BbiI")
DESCR_SEGMENT: Final = 6
"""Record bytes per MCA DumpIO Descr frame."""


@dataclass(frozen=True, slots=True)
class EdgeRecord:
    """What MCA DumpIO Descr says of one edge: encoding, raw range, name and unit."""

    width: int
    signed: bool
    exponent: int
    minimum: int
    maximum: int
    name: str
    unit: str

    def __post_init__(self) -> None:
        if self.width not in (2, 4):
            raise FrameError("edge width", f"must be 2 or 4, got {self.width}")
        check_range("edge exponent", self.exponent, -128, 127)
        check_range("edge minimum", self.minimum, -(1 << 31), (1 << 31) - 1)
        check_range("edge maximum", self.maximum, -(1 << 31), (1 << 32) - 1)
        for text in (self.name, self.unit):
            if "\0" in text:
                raise FrameError("edge name", "must not contain NUL")

    def encode(self) -> bytes:
        head = _DESCR_HEAD.pack(self.width | (0x80 if self.signed else 0), self.exponent,
                                self.minimum, self.maximum & 0xFFFFFFFF)
        return head + self.name.encode("latin-1", "replace") + b"\0" + \
            self.unit.encode("latin-1", "replace") + b"\0"

    @classmethod
    def decode(cls, data: bytes) -> EdgeRecord:
        if len(data) < _DESCR_HEAD.size + 2:
            raise FrameError("edge record", f"{len(data)} bytes is too short")
        fmt, exponent, minimum, maximum = _DESCR_HEAD.unpack_from(data)
        signed = bool(fmt & 0x80)
        if signed and maximum >= 1 << 31:
            maximum -= 1 << 32
        texts = data[_DESCR_HEAD.size:].split(b"\0")
        if len(texts) != 3 or texts[2]:
            raise FrameError("edge record", "name and unit must each end with NUL")
        return cls(fmt & 0x7F, signed, exponent, minimum, maximum,
                   texts[0].decode("latin-1"), texts[1].decode("latin-1"))

    def segments(self, kind: Kind, index: int) -> list[DescrSegment]:
        raw = self.encode()
        chunks = [raw[i:i + DESCR_SEGMENT] for i in range(0, len(raw), DESCR_SEGMENT)]
        return [DescrSegment(kind, index, n, n == len(chunks) - 1, c)
                for n, c in enumerate(chunks)]


@dataclass(frozen=True, slots=True)
class DescrSegment:
    """MCA DumpIO Descr (23): one piece of an edge's record."""

    FUNCTION: ClassVar[Function] = Function.MCA_DUMPIO_DESCR
    kind: Kind
    index: int
    segment: int
    last: bool
    data: bytes

    def __post_init__(self) -> None:
        check_range("DumpIO index", self.index, 0, 0xFF)
        check_range("DumpIO segment", self.segment, 0, 31)
        check_range("DumpIO segment length", len(self.data), 1, DESCR_SEGMENT)

    def encode(self) -> bytes:
        head = (self.kind << 6) | (0x20 if self.last else 0) | self.segment
        return bytes((head, self.index)) + self.data

    @classmethod
    def decode(cls, data: bytes) -> DescrSegment:
        if not 3 <= len(data) <= 8:
            raise FrameError("MCA DumpIO Descr payload length",
                             f"expected 3..8 bytes, got {len(data)}")
        kind = _KINDS.get(data[0] >> 6)
        if kind is None:
            raise FrameError("DumpIO kind", f"reserved value 0x{data[0] >> 6:02X}")
        return cls(kind, data[1], data[0] & 0x1F, bool(data[0] & 0x20), bytes(data[2:]))


@dataclass(frozen=True, slots=True)
class DumpRequest:
    """MCA Dump CI (24): send the current values of ``count`` edges of ``kind`` from
    ``index`` (CI, SO or PAR: a parameter read-back); answered by MCA DSP CI frames."""

    FUNCTION: ClassVar[Function] = Function.MCA_DUMP_CI
    kind: Kind
    index: int
    count: int

    def __post_init__(self) -> None:
        check_range("Dump index", self.index, 0, 0xFE)
        check_range("Dump count", self.count, 1, 0xFF)

    def encode(self) -> bytes:
        return bytes((self.kind, self.index, self.count))

    @classmethod
    def decode(cls, data: bytes) -> DumpRequest:
        check_length("MCA Dump CI", data, 3)
        return cls(check_enum(Kind, "Dump kind", data[0]), data[1], data[2])


@dataclass(frozen=True, slots=True)
class DumpValues:
    """MCA DSP CI (27): raw values of consecutive edges of ``kind`` from ``index``."""

    FUNCTION: ClassVar[Function] = Function.MCA_DSP_CI
    kind: Kind
    index: int
    data: bytes

    def __post_init__(self) -> None:
        check_range("DSP CI index", self.index, 0, 0xFE)
        check_range("DSP CI values", len(self.data), 2, 6)

    def encode(self) -> bytes:
        return bytes((self.kind, self.index)) + self.data

    @classmethod
    def decode(cls, data: bytes) -> DumpValues:
        if not 4 <= len(data) <= 8:
            raise FrameError("MCA DSP CI payload length", f"expected 4..8 bytes, got "
                             f"{len(data)}")
        return cls(check_enum(Kind, "DSP CI kind", data[0]), data[1], bytes(data[2:]))


@dataclass(frozen=True, slots=True)
class AdminData:
    """MCA Admin Data (25): one configuration item (see :class:`AdminOp`); acknowledged
    with MCA Ready echoing ``op`` and the first argument byte."""

    FUNCTION: ClassVar[Function] = Function.MCA_ADMIN_DATA
    op: AdminOp
    args: bytes = b""

    def __post_init__(self) -> None:
        need = {AdminOp.ALIVE: (2,), AdminOp.SO_MAP: (4, 5, 6, 7),
                AdminOp.CI_MAP: (5,), AdminOp.CLEAR_MAPS: (0,)}[self.op]
        if len(self.args) not in need:
            raise FrameError(f"Admin Data {self.op.name} payload length",
                             f"expected {' or '.join(str(n + 1) for n in need)} bytes, "
                             f"got {len(self.args) + 1}")
        if self.op in (AdminOp.SO_MAP, AdminOp.CI_MAP):
            check_range("Admin Data map", self.args[0], 1, MAX_MAP)
        if self.op is AdminOp.ALIVE:
            check_range("Admin Data alive timeout", self.alive_ms, ALIVE_MIN_MS, ALIVE_MAX_MS)

    @classmethod
    def alive(cls, timeout_ms: int) -> AdminData:
        return cls(AdminOp.ALIVE, timeout_ms.to_bytes(2, "big"))

    @classmethod
    def so_map(cls, map_no: int, period: int, edges: Sequence[int]) -> AdminData:
        check_range("SO map edges", len(edges), 1, 4)
        check_range("SO map period", period, 0, 0xFFFF)
        return cls(AdminOp.SO_MAP, bytes((map_no,)) + period.to_bytes(2, "big") + bytes(edges))

    @classmethod
    def ci_map(cls, map_no: int, slots: Sequence[int]) -> AdminData:
        if len(slots) != MAP_SLOTS:
            raise FrameError("CI map slots", f"need {MAP_SLOTS} (0xFF = not this board's)")
        return cls(AdminOp.CI_MAP, bytes((map_no, *slots)))

    @property
    def alive_ms(self) -> int:
        return int.from_bytes(self.args[:2], "big")

    @property
    def map_no(self) -> int:
        return self.args[0]

    @property
    def period(self) -> int:
        return int.from_bytes(self.args[1:3], "big")

    @property
    def edges(self) -> tuple[int, ...]:
        return tuple(self.args[3:]) if self.op is AdminOp.SO_MAP else tuple(self.args[1:])

    def encode(self) -> bytes:
        return bytes((self.op,)) + self.args

    @classmethod
    def decode(cls, data: bytes) -> AdminData:
        if not data:
            raise FrameError("MCA Admin Data payload length", "expected 1..8 bytes, got 0")
        return cls(check_enum(AdminOp, "Admin Data op", data[0]), bytes(data[1:]))


@dataclass(frozen=True, slots=True)
class Alive:
    """MCA Alive (26): the PC is alive (broadcast or addressed; no answer)."""

    FUNCTION: ClassVar[Function] = Function.MCA_ALIVE

    def encode(self) -> bytes:
        return b""

    @classmethod
    def decode(cls, data: bytes) -> Alive:
        check_length("MCA Alive", data, 0)
        return cls()


MAP_MASK: Final = 0x55
"""Every byte of a process-data payload travels XOR 0x55 (``man/ucom-protocol.7``, RUN
TIME, Process data): values at rest (0, -1, small numbers: long runs of equal bits) would
otherwise need up to 20 stuff bits per frame; masked, they need almost none, which keeps
a fully loaded bus's load close to its nominal figure (Nolte et al., *Reducing the number
of stuff bits in CAN frames*, 2001)."""
_MASK_TABLE: Final = bytes(b ^ MAP_MASK for b in range(256))


def mask(data: bytes | bytearray) -> bytes:
    """A process-data payload as it travels, or back (the mask is its own inverse)."""
    return bytes(data).translate(_MASK_TABLE)


@dataclass(frozen=True, slots=True)
class MapFrame:
    """Process data (13 down, 14 up; identifier type 1, map number): the values of a map,
    without header; ``data`` holds them plainly, the wire carries them masked
    (:func:`mask`)."""

    function: Function
    map_no: int
    data: bytes

    def __post_init__(self) -> None:
        if self.function not in (Function.MCA_CONTROLLER_INPUT, Function.MCA_SENSOR_OUTPUT):
            raise FrameError("map function", "process data is CI (13) or SO (14)")
        check_range("map number", self.map_no, 1, MAX_MAP)
        check_range("map data length", len(self.data), 2, 8)

    @property
    def FUNCTION(self) -> Function:
        return self.function

    def encode(self) -> bytes:
        return mask(self.data)

    def arbitration_id(self) -> int:
        return encode_id(self.function, Address(IdType.FIXED, self.map_no))


McaMessage = (EdgeWrite | McaReady | McaStart | DescrRequest | DescrSegment | DumpRequest
              | DumpValues | AdminData | Alive | MapFrame | DigestRequest | DescrDigest)

_FUNCTIONS: Final = {int(f): f for f in Function}
"""Each function by its code (an enum's call costs some microseconds a frame)."""
_KINDS: Final = {int(k): k for k in Kind}

MCA_FUNCTIONS: Final = frozenset({
    Function.MCA_CONTROLLER_INPUT, Function.MCA_SENSOR_OUTPUT, Function.MCA_PARAMETER,
    Function.MCA_READY, Function.MCA_START, Function.MCA_DUMPIO_DESCR_REQUEST,
    Function.MCA_DUMPIO_DESCR, Function.MCA_DUMP_CI, Function.MCA_ADMIN_DATA,
    Function.MCA_ALIVE, Function.MCA_DSP_CI})


def encode(message: McaMessage, address: Address | None = None) -> tuple[int, bytes]:
    """(identifier, payload) of a run-time message; process data carry their map number,
    every other message goes to (or comes from) ``address`` (a seq ID, or broadcast)."""
    if isinstance(message, MapFrame):
        return message.arbitration_id(), message.encode()
    if address is None:
        raise FrameError("address", "a generic MCA message needs a board address")
    if address.id_type is not IdType.SEQUENTIAL:
        raise FrameError("address", "run-time messages address boards by seq ID (type 0)")
    return encode_id(message.FUNCTION, address), message.encode()


def decode(arbitration_id: int, data: bytes) -> tuple[Address | None, McaMessage]:
    """Decode a run-time frame: (board address, message), or (None, MapFrame) for process
    data.  Raises :class:`FrameError` naming the field for anything malformed."""
    code, address = decode_id(arbitration_id)
    if code not in MCA_FUNCTIONS:
        raise FrameError("function", f"code {code} is not a run-time (MCA) message")
    function = _FUNCTIONS[code]
    data = bytes(data)
    if address.id_type is IdType.FIXED:
        if function not in (Function.MCA_CONTROLLER_INPUT, Function.MCA_SENSOR_OUTPUT):
            raise FrameError("identifier type", f"{function.label} has no process data form")
        return None, MapFrame(function, address.number, mask(data))
    if function in (Function.MCA_CONTROLLER_INPUT, Function.MCA_PARAMETER):
        if len(data) < 3:
            raise FrameError(f"{function.label} payload length",
                             f"expected 3..8 bytes, got {len(data)}")
        kind = Kind.CI if function is Function.MCA_CONTROLLER_INPUT else Kind.PAR
        return address, EdgeWrite(kind, data[0], data[1:])
    if function is Function.MCA_SENSOR_OUTPUT:
        raise FrameError("identifier type", "MCA Sensor Output is process data (type 1) only")
    return address, _DECODERS[function](data)


def _descr_request(data: bytes) -> DescrRequest | DigestRequest:
    """22: DLC 0 or 2 the records, DLC 1 the digest (:mod:`ucom_tools.wire.digest`)."""
    return DigestRequest.decode(data) if len(data) == 1 else DescrRequest.decode(data)


def _descr(data: bytes) -> DescrSegment | DescrDigest:
    """23: a record's segment, or (kind 3) the digest."""
    if data and data[0] >> 6 == DIGEST_KIND:
        return DescrDigest.decode(data)
    return DescrSegment.decode(data)


_DECODERS: Final[dict[Function, Callable[[bytes], McaMessage]]] = {
    Function.MCA_READY: McaReady.decode, Function.MCA_START: McaStart.decode,
    Function.MCA_DUMPIO_DESCR_REQUEST: _descr_request,
    Function.MCA_DUMPIO_DESCR: _descr, Function.MCA_DUMP_CI: DumpRequest.decode,
    Function.MCA_ADMIN_DATA: AdminData.decode, Function.MCA_ALIVE: Alive.decode,
    Function.MCA_DSP_CI: DumpValues.decode,
}
