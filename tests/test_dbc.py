"""``ucom dbc``: the DBC export loads with cantools and decodes real frames (made by the
project's codecs, and recorded from the virtual fleet) to the right signal values."""

from __future__ import annotations

import builtins
import os
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import click
import pytest
from click.testing import CliRunner, Result

from ucom_tools.cli import dbc as dbc_cli
from ucom_tools.cli.main import UcomGroup, cli
from ucom_tools.errors import InputError
from ucom_tools.trace import dbc as dbc_ops
from ucom_tools.wire import mca
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import (
    BoardState,
    InitAckKind,
    ReadyReason,
    ResultStatus,
    Space,
    StatusOp,
    Target,
)
from ucom_tools.wire.descriptor import ImageDescriptor
from ucom_tools.wire.fpga import FpgaVersion
from ucom_tools.wire.ids import ALL, fixed, seq
from ucom_tools.wire.info import BoardInfo

cantools = pytest.importorskip("cantools")


def group() -> click.Group:
    g = UcomGroup("ucom", commands=dict(cli.commands), params=cli.params,
                  callback=cli.callback)
    g.add_command(dbc_cli.dbc)
    return g


def ucom(*args: str) -> Result:
    return CliRunner().invoke(group(), list(args))


@pytest.fixture(scope="module")
def db_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("dbc") / "ucom.dbc"
    r = ucom("dbc", "-o", str(path))
    assert r.exit_code == 0, r.stderr
    assert f"wrote {path}" in r.stderr
    return path


@pytest.fixture(scope="module")
def db(db_file: Path) -> Any:
    return cantools.database.load_file(str(db_file))


def decode(db: Any, frame: tuple[int, bytes]) -> dict[str, Any]:
    arbitration_id, data = frame
    return dict(db.decode_message(arbitration_id, data, allow_truncated=True))


def test_one_message_per_identifier(db: Any) -> None:
    ids = [msg.frame_id for msg in db.messages]
    assert len(ids) == len(set(ids)) == len(dbc_ops.entries())
    names = {msg.frame_id: msg.name for msg in db.messages}
    assert names[0x143] == "Info_3" and names[0x165] == "Info_F5"
    assert names[0x1C0] == "SetStatus_All" and names[0x0C0] == "InitAck_Unnumbered"
    assert names[0x2C0] == "Program_Slot0" and names[0x2FF] == "Program_Slot63"
    assert names[0x3A4] == "SoMap_4" and names[0x361] == "CiMap_1"
    assert names[0x503] == "McaReady_3" and 0x523 not in names  # run time: seq IDs only
    assert {n.name for n in db.nodes} == {"PC", "UCoM"}
    info = db.get_message_by_name("Info_3")
    assert info.senders == ["UCoM"] and "seq ID 3" in info.comment
    assert "XOR 0x55" in db.get_message_by_name("SoMap_1").comment


def test_info_record_decodes_to_its_fields(db: Any) -> None:
    info = BoardInfo(BoardState.BOOTLOADER, True, False, True, False, 3, 0, (1, 2),
                     0xCCD7F1F4, 12320, datetime(2026, 11, 22, 12, 30, 5, tzinfo=UTC),
                     0xD92172BB, 0x0080, Target.FLASH, "armar3.fl.S",
                     FpgaVersion(1, 1, 2, 3).register1(), FpgaVersion(1, 1, 2, 3).register2(),
                     1, False, ImageDescriptor(1, 1, 2, 0, (1, 4), ""))
    got = [decode(db, m.encode(frame, seq(3))) for frame in info.to_frames()]
    assert got[0] == {"Index": 0, "State": "BOOTLOADER", "AutoStart": 1, "ProgEnable": 0,
                      "FlashValid": 1, "ExtRamLoaded": 0, "InitDone": 1, "SeqID": 3,
                      "FixedID": 0, "BootloaderMajor": 1, "BootloaderMinor": 2}
    assert got[1] == {"Index": 1, "ProgID": 0xCCD7F1F4, "SizeWords": 12320}
    assert got[2] == {"Index": 2, "Year": 2026, "Month": 11, "Day": 22, "Hour": 12,
                      "Minute": 30, "Second": 5}
    assert got[3] == {"Index": 3, "Serial": 0xD92172BB, "Entry": 0x80, "Target": "FLASH"}
    name = "".join(chr(g[f"NameChar{i}"]) for g in got[4:8] for i in range(28)
                   if f"NameChar{i}" in g)
    assert name.rstrip("\0") == "armar3.fl.S"
    assert got[8] == {"Index": 8, "FpgaBoardID": 1, "FpgaAppID": 1, "FpgaMajor": 2,
                      "FpgaMinor": 3, "MeasuredBoardID": 1, "FpgaNeutral": 0}
    assert got[9] == {"Index": 9, "DescriptorPresent": 1, "DescriptorCorrupt": 0,
                      "DescBoardID": 1, "DescAppID": 1, "DescFpgaMajor": 2,
                      "DescFpgaMinor": 0, "DescVersionMajor": 1, "DescVersionMinor": 4}


