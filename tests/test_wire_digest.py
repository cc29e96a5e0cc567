"""The description's digest (``ucom_tools.wire.digest``): its request and answer byte for
byte (the frames man/ucom-protocol.7 prints), round trips through ``wire.mca``, what is
refused, and the digest itself: CRC-32 over the records as DumpIO Descr sends them."""

from __future__ import annotations

import zlib

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st

from ucom_tools.edgelists import armar3, lauron4
from ucom_tools.edgelists.model import EdgeKind, ProgramSpec
from ucom_tools.errors import FrameError
from ucom_tools.trace.decode import decode_frames
from ucom_tools.wire import mca
from ucom_tools.wire.digest import DIGEST_HEAD, DescrDigest, DigestRequest, digest_of
from ucom_tools.wire.ids import Function, seq


def records(spec: ProgramSpec) -> list[mca.EdgeRecord]:
    """A program's records, CI, then SO, then PAR, each kind in index order."""
    return [mca.EdgeRecord(e.width, e.signed, e.exponent, e.minimum, e.maximum, e.name,
                           e.unit) for k in EdgeKind for e in spec.of(k)]


def test_the_pages_example_frames() -> None:
    assert mca.encode(DigestRequest(), seq(3)) == (0x583, b"\x03")
    assert mca.encode(DescrDigest(0x0E506B11), seq(3)) == (0x5C3, bytes.fromhex("E0000E506B11"))
    assert DIGEST_HEAD == 3 << 6 | 1 << 5 | 0 == 0xE0


@given(st.integers(0, 0xFFFFFFFF), st.integers(1, 31))
def test_the_answer_round_trips(value: int, board: int) -> None:
    arb, data = mca.encode(DescrDigest(value), seq(board))
    assert len(data) == 6 and data[:2] == b"\xe0\x00"
    assert mca.decode(arb, data) == (seq(board), DescrDigest(value))


def test_the_request_round_trips_beside_the_others() -> None:
    for msg in (DigestRequest(), mca.DescrRequest(), mca.DescrRequest(mca.Kind.PAR, 3)):
        arb, data = mca.encode(msg, seq(2))
        assert mca.decode(arb, data) == (seq(2), msg)


@pytest.mark.parametrize("function, data, field", [
    (Function.MCA_DUMPIO_DESCR_REQUEST, b"\x02", "DumpIO kind"),  # a kind, but DLC 1
    (Function.MCA_DUMPIO_DESCR_REQUEST, b"\x00", "DumpIO kind"),
    (Function.MCA_DUMPIO_DESCR_REQUEST, b"\x03\x00\x00", "payload length"),
    (Function.MCA_DUMPIO_DESCR, bytes.fromhex("E0000E506B"), "payload length"),
    (Function.MCA_DUMPIO_DESCR, bytes.fromhex("E0000E506B1100"), "payload length"),
    (Function.MCA_DUMPIO_DESCR, bytes.fromhex("E1000E506B11"), "digest header"),
    (Function.MCA_DUMPIO_DESCR, bytes.fromhex("C0000E506B11"), "digest header"),
    (Function.MCA_DUMPIO_DESCR, bytes.fromhex("E0010E506B11"), "digest header"),
])
def test_a_malformed_digest_frame_names_its_field(function: Function, data: bytes,
                                                  field: str) -> None:
    with pytest.raises(FrameError) as info:
        mca.decode(function << 6 | 3, data)
    assert field in info.value.field


def test_a_value_past_32_bits_is_refused() -> None:
    with pytest.raises(FrameError, match="description digest"):
        DescrDigest(1 << 32)


@pytest.mark.parametrize("spec", [armar3.SPEC, lauron4.SPEC], ids=["armar3", "lauron4"])
def test_the_digest_is_crc32_over_the_records_as_described(spec: ProgramSpec) -> None:
    recs = records(spec)
    whole = b"".join(r.encode() for r in recs)
    assert digest_of(recs) == zlib.crc32(whole)
    # the bytes DumpIO Descr sends, segment by segment, CI, then SO, then PAR
    where = [(k, i) for k in mca.Kind for i in range(len(spec.of(EdgeKind(k))))]
    sent = b"".join(seg.data for r, (k, i) in zip(recs, where, strict=True)
                    for seg in r.segments(k, i))
    assert sent == whole
    assert digest_of([]) == 0


def test_one_changed_record_changes_the_digest() -> None:
    recs = records(armar3.SPEC)
    base = digest_of(recs)
    assert base == 0x0E506B11  # the page's example, board 3 of CAN0
    par3 = 13 + 20 + 3
    assert recs[par3].name == "Set Joint Moving Direction(BitMask)"
    renamed = [*recs[:par3], mca.EdgeRecord(2, False, 0, 0, 7, "Set Joint Moving", ""),
               *recs[par3 + 1:]]
    assert digest_of(renamed) != base
    swapped = recs[:1] + recs[2:3] + recs[1:2] + recs[3:]  # the same records, reordered
    assert digest_of(swapped) != base


def test_a_trace_of_the_digest_decodes_to_its_request_and_answer() -> None:
    frames = [can.Message(timestamp=1.0 + 0.0002 * i, arbitration_id=arb, data=data,
                          is_extended_id=False, channel="CAN0")
              for i, (arb, data) in enumerate((mca.encode(DigestRequest(), seq(3)),
                                               mca.encode(DescrDigest(0x0E506B11), seq(3))))]
    (bus,) = decode_frames(frames).buses
    assert [(x.function, x.text) for x in bus.messages] == [
        ("MCA DumpIO Descr Request", "the description's digest"),
        ("MCA DumpIO Descr", "digest 0x0E506B11")]
    assert "violations: none" in str(decode_frames(frames))
