"""Every bootloader-level message: byte layouts, round trips, and errors naming the field."""

from __future__ import annotations

from datetime import UTC, datetime

import pytest
from hypothesis import given
from hypothesis import strategies as st

from ucom_tools.errors import FrameError
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import (
    BoardState,
    ErrorCode,
    InitAckKind,
    InitOp,
    ReadyReason,
    ReportChannel,
    ResultStatus,
    Space,
    StatusOp,
    Target,
)
from ucom_tools.wire.descriptor import ImageDescriptor
from ucom_tools.wire.ids import ALL, Address, Direction, Function, IdType, encode_id, seq
from ucom_tools.wire.info import BoardInfo

u8, u16, u32 = st.integers(0, 0xFF), st.integers(0, 0xFFFF), st.integers(0, 0xFFFFFFFF)
numbers = st.integers(0, 31)
addresses = st.builds(Address, st.sampled_from(IdType), numbers)


def _set_status() -> st.SearchStrategy[m.SetStatus]:
    return st.one_of(
        st.builds(m.SetStatus, st.just(StatusOp.SEQ_ID), st.integers(1, 31)),
        st.builds(m.SetStatus, st.sampled_from([o for o in StatusOp if o is not StatusOp.SEQ_ID]),
                  st.integers(0, 1)))


def _init_request() -> st.SearchStrategy[m.InitRequest]:
    return st.one_of(
        st.builds(m.InitRequest, st.just(InitOp.NEXT), st.integers(2, 31)),
        st.builds(m.InitRequest, st.just(InitOp.REJOIN), st.integers(1, 31),
                  st.integers(0, 0xFFFFFFFF)),
        st.builds(m.InitRequest, st.sampled_from([o for o in InitOp
                                                  if o not in (InitOp.NEXT, InitOp.REJOIN)])))


MESSAGES = st.one_of(
    st.builds(m.Reset), st.builds(m.XReset), st.builds(m.InfoRequest),
    _set_status(), _init_request(),
    st.builds(m.ReportRequest, st.sampled_from(ReportChannel), st.sampled_from(Space), u16, u16),
    st.builds(m.Start, st.sampled_from(Target)),
    st.builds(m.ProgramBegin, st.sampled_from(Target), st.integers(1, 256), u16),
    st.builds(m.ProgramMeta, st.integers(0, 9), st.binary(min_size=4, max_size=4)),
    st.builds(m.ProgramErase, st.sampled_from(Space), u8, st.integers(1, 256)),
    st.builds(m.ProgramPrepare, u16), st.builds(m.ProgramEnd), st.builds(m.ProgramAbort),
    st.builds(m.ProgramBlock, st.sampled_from(Space), u16, st.integers(1, 64), u8, u16),
    st.builds(m.ProgramData, st.binary(min_size=8, max_size=8), st.integers(0, 63)),
    st.builds(m.Error, st.sampled_from(ErrorCode), u8, u32),
    st.builds(m.InitAck, st.sampled_from(InitAckKind), numbers, numbers, u8, u32),
    st.builds(m.ProgramResult, st.sampled_from(ResultStatus), st.integers(0, 64), u32),
    st.builds(m.ProgramMissing, u16, st.integers(1, 0xFFFF)),
    st.integers(0, 63).flatmap(lambda first: st.builds(
        m.ProgramPartial, u16, st.just(first), st.integers(1, 64 - first))),
    st.builds(m.InfoFrame, st.integers(0, 9), st.binary(min_size=7, max_size=7)),
    st.builds(m.Ready, st.sampled_from(ReadyReason), st.sampled_from(BoardState), u16, u32),
    st.builds(m.StatusReport, st.sampled_from(BoardState), st.integers(0, 15),
              st.integers(0, 15), u8, u8, numbers, u16),
    st.builds(m.MemoryReport, u16, st.lists(u16, min_size=1, max_size=3).map(tuple)),
    st.builds(m.TextReport, st.integers(0, 127), st.booleans(), st.binary(max_size=7)),
    st.builds(m.AppReport, st.binary(max_size=8)),
)


@given(MESSAGES, addresses)
def test_every_message_round_trips(msg: m.BootMessage, address: Address) -> None:
    arb, data = m.encode(msg, address)
    assert len(data) <= 8
    got_address, got = m.decode(arb, data)
    assert got == msg
    if isinstance(msg, m.ProgramData):  # no address: bits 5-0 are the slot
        assert arb == 0x2C0 | msg.slot
    else:
        assert got_address == address


@given(MESSAGES)
def test_direction_check_rejects_the_other_side(msg: m.BootMessage) -> None:
    arb, data = m.encode(msg, seq(1))
    wrong = (Direction.BOARD_TO_HOST if msg.FUNCTION.direction is Direction.HOST_TO_BOARD
             else Direction.HOST_TO_BOARD)
    with pytest.raises(FrameError, match="function"):
        m.decode(arb, data, sender=wrong)


