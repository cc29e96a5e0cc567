"""The PDOs of one gateway node: compiled from its dictionary's PDO records (0x1400-0x1BFF)
into plans that are cheap to run on every SYNC, and the checks a master's SDO writes to
those records pass before they are stored.

A TPDO's frame is the concatenation of its mapped objects' stored bytes (the dictionary
keeps every value little-endian, as the frame carries it): building one is a join over
references fixed when the PDO was compiled, no per-value encoding.  An RPDO is decoded
with one ``struct.Struct`` precomputed for its whole mapping.  Mapped objects are whole
and byte-sized (BOOLEAN, INTEGER/UNSIGNED 8/16/32/64, REAL32/64) or dummy entries
(0x0002-0x0007, 0x0015, 0x001B): bit-sized mappings are refused as not mappable.

Remapping follows CiA 301 and Lely's slave checks: a mapping entry is written only while
the PDO is invalid (COB-ID bit 31) and its count (sub-index 0) is 0; the count is checked
against the entries (each existing 0x06020000/0x06090011, mappable 0x06040041, at most
64 bits 0x06040042); a valid PDO's COB-ID, inhibit time and SYNC start value stay as they
are (0x06090030).  Refused writes are not stored.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Callable
from dataclasses import dataclass

from canopen import ObjectDictionary
from canopen.objectdictionary import ODArray, ODRecord, ODVariable, datatypes
from canopen.sdo import SdoAbortedError

from ucom_tools.gateway.codes import COB_29BIT, COB_ID_MASK, COB_INVALID, SdoAbort, restricted

log = logging.getLogger("ucom.gateway")

#: struct format of each data type a PDO may carry
FORMATS: dict[int, str] = {
    datatypes.BOOLEAN: "?", datatypes.INTEGER8: "b", datatypes.UNSIGNED8: "B",
    datatypes.INTEGER16: "h", datatypes.UNSIGNED16: "H", datatypes.INTEGER32: "i",
    datatypes.UNSIGNED32: "I", datatypes.INTEGER64: "q", datatypes.UNSIGNED64: "Q",
    datatypes.REAL32: "f", datatypes.REAL64: "d",
}
#: dummy mapping entries (a data type's index, sub-index 0) and their lengths in bits
DUMMY_BITS: dict[int, int] = {
    datatypes.INTEGER8: 8, datatypes.INTEGER16: 16, datatypes.INTEGER32: 32,
    datatypes.UNSIGNED8: 8, datatypes.UNSIGNED16: 16, datatypes.UNSIGNED32: 32,
    datatypes.INTEGER64: 64, datatypes.UNSIGNED64: 64,
}
RPDO_COMM, RPDO_MAP, TPDO_COMM, TPDO_MAP = 0x1400, 0x1600, 0x1800, 0x1A00
MAX_PDOS = 512
MAX_ENTRIES = 8
#: transmission types: synchronous (acyclic 0, cyclic 1-240) and event-driven (254, 255)
SYNC_TYPES = range(0, 241)
EVENT_TYPES = (254, 255)


def find(od: ObjectDictionary, index: int, subindex: int) -> ODVariable:
    """The variable at ``index``:``subindex``, or the SDO abort a master would get."""
    if index not in od:
        raise SdoAbortedError(SdoAbort.NO_OBJECT)
    obj = od[index]
    if isinstance(obj, ODVariable):
        if subindex:
            raise SdoAbortedError(SdoAbort.NO_SUBINDEX)
        return obj
    if isinstance(obj, (ODRecord, ODArray)) and subindex in obj.subindices:
        var = obj[subindex]
        assert isinstance(var, ODVariable)
        return var
    raise SdoAbortedError(SdoAbort.NO_SUBINDEX)


@dataclass(frozen=True)
class MapEntry:
    """One mapped object: where it lives, its length and its struct format (``Nx`` for a
    dummy entry, which carries nothing)."""

    index: int
    subindex: int
    bits: int
    fmt: str
    dummy: bool
    low: int | float | None = None  # the object's LowLimit/HighLimit (an RPDO's value
    high: int | float | None = None  # outside them is not applied)


def check_entry(od: ObjectDictionary, entry: int, transmit: bool) -> MapEntry:
    """A mapping entry (``index << 16 | subindex << 8 | bits``) that may be mapped into a
    TPDO (``transmit``) or an RPDO, or the SDO abort that refuses it."""
    index, subindex, bits = entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF
    if index in DUMMY_BITS and subindex == 0:
        if bits != DUMMY_BITS[index]:
            raise SdoAbortedError(SdoAbort.NOT_MAPPABLE)
        return MapEntry(index, 0, bits, f"{bits // 8}x", True)
    obj = find(od, index, subindex)
    fmt = FORMATS.get(obj.data_type or -1)
    allowed = obj.readable if transmit else obj.writable
    if not obj.pdo_mappable or fmt is None or not allowed or bits != len(obj):
        raise SdoAbortedError(SdoAbort.NOT_MAPPABLE)
    return MapEntry(index, subindex, bits, fmt, False, obj.min, obj.max)


def check_mapping(od: ObjectDictionary, entries: list[int], transmit: bool,
                  ) -> tuple[MapEntry, ...]:
    """A whole mapping (the entries its count covers; zero entries are skipped), or the
    SDO abort that refuses it: too many or too long 0x06040042, an entry's own."""
    if len(entries) > MAX_ENTRIES:
        raise SdoAbortedError(SdoAbort.PDO_LENGTH)
    checked: list[MapEntry] = []
    bits = 0
    for entry in entries:
        if not entry:
            continue
        bits += entry & 0xFF
        if bits > 64:
            raise SdoAbortedError(SdoAbort.PDO_LENGTH)
        checked.append(check_entry(od, entry, transmit))
    return tuple(checked)