def test_bootloader_messages(db: Any) -> None:
    assert decode(db, m.encode(m.SetStatus(StatusOp.PROG_ENABLE, 1), seq(3))) == {
        "Op": "PROG_ENABLE", "Value": 1}  # the protocol page's 0x1C3 01 01
    assert decode(db, (0x1C3, bytes.fromhex("0101"))) == {"Op": "PROG_ENABLE", "Value": 1}
    assert decode(db, m.encode(m.SetStatus(StatusOp.SEQ_ID, 7), fixed(4))) == {
        "Op": "SEQ_ID", "Value": 7}
    assert decode(db, m.encode(m.InitAck(InitAckKind.ASSIGNED, 1, 0, 0x10, 0x12345678),
                               seq(1))) == {
        "Kind": "ASSIGNED", "SeqID": 1, "FixedID": 0, "BootloaderMajor": 1,
        "BootloaderMinor": 0, "Serial": 0x12345678}
    assert decode(db, (0x084, bytes.fromhex("050B00008000"))) == {
        "Code": "PROTECTED_ADDRESS", "Function": "Program", "Detail": 0x8000}
    assert decode(db, m.encode(m.Ready(ReadyReason.ERASED, BoardState.RECEIVING, 128, 90),
                               seq(2))) == {
        "Reason": "ERASED", "State": "RECEIVING", "Erased_RingFrames": 128,
        "Erased_UsPerFrame": 90}
    assert decode(db, m.encode(m.Ready(ReadyReason.STATUS, BoardState.BOOTLOADER, 0x0101),
                               seq(2))) == {
        "Reason": "STATUS", "State": "BOOTLOADER", "Status_Op": "PROG_ENABLE",
        "Status_Value": 1}
    assert decode(db, (0x101, bytes.fromhex("0001000200000000"))) == {  # two reports follow
        "Kind": "RESULT", "Result_Status": "MISSING", "Result_Reports": 2,
        "Result_ProgID": 0}
    assert decode(db, m.encode(m.ProgramPartial(5, 17, 2), seq(1))) == {
        "Kind": "PARTIAL", "Partial_Block": 5, "Partial_FirstSlot": 17, "Partial_Count": 2}
    assert decode(db, m.encode(m.ProgramResult(ResultStatus.VERIFIED, 0, 0x67228575),
                               seq(1)))["Result_ProgID"] == 0x67228575
    text = decode(db, m.encode(m.TextReport(1, True, b"running"), seq(3)))
    assert text["Piece"] == 1 and text["Last"] == 1
    assert "".join(chr(text[f"Char{i}"]) for i in range(7)) == "running"
    assert decode(db, m.encode(m.MemoryReport(0x4000, (0x0081, 0x0400)), seq(1))) == {
        "Address": 0x4000, "Word0": 0x0081, "Word1": 0x0400}


def test_program_frames(db: Any) -> None:
    """Program identifiers describe the data frame (DLC 8, four words low byte first); a
    control frame (DLC < 8, first byte its op, the examples of ucom-protocol(7)) is not
    decoded strictly and has no signal that fits it when truncation is allowed: a data
    frame whose first byte is an op code is never read as a control frame, nor the
    reverse."""
    program_words = (0x0702, 0x1234, 0xBEEF, 0x0081)
    data = m.ProgramData(b"".join(w.to_bytes(2, "little") for w in program_words), 9)
    arbitration_id, payload = m.encode(data, ALL)
    assert arbitration_id == 0x2C9 and payload[0] == 0x02  # looks like META
    words = db.decode_message(arbitration_id, payload)["Words"]
    assert [(words >> 16 * i) & 0xFFFF for i in range(4)] == list(program_words)
    for control in ((0x2C0, bytes.fromhex("05400100011234")), (0x2C0, bytes.fromhex("040018")),
                    m.encode(m.ProgramBlock(Space.X, 0x1000, 17, 47, 0xBEEF), ALL),
                    m.encode(m.ProgramBegin(Target.FLASH, 50, 0x80), seq(2))):
        with pytest.raises(cantools.database.DecodeError, match="Wrong data size"):
            db.decode_message(*control)
        assert decode(db, control) == {}


