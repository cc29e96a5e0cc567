"""``--log FILE``: every bus command records every frame of every bus it opened, received
and sent, into a python-can log; a bad FILE is exit code 3 before any bus is opened."""

from __future__ import annotations

import itertools
import os
from pathlib import Path

import can
import pytest
from click.testing import CliRunner, Result

from ucom_tools.cli.main import cli
from ucom_tools.ops.robot import ConnectSpec, open_robot
from ucom_tools.trace import logs as logs_mod
from ucom_tools.trace.decode import decode_frames, read_trace
from ucom_tools.trace.logs import FrameLog, LogError

ROOT = Path(__file__).resolve().parents[1]


def ucom(*args: str) -> Result:
    return CliRunner().invoke(cli, list(args))


@pytest.fixture
def no_bus(monkeypatch: pytest.MonkeyPatch) -> list[tuple]:
    """Fails the test if any bus is opened."""
    opened: list[tuple] = []

    def bus(*args: object, **kwargs: object) -> can.BusABC:
        opened.append((args, kwargs))
        raise AssertionError("a bus was opened")

    monkeypatch.setattr(can, "Bus", bus)
    return opened


@pytest.mark.parametrize("name", ["t.xyz", "t", "t.asc.bz2"])
def test_unsupported_extension_is_bad_input_and_nothing_is_opened(
        tmp_path: Path, no_bus: list, name: str) -> None:
    r = ucom("init", "--virtual", "armar3", "--log", str(tmp_path / name))
    assert r.exit_code == 3, r.output
    assert "--log" in r.stderr and "not a CAN log format" in r.stderr and ".blf" in r.stderr
    assert no_bus == [] and os.listdir(tmp_path) == []


def test_missing_directory_or_a_directory_is_bad_input(tmp_path: Path, no_bus: list) -> None:
    r = ucom("reset", "--virtual", "armar3", "--log", str(tmp_path / "no" / "t.asc"))
    assert r.exit_code == 3 and "does not exist" in r.stderr and "--log" in r.stderr
    (tmp_path / "d.log").mkdir()
    r = ucom("flash", str(ROOT / "firmware_images/armar3.fl.S"), "--virtual", "armar3",
             "--log", str(tmp_path / "d.log"))
    assert r.exit_code == 3 and "is a directory" in r.stderr
    r = ucom("remote", "run", "armar3", "--virtual", "armar3", "--for", "0.1", "--log",
             str(tmp_path / "run.pdf"))
    assert r.exit_code == 3 and "--log" in r.stderr
    assert no_bus == []


def test_every_frame_of_every_bus_with_virtual_time(tmp_path: Path) -> None:
    log = tmp_path / "init.log"
    r = ucom("init", "--virtual", "armar3", "--log", str(log))
    assert r.exit_code == 0, r.stderr
    assert os.listdir(tmp_path) == ["init.log"]  # no temporary file left
    frames = read_trace(log)
    assert {f.channel for f in frames} == {"CAN0", "CAN1", "CAN2", "CAN3"}
    can0 = [f for f in frames if f.channel == "CAN0"]
    sent = [f for f in can0 if not f.is_rx]
    received = [f for f in can0 if f.is_rx]
    assert sent[0].arbitration_id == 0x280 and bytes(sent[0].data) == b"\x01\x00"  # BEGIN
    assert received[0].arbitration_id == 0x0C1  # Init Ack of board 1
    # sent and received frames on one time base, the fleet's virtual time: the board
    # answers BEGIN after its settle time (100 us) and the two frames' wire time
    answer = received[0].timestamp - sent[0].timestamp
    assert 0.0001 < answer < 0.001
    next2 = next(f for f in sent if bytes(f.data) == b"\x02\x02")
    assert received[0].timestamp <= next2.timestamp < received[0].timestamp + 0.001
    # three unanswered NEXT 4 at T_init (30 ms of virtual time) apart
    nexts = [f.timestamp for f in sent if bytes(f.data) == b"\x02\x04"]
    assert [round(b - a, 3) for a, b in itertools.pairwise(nexts)] == [0.03, 0.03]
    assert decode_frames(frames).ok


@pytest.mark.parametrize("ext", [".asc", ".blf", ".trc", ".csv", ".db", ".log.gz"])
def test_formats_by_extension(tmp_path: Path, ext: str) -> None:
    log = tmp_path / f"t{ext}"
    r = ucom("count", "--virtual", "armar3", "--init", "--log", str(log))
    if ext in (".csv", ".db"):  # no channel column: four buses could not be told apart
        assert r.exit_code == 3 and "has no channel column" in r.stderr
        assert os.listdir(tmp_path) == []
        r = ucom("count", "--virtual", "tests/data/armar3_can0.toml", "--init", "--log",
                 str(log))
    assert r.exit_code == 0, r.stderr
    frames = read_trace(log)
    conv = decode_frames(frames)
    names = [b.name for b in conv.buses]
    if ext in (".csv", ".db"):  # one bus: kept, as the default bus
        assert names == ["CAN"]
    else:  # bus CANn stored as channel n where the format wants numbers
        assert names == ["CAN0", "CAN1", "CAN2", "CAN3"]
        assert conv.ok, conv.render()
        assert "END: the chain has seq IDs 1-3" in [
            m.text for m in conv.messages(bus="CAN0", function="Init Request")]


def test_bad_input_after_opening_leaves_no_log(tmp_path: Path) -> None:
    log = tmp_path / "t.log"
    r = ucom("info", "1", "--virtual", "armar3", "--init", "--bus", "CAN7", "--log", str(log))
    assert r.exit_code == 3 and "no bus 'CAN7'" in r.stderr
    assert os.listdir(tmp_path) == []


def test_an_existing_log_is_replaced_whole_and_keeps_its_mode(tmp_path: Path) -> None:
    log = tmp_path / "t.log"
    log.write_text("old\n")
    os.chmod(log, 0o640)
    r = ucom("reset", "--virtual", "armar3", "--log", str(log))
    assert r.exit_code == 0, r.stderr
    assert "old" not in log.read_text() and log.stat().st_mode & 0o777 == 0o640
    assert [f.arbitration_id for f in read_trace(log)] == [0x000] * 4  # Reset on each bus


def test_library_open_robot_records_and_close_keeps(tmp_path: Path) -> None:
    log = tmp_path / "lib.asc"
    r = open_robot(ConnectSpec(virtual="armar3", log=log))
    try:
        assert r.log is not None
        r.buses["CAN1"].client.init_chain()
    finally:
        r.close()
    frames = read_trace(log)
    assert {f.channel for f in frames} == {1}  # CAN1, numbered in .asc
    assert all(not h.link.dispatcher.taps for h in r.buses.values())


def test_a_recording_that_cannot_be_written_leaves_no_file(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    log = FrameLog(tmp_path / "t.log")

    def full(msg: can.Message) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(log._frames._writer, "on_message_received", full)
    log._frames.write(can.Message(arbitration_id=0x200, is_extended_id=False, is_rx=False),
                      "CAN0")
    with pytest.raises(LogError, match="No space left"):
        log.close()
    assert os.listdir(tmp_path) == []


def test_check_log_names_the_input_and_the_command_line_its_option() -> None:
    from ucom_tools.cli.errortext import describe

    with pytest.raises(logs_mod.InputError) as e:
        logs_mod.check_log("x.nope")
    assert e.value.key == "log"
    assert describe(e.value).startswith("--log: x.nope: '.nope' is not a CAN log format")