Store = dict[int, bytes]
Read = Callable[[int, int], int]


class Tpdo:
    """A valid TPDO: its frame's parts and when it is due."""

    __slots__ = ("cob_id", "count", "entries", "event_timer", "inhibit", "last",
                 "last_time", "number", "parts", "pending", "started", "sync_start",
                 "trans_type")

    def __init__(self, number: int, cob_id: int, trans_type: int, inhibit: float,
                 event_timer: float, sync_start: int, entries: tuple[MapEntry, ...],
                 parts: list[tuple[Store, int]]) -> None:
        self.number = number
        self.cob_id = cob_id
        self.trans_type = trans_type
        self.inhibit = inhibit  # seconds (0x1800 sub 3, 100 us units)
        self.event_timer = event_timer  # seconds (sub 5, ms); 0: none
        self.sync_start = sync_start  # sub 6
        self.entries = entries
        self.parts = parts
        self.count = 0  # SYNCs since the last transmission
        self.started = sync_start == 0
        self.last: bytes | None = None  # the data last sent
        self.last_time = float("-inf")  # when (time.monotonic)
        self.pending = False  # an event-driven TPDO with a change to send

    def build(self) -> bytes:
        """The frame's data from the current values."""
        return b"".join([store[sub] for store, sub in self.parts])

    def reset(self) -> None:
        """Counting from the start (entering OPERATIONAL, a new configuration)."""
        self.count = 0
        self.started = self.sync_start == 0
        self.last = None
        self.pending = self.trans_type in EVENT_TYPES


class Rpdo:
    """A valid RPDO: its decoder and where its values go."""

    __slots__ = ("cob_id", "entries", "length", "number", "pending", "slots", "struct",
                 "synchronous", "trans_type")

    def __init__(self, number: int, cob_id: int, trans_type: int,
                 entries: tuple[MapEntry, ...], stores: list[Store]) -> None:
        self.number = number
        self.cob_id = cob_id
        self.trans_type = trans_type
        self.synchronous = trans_type in SYNC_TYPES
        self.entries = entries
        self.struct = struct.Struct("<" + "".join(e.fmt for e in entries))
        self.length = self.struct.size
        # (value position in the unpacked tuple, byte offset, size, store, entry)
        slots: list[tuple[int, int, int, Store, MapEntry]] = []
        offset = position = 0
        for entry, store in zip(entries, stores, strict=True):
            size = entry.bits // 8
            if not entry.dummy:
                slots.append((position, offset, size, store, entry))
                position += 1
            offset += size
        self.slots = slots
        self.pending: bytes | None = None  # synchronous data waiting for the next SYNC


def _pdo_params(read: Read, comm: int, has: Callable[[int, int], bool],
                ) -> tuple[int, int, int, int, int]:
    """COB-ID, transmission type, inhibit time, event timer and SYNC start value of a
    communication record (0 where the record lacks the sub-index)."""
    def opt(sub: int) -> int:
        return read(comm, sub) if has(comm, sub) else 0
    return read(comm, 1), read(comm, 2), opt(3), opt(5), opt(6)


def _mapping(read: Read, mapping: int) -> list[int]:
    return [read(mapping, sub) for sub in range(1, read(mapping, 0) + 1)]