def test_run_time_messages(db: Any) -> None:
    """The examples of ucom-protocol(7), RUN TIME."""
    assert decode(db, (0x503, bytes.fromhex("0014 0000 0D142600".replace(" ", "")))) == {
        "State": "STOPPED", "Answers": "MCA Ready", "Echo0": 0, "Echo1": 0, "CountCI": 13,
        "CountSO": 20, "CountPAR": 38, "Overrun": 0, "LatchedByWatchdog": 0}
    # values as raw bytes: an edge's width (2 or 4) is in its DumpIO Descr record
    assert decode(db, (0x3C3, bytes.fromhex("0003E836B00000"))) == {
        "FirstIndex": 0, "Data1": 0x03, "Data2": 0xE8, "Data3": 0x36, "Data4": 0xB0,
        "Data5": 0, "Data6": 0}
    assert decode(db, (0x343, bytes.fromhex("06CE4BD33F"))) == {
        "FirstIndex": 6, "Data1": 0xCE, "Data2": 0x4B, "Data3": 0xD3, "Data4": 0x3F}
    assert decode(db, (0x643, bytes.fromhex("020100010002 0E0F".replace(" ", "")))) == {
        "Op": "SO_MAP", "SoMap_Map": 1, "SoMap_Period": 1, "SoMap_Edge0": 0,
        "SoMap_Edge1": 2, "SoMap_Edge2": 14, "SoMap_Edge3": 15}
    assert decode(db, m_admin(mca.AdminData.alive(50))) == {"Op": "ALIVE",
                                                             "Alive_TimeoutMs": 50}
    assert decode(db, (0x5C3, bytes.fromhex("A703736B290000"))) == {
        "Kind": "PAR", "Last": 1, "Segment": 7, "Index": 3, "RecordByte0": 0x73,
        "RecordByte1": 0x6B, "RecordByte2": 0x29, "RecordByte3": 0, "RecordByte4": 0}
    assert decode(db, (0x6C3, bytes.fromhex("020502FAF080"))) == {
        "Kind": "PAR", "FirstIndex": 5, "Data2": 0x02, "Data3": 0xFA, "Data4": 0xF0,
        "Data5": 0x80}
    assert decode(db, (0x3A1, bytes.fromhex("56BDA94D55555555"))) == {
        "MaskedWord0": 0x56BD, "MaskedWord1": 0xA94D, "MaskedWord2": 0x5555,
        "MaskedWord3": 0x5555}
    assert decode(db, (0x4C3, bytes.fromhex("0102BC03E8000000"))) == {
        "RunState": "RUNNING", "Load": 70.0, "CycleTime": 1000, "Overruns": 0,
        "Overrun": 0, "LatchedByWatchdog": 0}


def m_admin(msg: mca.AdminData) -> tuple[int, bytes]:
    return mca.encode(msg, seq(3))


def test_a_recorded_trace_decodes_without_error(db: Any, tmp_path: Path) -> None:
    log = tmp_path / "t.log"
    r = CliRunner().invoke(cli, ["count", "--virtual", "armar3", "--init", "--log", str(log)])
    assert r.exit_code == 0, r.stderr
    import can
    frames = list(can.LogReader(str(log)))
    decoded = [db.decode_message(f.arbitration_id, bytes(f.data), allow_truncated=True)
               for f in frames]
    assert len(decoded) == len(frames)
    info0 = next(d for f, d in zip(frames, decoded, strict=True)
                 if f.arbitration_id == 0x142 and f.data[0] == 0)
    assert info0["SeqID"] == 2 and info0["State"] == "BOOTLOADER"


def test_existing_file_needs_force(db_file: Path, tmp_path: Path) -> None:
    target = tmp_path / "u.dbc"
    target.write_text("mine")
    r = ucom("dbc", "-o", str(target))
    assert r.exit_code == 3 and "exists" in r.stderr and "--force" in r.stderr
    assert target.read_text() == "mine"
    os.chmod(target, 0o600)
    r = ucom("dbc", "-o", str(target), "--force")
    assert r.exit_code == 0, r.stderr
    assert target.read_bytes() == db_file.read_bytes()
    assert target.stat().st_mode & 0o777 == 0o600 and os.listdir(tmp_path) == ["u.dbc"]


def test_missing_directory_is_bad_input(tmp_path: Path) -> None:
    r = ucom("dbc", "-o", str(tmp_path / "no" / "u.dbc"))
    assert r.exit_code == 3 and "does not exist" in r.stderr
    assert not (tmp_path / "no").exists()


def test_standard_output(db_file: Path) -> None:
    r = ucom("dbc", "-o", "-")
    assert r.exit_code == 0
    assert r.stdout.startswith('VERSION "ucom-tools')
    assert cantools.database.load_string(r.stdout).get_message_by_name("Info_1")


def test_without_cantools_the_error_says_how_to_install(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    real = builtins.__import__

    def no_cantools(name: str, *args: Any, **kwargs: Any) -> Any:
        if name == "cantools" or name.startswith("cantools."):
            raise ImportError("No module named 'cantools'")
        return real(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_cantools)
    with pytest.raises(InputError, match=r"pip install 'ucom-tools\[dbc\]'"):
        dbc_ops.build()
    r = ucom("dbc", "-o", str(tmp_path / "u.dbc"))
    assert r.exit_code == 3 and "ucom-tools[dbc]" in r.stderr
    assert os.listdir(tmp_path) == []
