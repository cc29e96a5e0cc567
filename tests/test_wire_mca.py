"""Run-time (MCA) messages: byte-exact examples (the ones man/ucom-protocol.7 prints) and
round trips of every message and value encoding."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from ucom_tools.edgelists import armar3, lauron4
from ucom_tools.errors import FrameError
from ucom_tools.wire import mca
from ucom_tools.wire.ids import ALL, Function, seq

u8 = st.integers(0, 0xFF)
kinds = st.sampled_from(mca.Kind)
maps = st.integers(1, mca.MAX_MAP)

MESSAGES = st.one_of(
    st.builds(mca.EdgeWrite, st.sampled_from([mca.Kind.CI, mca.Kind.PAR]),
              st.integers(0, 0xFE), st.binary(min_size=2, max_size=7)),
    st.builds(mca.McaReady, st.sampled_from(mca.RunState), st.integers(0, 31),
              st.binary(min_size=2, max_size=2), u8, u8, u8, u8),
    st.builds(mca.McaStart, st.sampled_from(mca.StartOp)),
    st.builds(mca.DescrRequest), st.builds(mca.DescrRequest, kinds, u8),
    st.builds(mca.DescrSegment, kinds, u8, st.integers(0, 31), st.booleans(),
              st.binary(min_size=1, max_size=6)),
    st.builds(mca.DumpRequest, kinds, st.integers(0, 0xFE), st.integers(1, 0xFF)),
    st.builds(mca.DumpValues, kinds, st.integers(0, 0xFE), st.binary(min_size=2, max_size=6)),
    st.builds(mca.AdminData.alive, st.integers(mca.ALIVE_MIN_MS, mca.ALIVE_MAX_MS)),
    st.builds(mca.AdminData.so_map, maps, st.integers(0, 0xFFFF),
              st.lists(u8, min_size=1, max_size=4)),
    st.builds(mca.AdminData.ci_map, maps, st.lists(u8, min_size=4, max_size=4)),
    st.builds(mca.AdminData, st.just(mca.AdminOp.CLEAR_MAPS)),
    st.builds(mca.Alive),
    st.builds(mca.MapFrame, st.sampled_from([Function.MCA_CONTROLLER_INPUT,
                                             Function.MCA_SENSOR_OUTPUT]),
              maps, st.binary(min_size=2, max_size=8)),
)


@given(MESSAGES, st.integers(0, 31))
def test_every_run_time_message_round_trips(msg: mca.McaMessage, number: int) -> None:
    if isinstance(msg, mca.MapFrame):
        arb, data = mca.encode(msg)
        assert arb >> 5 & 1 == 1 and arb & 0x1F == msg.map_no
    else:
        arb, data = mca.encode(msg, seq(number))
    assert len(data) <= 8
    address, got = mca.decode(arb, data)
    assert got == msg
    assert (address is None) == isinstance(msg, mca.MapFrame)


# The examples man/ucom-protocol.7 prints, RUN TIME.
@pytest.mark.parametrize("msg, address, ident, payload", [
    (mca.McaStart(mca.StartOp.START), seq(3), 0x543, "01"),
    (mca.McaReady(mca.RunState.STOPPED, 20, b"\0\0", 13, 20, 38), seq(3), 0x503,
     "00 14 0000 0d 14 26 00"),
    (mca.AdminData.alive(50), seq(3), 0x643, "01 0032"),
    (mca.AdminData.so_map(1, 1, [0, 2, 14, 15]), seq(3), 0x643, "02 01 0001 00 02 0e 0f"),
    (mca.AdminData.ci_map(1, [0xFF, 0xFF, 3, 4]), seq(3), 0x643, "03 01 ff ff 03 04"),
    (mca.EdgeWrite(mca.Kind.PAR, 6, (500).to_bytes(4, "big")), seq(3), 0x3C3,
     "06 000001f4"),
    (mca.Alive(), ALL, 0x680, ""),
    (mca.MapFrame(Function.MCA_SENSOR_OUTPUT, 1, bytes.fromhex("0064ff9c00000001")), None,
     0x3A1, "5531aac955555554"),  # 100, -100, 0, 1: each byte XOR 0x55
    (mca.MapFrame(Function.MCA_CONTROLLER_INPUT, 2, bytes.fromhex("03e8fc18")), None, 0x362,
     "56bda94d"),
    (mca.DescrSegment(mca.Kind.PAR, 3, 0, False, bytes.fromhex("0200000000000000")[:6]),
     seq(3), 0x5C3, "80 03 020000000000"),
])
def test_byte_layouts(msg: mca.McaMessage, address, ident: int, payload: str) -> None:
    assert mca.encode(msg, address) == (ident, bytes.fromhex(payload.replace(" ", "")))


@pytest.mark.parametrize("spec", [armar3.SPEC, lauron4.SPEC])
def test_every_edge_description_round_trips_through_its_segments(spec) -> None:
    for e in spec.edges:
        record = mca.EdgeRecord(e.width, e.signed, e.exponent, e.minimum, e.maximum, e.name,
                                e.unit)
        segments = record.segments(mca.Kind(e.kind), 0)
        assert segments[-1].last and not any(s.last for s in segments[:-1])
        assert [s.segment for s in segments] == list(range(len(segments)))
        raw = b"".join(mca.DescrSegment.decode(s.encode()).data for s in segments)
        assert mca.EdgeRecord.decode(raw) == record


def test_the_longest_b5_name_needs_several_segments() -> None:
    e = next(e for e in armar3.SPEC.edges if e.name == "Set Joint Moving Direction(BitMask)")
    assert len(e.name) == 35
    record = mca.EdgeRecord(e.width, e.signed, e.exponent, e.minimum, e.maximum, e.name, "")
    assert len(record.segments(mca.Kind.PAR, 3)) == 8  # 10 + 36 + 1 bytes, 6 per frame


@given(st.data())
def test_values_pack_and_unpack_exactly(data: st.DataObject) -> None:
    specs = data.draw(st.lists(st.tuples(st.sampled_from([2, 4]), st.booleans()),
                               min_size=1, max_size=4))
    values = [data.draw(st.integers(-(1 << 8 * w - 1), (1 << 8 * w - 1) - 1) if s
                        else st.integers(0, (1 << 8 * w) - 1)) for w, s in specs]
    assert mca.unpack_values(specs, mca.pack_values(specs, values)) == values


def test_every_b5_default_travels_exactly() -> None:
    """0.0005, -12725, 0x444, 14000: the tree's text -> raw -> value, exactly."""
    from decimal import Decimal

    from ucom_tools.config.attrtree import load

    board = load("attribute_trees/armar3/head_right.tree").boards[0]
    for edge in board.edges:
        if edge.default is None:
            continue
        spec = armar3.SPEC.edges[edge.index]
        raw = spec.raw(edge.default.text)
        expected = Decimal(int(edge.default.text, 16)) if "0x" in edge.default.text \
            else Decimal(edge.default.text)
        assert spec.value(raw) == expected
    with pytest.raises(ValueError, match="decimal places"):
        armar3.SPEC.edges[39].raw("0.00000001")  # MotorA I: six decimals
    with pytest.raises(ValueError, match="outside"):
        armar3.SPEC.edges[34].raw("20000")  # Max PWM: 0..16000


@pytest.mark.parametrize("ident, data, field", [
    (0x3C3, b"\x06\x00", "Parameter payload length"),
    (0x543, b"\x07", "MCA Start op"),
    (0x643, b"\x02\x00\x00\x01\x00", "Admin Data map"),
    (0x643, b"\x09", "Admin Data op"),
    (0x3A1 & ~0x20, b"\x00\x00", "identifier type"),
    (0x580 | 0x20 | 3, b"", "identifier type"),
])
def test_bad_frames_name_the_field(ident: int, data: bytes, field: str) -> None:
    with pytest.raises(FrameError, match=field):
        mca.decode(ident, data)