def compile_pdos(od: ObjectDictionary, read: Read, store: Callable[[int, int, int], Store],
                 node_id: int) -> tuple[list[Tpdo], list[Rpdo]]:
    """The node's valid TPDOs and RPDOs as its dictionary now holds them.  ``read`` gives
    a stored value, ``store(index, subindex, size)`` the dictionary's storage of an
    object (seeded with its value); a PDO whose stored configuration is invalid (from an
    EDS, say) is left out with a warning."""
    def has(index: int, sub: int) -> bool:
        try:
            find(od, index, sub)
        except SdoAbortedError:
            return False
        return True

    tpdos: list[Tpdo] = []
    rpdos: list[Rpdo] = []
    numbers = sorted({index & 0x1FF for index in od if RPDO_COMM <= index < TPDO_MAP + MAX_PDOS})
    for n in numbers:
        for comm, mapping, transmit in ((TPDO_COMM + n, TPDO_MAP + n, True),
                                        (RPDO_COMM + n, RPDO_MAP + n, False)):
            if comm not in od or mapping not in od:
                continue
            try:
                cob, trans, inhibit, event, start = _pdo_params(read, comm, has)
                if cob & COB_INVALID:
                    continue
                if cob & COB_29BIT or (cob & 0x1FFFFFFF) > COB_ID_MASK:
                    raise SdoAbortedError(SdoAbort.VALUE_RANGE)
                if trans not in SYNC_TYPES and trans not in EVENT_TYPES:
                    raise SdoAbortedError(SdoAbort.VALUE_RANGE)
                entries = check_mapping(od, _mapping(read, mapping), transmit)
            except SdoAbortedError as err:
                kind = "TPDO" if transmit else "RPDO"
                log.warning("node %d: %s %d left out: its stored configuration is invalid "
                            "(%s)", node_id, kind, n + 1, err)
                continue
            stores = [store(e.index, e.subindex, e.bits // 8) if not e.dummy
                      else {0: bytes(e.bits // 8)} for e in entries]
            if transmit:
                parts = [(s, e.subindex if not e.dummy else 0)
                         for s, e in zip(stores, entries, strict=True)]
                tpdos.append(Tpdo(n + 1, cob & COB_ID_MASK, trans, inhibit * 1e-4,
                                  event * 1e-3, start, entries, parts))
            else:
                rpdos.append(Rpdo(n + 1, cob & COB_ID_MASK, trans, entries, stores))
    return tpdos, rpdos


def check_write(od: ObjectDictionary, read: Read, index: int, subindex: int,
                value: int) -> None:
    """Refuse (raise the SDO abort) a write to a PDO record that CiA 301 does not allow
    in the PDO's present state; return for an allowed one.  ``read`` gives the values
    stored now (the write is not stored yet)."""
    if not RPDO_COMM <= index < TPDO_MAP + MAX_PDOS:
        return
    transmit = index >= TPDO_COMM
    base = index & ~0x1FF
    is_map = base in (RPDO_MAP, TPDO_MAP)
    comm = index - 0x200 if is_map else index
    if value == read(index, subindex):
        return  # (Lely: an unchanged value is always accepted)
    valid = not read(comm, 1) & COB_INVALID if comm in od else False
    if is_map:
        _check_map_write(od, read, index, subindex, value, valid, transmit)
    else:
        _check_comm_write(read, index, subindex, value, valid, transmit)


def _check_map_write(od: ObjectDictionary, read: Read, index: int, subindex: int,
                     value: int, valid: bool, transmit: bool) -> None:
    if subindex == 0:
        if valid:
            raise SdoAbortedError(SdoAbort.VALUE_RANGE)
        if value > MAX_ENTRIES:
            raise SdoAbortedError(SdoAbort.PDO_LENGTH)
        check_mapping(od, [read(index, s) for s in range(1, value + 1)], transmit)
        return
    if valid or read(index, 0):
        raise SdoAbortedError(SdoAbort.VALUE_RANGE)
    if value:
        check_entry(od, value, transmit)


def _check_comm_write(read: Read, index: int, subindex: int, value: int, valid: bool,
                      transmit: bool) -> None:
    if subindex == 1:
        now_valid = not value & COB_INVALID
        if valid and now_valid and (value ^ read(index, 1)) & 0x1FFFFFFF:
            raise SdoAbortedError(SdoAbort.VALUE_RANGE)  # a valid PDO keeps its COB-ID
        cob = value & 0x1FFFFFFF
        if value & COB_29BIT or cob > COB_ID_MASK or (now_valid and restricted(cob)):
            raise SdoAbortedError(SdoAbort.VALUE_RANGE)
    elif subindex == 2:
        if value not in SYNC_TYPES and value not in EVENT_TYPES:
            raise SdoAbortedError(SdoAbort.VALUE_RANGE)  # reserved, or RTR-only (none)
    elif subindex in (3, 6) and valid:
        raise SdoAbortedError(SdoAbort.VALUE_RANGE)  # inhibit, SYNC start: invalid first
