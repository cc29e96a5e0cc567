"""A CAN data frame counted bit by bit, the slow way the tests hold ucom_tools.wire.canbits
against: the fields, CRC-15/CAN (polynomial 0x4599) over them, bit stuffing after five
equal bits, and the 13 fixed tail bits (CRC delimiter, ACK, EOF, IFS)."""

from __future__ import annotations


def frame_bits(header: list[int], data: bytes) -> int:
    """Bits on the bus of a data frame whose bits from SOF to DLC are ``header``."""
    bits = list(header)
    for byte in data:
        bits += [(byte >> i) & 1 for i in range(7, -1, -1)]
    crc = 0
    for b in bits:
        top = (crc >> 14) & 1
        crc = (crc << 1) & 0x7FFF
        if b ^ top:
            crc ^= 0x4599
    bits += [(crc >> i) & 1 for i in range(14, -1, -1)]
    stuffed, run, last = 0, 0, None
    for b in bits:
        run = run + 1 if b == last else 1
        last = b
        if run == 5:
            stuffed += 1
            last, run = 1 - b, 1
    return len(bits) + stuffed + 13


def standard(arb: int, data: bytes) -> int:
    """SOF, 11-bit identifier, RTR IDE r0, DLC, then the data."""
    header = [0] + [(arb >> i) & 1 for i in range(10, -1, -1)] + [0, 0, 0]
    return frame_bits(header + [(len(data) >> i) & 1 for i in range(3, -1, -1)], data)


def extended(arb: int, data: bytes) -> int:
    """SOF, base identifier, SRR IDE, identifier extension, RTR r1 r0, DLC, the data."""
    base, low = arb >> 18, arb & 0x3FFFF
    header = [0] + [(base >> i) & 1 for i in range(10, -1, -1)] + [1, 1]
    header += [(low >> i) & 1 for i in range(17, -1, -1)] + [0, 0, 0]
    return frame_bits(header + [(len(data) >> i) & 1 for i in range(3, -1, -1)], data)