# Byte-exact examples; the same vectors are printed in man/ucom-protocol.7.
@pytest.mark.parametrize("msg, address, ident, payload", [
    (m.Reset(), ALL, 0x000, ""),
    (m.InitRequest(InitOp.NEXT, 2), ALL, 0x280, "0202"),
    (m.InitRequest(InitOp.REJOIN, 3, 0x12345678), ALL, 0x280, "060312345678"),
    (m.SetStatus(StatusOp.PROG_ENABLE, 1), seq(3), 0x1C3, "0101"),
    (m.Start(Target.FLASH), seq(2), 0x302, "00"),
    (m.ProgramBlock(Space.P, 0x0100, 64, 1, 0x1234), ALL, 0x2C0, "05 40 0100 01 1234"),
    (m.ProgramBlock(Space.X, 0x1000, 3, 130, 0xBEEF), ALL, 0x2C0, "05 83 1000 82 beef"),
    (m.InitAck(InitAckKind.ASSIGNED, 1, 0, 0x10, 0x12345678), seq(1), 0x0C1,
     "0001001012345678"),
    (m.Ready(ReadyReason.ERASED, BoardState.RECEIVING, 128, 90), seq(1), 0x181,
     "010200800000005a"),
    (m.ProgramResult(ResultStatus.VERIFIED, 0, 0xCAFEBABE), seq(1), 0x101, "000000 00cafebabe"),
    (m.ProgramResult(ResultStatus.MISSING, 2, 0), seq(1), 0x101, "000100 0200000000"),
    (m.ProgramPartial(5, 17, 2), seq(1), 0x101, "02 0005 11 02"),
    (m.ProgramData(bytes(range(8)), 9), ALL, 0x2C9, "0001020304050607"),
    (m.ProgramPrepare(24), ALL, 0x2C0, "04 0018"),
    (m.Error(ErrorCode.PROTECTED_ADDRESS, 11, 0x8000), seq(4), 0x084, "050b00008000"),
])
def test_byte_layouts(msg: m.BootMessage, address: Address, ident: int, payload: str) -> None:
    assert m.encode(msg, address) == (ident, bytes.fromhex(payload.replace(" ", "")))


@pytest.mark.parametrize("function, data, field", [
    (Function.RESET, b"\x00", "Reset payload length"),
    (Function.SET_STATUS, b"\x09\x01", "SetStatus op"),
    (Function.SET_STATUS, b"\x01\x05", "SetStatus value"),
    (Function.INIT_REQUEST, b"\x02\x01", "Init Request number"),
    (Function.INIT_REQUEST, b"\x06\x03", "Init Request REJOIN payload length"),
    (Function.INIT_REQUEST, b"\x06\x00\x00\x00\x00\x01", "Init Request number"),
    (Function.START, b"\x07", "Start target"),
    (Function.PROGRAM, b"", "Program payload length"),
    (Function.PROGRAM, b"\x08", "Program op"),
    (Function.PROGRAM, b"\x05\x00\x01", "Program Block payload length"),
    (Function.PROGRAM, b"\x05\x41\x00\x00\x00\x00\x00", "Program Block frames"),
    (Function.PROGRAM, b"\x05\x00\x00\x00\x41\x00\x00", "Program Block frames"),
    (Function.READY, b"\x09\x00\x00\x00\x00\x00\x00\x00", "Ready reason"),
    (Function.ERROR, b"\x01", "Error payload length"),
    (Function.INFO, b"\x0a" + bytes(7), "Info index"),
])
def test_bad_frames_name_the_field(function: Function, data: bytes, field: str) -> None:
    with pytest.raises(FrameError) as info:
        m.decode(encode_id(function, seq(1)), data)
    assert info.value.field == field


def test_mca_and_unassigned_functions_are_not_bootloader_messages() -> None:
    with pytest.raises(FrameError, match="run-time"):
        m.decode(encode_id(Function.MCA_CONTROLLER_INPUT, seq(1)), b"")
    with pytest.raises(FrameError, match="unassigned"):
        m.decode(encode_id(30, seq(1)), b"")


def test_text_reports_split_and_join() -> None:
    frames = m.text_reports("program 'armar3.fl.S' running")
    assert [f.last for f in frames] == [False] * (len(frames) - 1) + [True]
    assert b"".join(f.text for f in frames).decode() == "program 'armar3.fl.S' running"


@given(st.builds(
    BoardInfo, st.sampled_from(BoardState), st.booleans(), st.booleans(), st.booleans(),
    st.booleans(), numbers, numbers, st.tuples(u8, u8), u32, st.integers(0, 0xFFFFFF),
    st.one_of(st.none(), st.datetimes(min_value=datetime(2000, 1, 1), max_value=datetime(
        2099, 12, 31)).map(lambda d: d.replace(microsecond=0, tzinfo=UTC))),
    u32, u16, st.sampled_from(Target),
    st.text(alphabet=st.characters(min_codepoint=32, max_codepoint=126), max_size=28),
    u16.filter(lambda r: not r & 0x10), u16.map(lambda r: r & 0xFFF0), st.integers(0, 15),
    st.booleans(),
    st.one_of(st.none(), st.builds(ImageDescriptor, st.integers(0, 15), st.integers(0, 127),
                                   st.integers(0, 63), st.integers(0, 63),
                                   st.tuples(u8, u8), st.just(""))),
    st.booleans()))
def test_info_record_round_trips(info: BoardInfo) -> None:
    frames = info.to_frames()
    assert len(frames) == 10
    assert BoardInfo.from_frames({f.index: f.body for f in frames}) == info


def test_info_needs_all_frames() -> None:
    with pytest.raises(FrameError, match="Info index"):
        BoardInfo.from_frames({0: bytes(7)})
