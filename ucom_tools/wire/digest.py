"""The description's digest (``man/ucom-protocol.7``, RUN TIME, Messages 22 and 23): one
frame that says which edge records a program has, so that a host that has read them once
can tell whether a board still runs the same program without reading them again (a lost
board that rejoins: RUN TIME, Faults, Rejoin, step 2).

The digest is CRC-32 (IEEE 802.3, as :func:`zlib.crc32` computes it) over every edge's
record bytes exactly as MCA DumpIO Descr sends them: CI, then SO, then PAR, each kind in
index order, each record whole.  A program carries it as a constant of its record table.

- :class:`DigestRequest`, MCA DumpIO Descr Request with DLC 1: [0] = 3, a kind no edge has;
- :class:`DescrDigest`, its answer, one MCA DumpIO Descr frame, DLC 6: [0] = 3 << 6 | last
  (0xE0: kind 3, the last and only segment 0), [1] = 0, [2..5] the digest, big endian.

A program that does not know the request answers it with Error BAD_LENGTH (or not at all);
the host then reads the records (:meth:`ucom_tools.protocol.mca.McaClient.digest` gives
None).  Both messages go through :func:`ucom_tools.wire.mca.encode`/``decode`` like the
other run-time messages.
"""

from __future__ import annotations

import zlib
from collections.abc import Iterable
from dataclasses import dataclass
from typing import ClassVar, Final, Protocol

from ucom_tools.errors import FrameError
from ucom_tools.wire.fields import check_length, check_range
from ucom_tools.wire.ids import Function

DIGEST_KIND: Final = 3
"""The kind field (2 bits) that names the digest: no edge kind is 3 (CI 0, SO 1, PAR 2)."""
DIGEST_HEAD: Final = DIGEST_KIND << 6 | 0x20
"""Byte 0 of the answer: kind 3, the last segment, segment 0 (0xE0)."""
DIGEST_DLC: Final = 6


class Record(Protocol):
    """An edge record as MCA DumpIO Descr sends it (:class:`ucom_tools.wire.mca.EdgeRecord`)."""

    def encode(self) -> bytes: ...


def digest_of(records: Iterable[Record]) -> int:
    """CRC-32 over the records' bytes, in the order given: every CI record, then every SO
    record, then every PAR record, each kind in index order (what the page specifies)."""
    crc = 0
    for record in records:
        crc = zlib.crc32(record.encode(), crc)
    return crc


@dataclass(frozen=True, slots=True)
class DigestRequest:
    """MCA DumpIO Descr Request (22) with DLC 1, [0] = 3: the description's digest."""

    FUNCTION: ClassVar[Function] = Function.MCA_DUMPIO_DESCR_REQUEST

    def encode(self) -> bytes:
        return bytes((DIGEST_KIND,))

    @classmethod
    def decode(cls, data: bytes) -> DigestRequest:
        check_length("MCA DumpIO Descr Request", data, 1)
        if data[0] != DIGEST_KIND:
            raise FrameError("DumpIO kind", f"reserved value 0x{data[0]:02X} (DLC 1 asks "
                             f"for the digest: {DIGEST_KIND})")
        return cls()


@dataclass(frozen=True, slots=True)
class DescrDigest:
    """MCA DumpIO Descr (23) answering :class:`DigestRequest`: the description's digest."""

    FUNCTION: ClassVar[Function] = Function.MCA_DUMPIO_DESCR
    value: int

    def __post_init__(self) -> None:
        check_range("description digest", self.value, 0, 0xFFFFFFFF)

    def encode(self) -> bytes:
        return bytes((DIGEST_HEAD, 0)) + self.value.to_bytes(4, "big")

    @classmethod
    def decode(cls, data: bytes) -> DescrDigest:
        check_length("MCA DumpIO Descr (digest)", data, DIGEST_DLC)
        if data[0] != DIGEST_HEAD or data[1] != 0:
            raise FrameError("DumpIO digest header",
                             f"expected E0 00, got {data[0]:02X} {data[1]:02X}")
        return cls(int.from_bytes(data[2:6], "big"))
