"""Length of a CAN data frame on the wire, in bits, bit stuffing included, and the order
in which frames win arbitration.

A standard (CAN 2.0A) data frame is SOF(1) ID(11) RTR(1) IDE(1) r0(1) DLC(4) DATA(8n)
CRC(15), all subject to bit stuffing, then CRC delimiter(1) ACK(2) EOF(7) and the
interframe space (3): ``47 + 8n`` bits plus stuff bits.  Without stuffing this gives
Tab. B.2 of the dissertation (8 bytes: 64 / 111 bits = 577 kbit/s at 1 Mbit/s).

An extended (CAN 2.0B) data frame is SOF(1) base ID(11) SRR(1) IDE(1) ID extension(18)
RTR(1) r1(1) r0(1) DLC(4) DATA(8n) CRC(15), stuffed, and the same tail: ``67 + 8n``
bits plus stuff bits.  The UCoM protocol uses standard frames only; extended ones are
accounted so that a bus that carries them (``ucom fleet serve``) keeps its timing.

CRC and stuffing are computed byte-wise with tables, so accounting every frame of a
flash transfer stays cheap.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Final

if TYPE_CHECKING:  # i64 annotations (see compiled.py)
    from mypy_extensions import i64

CRC15_POLY: Final = 0x4599
FIXED_TAIL_BITS: Final = 1 + 2 + 7 + 3  # CRC delimiter, ACK slot + delimiter, EOF, IFS
EXTENDED_HEADER_BITS: Final = 39
"""SOF to DLC of an extended frame: 1 + 11 + 1 + 1 + 18 + 1 + 1 + 1 + 4 bits."""
MAX_EXTENDED_ID: Final = 0x1FFFFFFF


def unstuffed_bits(dlc: int, extended: bool = False) -> int:
    """Frame length without stuff bits (the basis of Tab. B.2)."""
    return (67 if extended else 47) + 8 * dlc


def payload_rate(dlc: int, bitrate: int = 1_000_000) -> float:
    """Effective payload rate in bit/s of back-to-back frames with ``dlc`` bytes (Tab. B.2)."""
    return 8 * dlc * bitrate / unstuffed_bits(dlc) if dlc else 0.0


def _crc15_bitwise(value: int, nbits: int) -> int:
    crc = 0
    for i in range(nbits - 1, -1, -1):
        bit = (value >> i) & 1
        top = (crc >> 14) & 1
        crc = (crc << 1) & 0x7FFF
        if bit ^ top:
            crc ^= CRC15_POLY
    return crc


def _crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte << 7
        for _ in range(8):
            crc = ((crc << 1) ^ CRC15_POLY) if crc & 0x4000 else crc << 1
            crc &= 0x7FFF
        table.append(crc)
    return tuple(table)


_CRC_TABLE: Final = _crc_table()


def crc15(value: int, nbits: int) -> int:
    """CAN CRC-15 over the ``nbits`` low bits of ``value`` (most significant first)."""
    # Leading zero bits do not change a CRC with initial value 0: pad to whole bytes.
    nbytes = (nbits + 7) // 8
    crc = 0
    for byte in value.to_bytes(nbytes, "big"):
        crc = ((crc << 8) & 0x7FFF) ^ _CRC_TABLE[((crc >> 7) ^ byte) & 0xFF]
    return crc


# Stuffing state: polarity of the current run (0/1) and its length 1..4 -> index pol*4+len-1.
def _stuff_step(state: int, bit: int) -> tuple[int, int]:
    pol, run = divmod(state, 4)
    run += 1  # stored as length - 1
    if bit == pol:
        run += 1
        if run == 5:  # five equal bits: a stuff bit of the other polarity follows
            return (1 - pol) * 4, 1
        return pol * 4 + run - 1, 0
    return bit * 4, 0


def _stuff_table() -> tuple[tuple[int, int], ...]:
    table = []
    for state in range(8):
        for byte in range(256):
            s, added = state, 0
            for i in range(7, -1, -1):
                s, a = _stuff_step(s, (byte >> i) & 1)
                added += a
            table.append((s, added))
    return tuple(table)


_STUFF_TABLE: Final = _stuff_table()


def stuff_bits(region: int, nbits: int) -> int:
    """Number of stuff bits inserted into the ``nbits``-bit stuffed region."""
    state, added = 0, 0  # the SOF bit (dominant, 0) opens a run of length 1
    head = (nbits - 1) % 8
    for i in range(nbits - 2, nbits - 2 - head, -1):
        state, a = _stuff_step(state, (region >> i) & 1)
        added += a
    rest_bits = nbits - 1 - head
    for byte in (region & ((1 << rest_bits) - 1)).to_bytes(rest_bits // 8, "big"):
        state, a = _STUFF_TABLE[state * 256 + byte]
        added += a
    return added


def _frame_bits_general(arbitration_id: int, data: bytes, remote: bool) -> int:
    """:func:`frame_bits` computed over the whole frame (any frame it takes)."""
    dlc = len(data)
    header = (arbitration_id << 7) | ((1 if remote else 0) << 6) | dlc  # SOF=0, IDE=0, r0=0
    nbits = 19 + (0 if remote else 8 * dlc)
    value = (header << (8 * dlc)) | int.from_bytes(data, "big") if not remote else header
    region = (value << 15) | crc15(value, nbits)
    return nbits + 15 + stuff_bits(region, nbits + 15) + FIXED_TAIL_BITS


def _extended_frame_bits(arbitration_id: int, data: bytes, remote: bool) -> int:
    if not 0 <= arbitration_id <= MAX_EXTENDED_ID:
        raise ValueError(f"extended identifier 0x{arbitration_id:X}: more than 29 bits")
    dlc = len(data)
    base, low = arbitration_id >> 18, arbitration_id & 0x3FFFF
    # SOF=0, base ID, SRR=1, IDE=1, ID extension, RTR, r1=0, r0=0, DLC
    header = (base << 27) | (0b11 << 25) | (low << 7) | ((1 if remote else 0) << 6) | dlc
    nbits = EXTENDED_HEADER_BITS + (0 if remote else 8 * dlc)
    value = (header << (8 * dlc)) | int.from_bytes(data, "big") if not remote else header
    region = (value << 15) | crc15(value, nbits)
    return nbits + 15 + stuff_bits(region, nbits + 15) + FIXED_TAIL_BITS


_CRC_HIGH: Final = bytes(c >> 8 for c in _CRC_TABLE)
_CRC_LOW: Final = bytes(c & 0xFF for c in _CRC_TABLE)
""":data:`_CRC_TABLE` as two byte strings, the high and the low byte of each entry: a byte
string's item is a native integer where this module is compiled (a tuple's is an object
to unbox)."""
_STUFF_NEXT: Final = bytes(s for s, _added in _STUFF_TABLE)
_STUFF_ADDED: Final = bytes(added for _s, added in _STUFF_TABLE)
""":data:`_STUFF_TABLE` as two byte strings: the next stuffing state (0-7) and the stuff
bits the byte added, at ``state * 256 + byte``."""

_NO_HEAD: Final = -1
_HEADS: Final[list[int]] = [_NO_HEAD] * (0x800 << 4)
"""Per identifier and DLC (index ``id << 4 | dlc``) of a standard data frame, once it was
seen: the CRC register after the header (SOF to DLC, 19 bits, which :func:`crc15` pads to
3 bytes) in bits 0-14, the stuffing state after its 17 bits behind SOF (up to DLC bit 1)
in bits 15-17 and the stuff bits they needed above; :data:`_NO_HEAD` before."""


def _head(arbitration_id: int, dlc: int) -> int:
    header = (arbitration_id << 7) | dlc  # 18 bits: ID, RTR=0, IDE=0, r0=0, DLC
    crc = 0
    for byte in header.to_bytes(3, "big"):
        crc = ((crc << 8) & 0x7FFF) ^ _CRC_TABLE[((crc >> 7) ^ byte) & 0xFF]
    state, added = 0, 0  # the SOF bit (dominant, 0) opens a run of length 1
    for i in range(17, 0, -1):
        state, a = _stuff_step(state, (header >> i) & 1)
        added += a
    return crc | state << 15 | added << 18


def frame_bits(arbitration_id: int, data: bytes, remote: bool = False,
               extended: bool = False) -> int:
    """Bits a data (or remote) frame occupies on the bus, IFS included; a standard frame
    (11-bit identifier) unless ``extended`` (29-bit).

    A data frame's header part (CRC register and stuffing state after SOF to DLC bit 1)
    is computed once per identifier and DLC (:data:`_HEADS`); the rest walks DLC bit 0,
    the data and the CRC byte by byte with tables of bytes: the same bits in the same
    order as over the whole frame (:func:`_frame_bits_general`, which remote frames take;
    ``tests/test_canbits.py`` holds both to a bit-by-bit reference).  Compiled, every
    step is arithmetic on 64-bit integers (``i64``: no tagged integers, no objects); a
    cache of whole frames cost more than it saved."""
    if extended:
        return _extended_frame_bits(arbitration_id, data, remote)
    dlc = len(data)
    if remote or dlc > 8 or not 0 <= arbitration_id <= 0x7FF:
        return _frame_bits_general(arbitration_id, data, remote)
    key = arbitration_id << 4 | dlc
    head: i64 = _HEADS[key]
    if head == _NO_HEAD:
        head = _HEADS[key] = _head(arbitration_id, dlc)
    crc: i64 = head & 0x7FFF
    state: i64 = (head >> 7) & 0x700  # its index into the stuffing tables (state * 256)
    added: i64 = head >> 18
    high, low = _CRC_HIGH, _CRC_LOW
    nxt, add = _STUFF_NEXT, _STUFF_ADDED
    # the bits after the head, DLC bit 0, the data and the CRC, stuffed a byte at a time:
    # each byte to stuff is the previous data bit (``carry``; first DLC bit 0) and the
    # data byte's 7 high bits; the last two bytes the last data bit and the CRC
    carry: i64 = dlc & 1
    n: i64 = dlc
    i: i64 = 0
    while i < n:
        byte: i64 = data[i]
        k: i64 = ((crc >> 7) ^ byte) & 0xFF
        crc = ((crc << 8) & 0x7FFF) ^ (high[k] << 8 | low[k])
        k = state + (carry << 7 | byte >> 1)
        state = nxt[k] << 8
        added += add[k]
        carry = byte & 1
        i += 1
    last: i64 = carry << 15 | crc
    k = state + (last >> 8)
    added += add[k] + add[(nxt[k] << 8) + (last & 0xFF)]
    return 34 + 8 * n + added + FIXED_TAIL_BITS


def worst_frame_bits(dlc: int, extended: bool = False) -> int:
    """Longest a data frame of ``dlc`` bytes can be: every stuff bit that the 34 + 8n
    bits (extended: 54 + 8n) from SOF to the CRC can need (one per 4 bits after the
    first 5)."""
    stuffed = (54 if extended else 34) + 8 * dlc
    return unstuffed_bits(dlc, extended) + (stuffed - 1) // 4


def arbitration_key(arbitration_id: int, extended: bool = False) -> int:
    """Rank of a data frame in arbitration, lower wins: its arbitration field as the bus
    sees it, bit by bit.  An extended frame's base ID (its 11 high bits) meets a standard
    frame's identifier; after them the standard frame sends RTR (dominant, 0) where the
    extended one sends SRR (recessive, 1), so the standard frame wins against every
    extended frame with the same base ID and loses against those with a lower one."""
    if not extended:
        return arbitration_id << 19
    return ((arbitration_id >> 18) << 19) | (1 << 18) | (arbitration_id & 0x3FFFF)
