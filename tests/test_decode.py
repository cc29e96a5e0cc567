"""``ucom decode``: traces recorded with ``--log`` while real commands ran on the virtual
fleet, read back as conversations; the same traces with faults put in by hand, each of
which must show as a violation naming the frame."""

from __future__ import annotations

import copy
import json
from collections.abc import Callable
from pathlib import Path

import can
import click
import pytest
from click.testing import CliRunner, Result

from ucom_tools.cli import decode as decode_cli
from ucom_tools.cli.main import UcomGroup, cli
from ucom_tools.image.formats import load_image
from ucom_tools.trace.decode import (
    BOARD_TO_PC,
    PC_TO_BOARD,
    Conversation,
    Message,
    decode_frames,
    load_trees,
    read_trace,
)

ROOT = Path(__file__).resolve().parents[1]
IMAGE = str(ROOT / "firmware_images/armar3.fl.S")
PROGID = f"0x{load_image(IMAGE).progid:08X}"


def group() -> click.Group:
    """main's commands plus decode (the integrator registers it in ucom_tools.cli.main)."""
    g = UcomGroup("ucom", commands=dict(cli.commands), params=cli.params,
                  callback=cli.callback)
    g.add_command(decode_cli.decode)
    return g


def ucom(*args: str) -> Result:
    return CliRunner().invoke(group(), list(args))


@pytest.fixture(scope="module")
def traces(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Real commands on the virtual fleet, each recording its frames with --log."""
    d = tmp_path_factory.mktemp("traces")
    state = d / "state"
    state.mkdir()
    runs = {
        "init": ["init", "--virtual", "armar3", "--log", str(d / "init.asc")],
        "flash": ["flash", IMAGE, "--virtual", "armar3", "--bus", "CAN0",
                  "--log", str(d / "flash.blf")],
        "flash_all": ["flash", IMAGE, "--virtual", "armar3", "--state", str(state)],
        "run": ["remote", "run", "armar3", "--virtual", "armar3", "--state", str(state),
                "--for", "0.2", "--set", "Right Eye Target=1000", "--log", str(d / "run.log")],
    }
    for name, args in runs.items():
        r = ucom(*args)
        assert r.exit_code == 0, (name, r.stderr)
    return {"init": d / "init.asc", "flash": d / "flash.blf", "run": d / "run.log"}


@pytest.fixture(scope="module")
def frames(traces: dict[str, Path]) -> dict[str, list[can.Message]]:
    return {name: read_trace(path) for name, path in traces.items()}


def texts(conv: Conversation, **where: str) -> list[str]:
    return [m.text for m in conv.messages(**where)]


def one(conv: Conversation, predicate: Callable[[Message], bool]) -> Message:
    found = [m for b in conv.buses for m in b.messages if predicate(m)]
    assert len(found) == 1, found
    return found[0]


# ============================================================================ clean traces
def test_init_trace_names_the_chain_and_the_info_records(frames) -> None:
    conv = decode_frames(frames["init"])
    assert conv.ok, conv.render()
    assert [b.name for b in conv.buses] == ["CAN0", "CAN1", "CAN2", "CAN3"]  # .asc numbers
    init = texts(conv, bus="CAN0", board="all", function="Init Request")
    assert init[:4] == ["BEGIN", "NEXT 2", "NEXT 3", "NEXT 4"]
    assert "END: the chain has seq IDs 1-3" in init
    assert "END: the chain has seq IDs 1-2" in texts(conv, bus="CAN3", board="all")
    acks = conv.messages(bus="CAN0", function="Init Ack")
    assert [(m.board, m.fields["kind"], m.fields["seq_id"]) for m in acks][:3] == [
        ("1", "ASSIGNED", 1), ("2", "ASSIGNED", 2), ("3", "ASSIGNED", 3)]
    assert all(m.dir == BOARD_TO_PC for m in acks)
    infos = conv.messages(bus="CAN0", function="Info")
    assert [m.board for m in infos] == ["1", "2", "3"]
    for ack, info in zip(acks, infos, strict=False):
        assert info.frames == 10
        assert info.fields["serial"] == ack.fields["serial"]  # the record, assembled
        assert info.fields["state"] == "BOOTLOADER" and info.fields["seq_id"] == int(info.board)
        assert info.fields["fpga"] == {"board_id": 1, "app_id": 1, "version": "1.0"}
    request = one(conv, lambda m: m.bus == "CAN0" and m.function == "Info Request")
    assert request.dir == PC_TO_BOARD and request.board == "all"


def test_flash_trace_shows_the_programming_as_blocks_without_resends(frames) -> None:
    conv = decode_frames(frames["flash"])
    assert conv.ok, conv.render()
    assert [b.name for b in conv.buses] == ["CAN0"]
    program = conv.messages(board="all", function="Program")
    begin = program[[m.fields.get("op") for m in program].index("BEGIN")]
    image = load_image(IMAGE)
    assert begin.fields["blocks"] == len(image.blocks)
    assert begin.fields["progid"] == PROGID and begin.fields["name"] == "armar3.fl.S"
    blocks = [m for m in program if m.fields.get("op") == "BLOCK"]
    assert [m.fields["index"] for m in blocks] == list(range(len(image.blocks)))
    for m, block in zip(blocks, image.blocks, strict=True):
        assert m.fields["frames"] == block.frames == m.fields["data_frames"]
        assert m.fields["resent"] == 0 and m.fields["not_sent"] == 0 and not m.fields["again"]
        assert m.frames == 1 + block.frames  # the BLOCK frame and its data frames
    end = [m for m in program if m.fields.get("op") == "END"]
    assert len(end) == 1 and end[0].fields["resent"] == 0
    assert end[0].fields["data_frames"] == sum(b.frames for b in image.blocks)
    for board in ("1", "2", "3"):
        result = one(conv, lambda m, b=board: m.board == b and
                     m.function == "Program Finished")
        assert result.fields["status"] == "VERIFIED" and result.fields["progid"] == PROGID
        erased = [m for m in conv.messages(board=board, function="Ready")
                  if m.fields["reason"] == "ERASED"]
        assert len(erased) == 1
        assert conv.messages(board=board, function="Info")[-1].fields["name"] == "armar3.fl.S"
    # one line per block, not per data frame
    assert len(conv.messages()) < 200 < len(frames["flash"])


def test_run_trace_with_the_trees_shows_values_by_unique_name(frames) -> None:
    conv = decode_frames(frames["run"], load_trees(["armar3"]))
    assert conv.ok, conv.render()
    # the descriptions, with the robot's names beside the program's
    descr = [m for m in conv.messages(bus="CAN0", board="3", function="MCA DumpIO Descr")]
    assert len(descr) == 71
    assert descr[3].fields["name"] == "MotorA Target"
    assert descr[3].fields["unique"] == "Right Eye Target"
    # a PAR write and its acknowledgement
    par = conv.messages(bus="CAN0", board="3", function="MCA Parameter")[0]
    assert par.text.startswith("PAR 0: LoopTime(ms)=1.000 ms")
    ready = conv.messages(bus="CAN0", board="3", function="MCA Ready")
    assert any(m.fields["answers"] == 15 for m in ready)
    # the CI map that carries the set point, by name and value
    ci = [m for m in conv.messages(bus="CAN0") if m.board.startswith("CI map")]
    values = {v["unique"]: v["value"] for m in ci for v in m.fields["values"]}
    assert values["Right Eye Target"] == "1000"
    assert "3:Right Eye Target=1000 counts (0..1000)" in " ".join(m.text for m in ci)
    # SO maps: every board's, at their periods, with values by name
    so = [m for m in conv.messages(bus="CAN0") if m.board.startswith("SO map")]
    assert {m.fields["board"] for m in so} == {"1", "2", "3"}
    eye = one(conv, lambda m: m.bus == "CAN0" and m.board.startswith("SO map")
              and any(v["unique"] == "Right Eye Joint Sensor" for v in m.fields["values"]))
    assert eye.fields["every_ms"] == pytest.approx(1.0, abs=0.05)
    assert eye.frames > 150
    joint = next(v for v in eye.fields["values"] if v["unique"] == "Right Eye Joint Sensor")
    assert 500 < int(joint["value"]) < 1100  # the eye moved to its target
    start = [m for m in conv.messages(bus="CAN0", board="3", function="MCA Start")]
    assert [m.text for m in start] == ["START", "STOP"]
    alive = one(conv, lambda m: m.bus == "CAN0" and m.function == "MCA Alive")
    assert alive.board == "all" and alive.frames > 10


def test_run_trace_without_trees_uses_the_descriptions_in_the_trace(frames) -> None:
    conv = decode_frames(frames["run"])
    assert conv.ok
    par = conv.messages(bus="CAN0", board="3", function="MCA Parameter")[0]
    assert par.text.startswith("PAR 0: LoopTime(ms)=1.000 ms, Max PWM=")
    ci = [m for m in conv.messages(bus="CAN0") if m.board.startswith("CI map")]
    assert "3:MotorA Target=1000 counts" in " ".join(m.text for m in ci)


def test_without_descriptions_the_trees_program_decodes_the_values(frames) -> None:
    """No MCA DumpIO Descr in the trace: the program the board's tree maps is used."""
    cut = [f for f in frames["run"] if f.arbitration_id >> 6 not in (22, 23)]
    conv = decode_frames(cut, load_trees(["armar3"]))
    assert conv.ok, conv.render()
    ci = [m for m in conv.messages(bus="CAN0") if m.board.startswith("CI map")]
    assert "3:Right Eye Target=1000 counts" in " ".join(m.text for m in ci)
    bare = decode_frames(cut)  # nothing says what the bytes are: shown raw
    par = bare.messages(bus="CAN0", board="3", function="MCA Parameter")[0]
    assert par.text == "PAR 0: 03 E8 36 B0 00 00" and par.fields["values"] == []


def test_text_reports_are_assembled(frames) -> None:
    conv = decode_frames(frames["run"])
    text = conv.messages(bus="CAN0", board="1", function="Report 2")[0]
    assert text.fields["complete"] and text.frames == 7
    assert text.fields["text"].startswith("program 'armar3.fl.S' running (ProgID")


def test_render_per_board_and_as_a_timeline(frames) -> None:
    conv = decode_frames(frames["init"])
    by_board = conv.render()
    assert "bus CAN0: 43 frames\n  board all\n" in by_board
    assert "  board 2\n" in by_board and by_board.endswith("violations: none\n")
    timeline = conv.render(timeline=True, bus="CAN0")
    assert "CAN1" not in timeline
    line = next(x for x in timeline.splitlines() if "Init Ack" in x)
    assert line.split()[1:4] == ["1", "<B", "Init"]
    assert str(conv) == conv.render(timeline=True)


def test_frames_without_a_channel_are_one_bus() -> None:
    msgs = [can.Message(timestamp=1.0, arbitration_id=0x280, data=b"\x01\x00",
                        is_extended_id=False),
            can.Message(timestamp=1.0002, arbitration_id=0x0C1,
                        data=bytes.fromhex("00010010D92172BB"), is_extended_id=False),
            can.Message(timestamp=1.0003, arbitration_id=0x280, data=b"\x01\x00",
                        is_extended_id=False, channel="other")]
    conv = decode_frames(msgs)
    assert [b.name for b in conv.buses] == ["CAN", "other"]
    assert conv.messages(bus="CAN", function="Init Ack")[0].t == pytest.approx(0.0002)


# ============================================================================ faults
def _violations(conv: Conversation, rule: str) -> list:
    return [v for v in conv.violations if v.rule == rule]


def test_a_dropped_answer_is_a_request_never_answered(frames) -> None:
    trace = frames["flash"]
    i = next(i for i, f in enumerate(trace) if f.arbitration_id == 0x182 and f.data[0] == 1)
    conv = decode_frames(trace[:i] + trace[i + 1:])  # board 2's Ready(ERASED)
    (v,) = conv.violations
    assert v.rule == "unanswered" and v.board == "2"
    assert "PREPARE (50 pages) to board 2 was not answered" in v.message
    prepare = next(j for j, f in enumerate(trace) if f.arbitration_id == 0x2C0
                   and f.dlc == 3 and f.data[0] == 4)
    assert v.index == prepare  # the request, by its place in the trace


def test_a_late_answer_is_named_with_its_delay(frames) -> None:
    trace = list(frames["flash"])
    i = next(i for i, f in enumerate(trace) if f.arbitration_id == 0x182 and f.data[0] == 5)
    trace[i] = copy.copy(trace[i])
    trace[i].timestamp += 0.2  # Ready(STATUS) of board 2, 200 ms late
    conv = decode_frames(trace)
    (v,) = _violations(conv, "late")
    assert v.rule == "late" and v.board == "2" and v.index == i
    # the frame was stamped later but not moved: the frames after it run back in time
    assert {x.rule for x in conv.violations} == {"late", "time-backwards"}
    assert "SetStatus PROG_ENABLE to every board: answer 200." in v.message
    assert v.t == pytest.approx(trace[i].timestamp - trace[0].timestamp)


def test_a_late_init_ack(frames) -> None:
    trace = list(frames["init"])
    i = next(i for i, f in enumerate(trace) if f.arbitration_id == 0x0C2)
    trace[i] = copy.copy(trace[i])
    trace[i].timestamp += 0.05  # T_init is 30 ms
    late = _violations(decode_frames(trace), "late")
    assert [(v.index, v.board) for v in late] == [(i, "2")]
    assert "Init Request NEXT 2 (seq ID 2)" in late[0].message


def test_a_frame_of_the_wrong_length_names_the_field(frames) -> None:
    trace = list(frames["init"])
    i = next(i for i, f in enumerate(trace) if f.arbitration_id == 0x0C3)
    f = trace[i]
    trace[i] = can.Message(timestamp=f.timestamp, arbitration_id=f.arbitration_id,
                           data=f.data[:7], is_extended_id=False, channel=f.channel)
    conv = decode_frames(trace)
    malformed = _violations(conv, "malformed")
    assert [(v.index, v.board) for v in malformed] == [(i, "3")]
    assert "Init Ack payload length: expected 8 bytes, got 7" in malformed[0].message
    msg = one(conv, lambda m: m.index == i)
    assert msg.fields["field"] == "Init Ack payload length"


def test_a_data_frame_out_of_sequence(frames) -> None:
    trace = list(frames["flash"])
    data = [i for i, f in enumerate(trace) if f.arbitration_id >> 6 == 11 and f.dlc == 8]
    a, b = data[100], data[101]  # swapped: slot n+1 before slot n
    trace[a], trace[b] = copy.copy(trace[b]), copy.copy(trace[a])
    trace[a].timestamp, trace[b].timestamp = trace[b].timestamp, trace[a].timestamp
    out = _violations(decode_frames(trace), "data-out-of-sequence")
    assert len(out) == 1 and out[0].index == b and "slots rise within a block" in out[0].message
    trace = list(frames["flash"])
    f = trace[data[5]]  # block 0 has 32 frames: slot 40 is outside it
    trace[data[5]] = can.Message(timestamp=f.timestamp, arbitration_id=0x2C0 + 40,
                                 data=f.data, is_extended_id=False, channel=f.channel)
    out = _violations(decode_frames(trace), "data-out-of-sequence")
    assert [v.index for v in out] == [data[5]]
    assert "slot 40 is outside block 0" in out[0].message


def test_an_so_map_that_stops_arriving(frames) -> None:
    trace = frames["run"]
    t0 = trace[0].timestamp
    so1 = [f for f in trace if f.channel == "CAN0" and f.arbitration_id == 0x3A1]
    cut = so1[len(so1) // 2].timestamp
    kept = [f for f in trace if not (f.channel == "CAN0" and f.arbitration_id == 0x3A1
                                     and cut < f.timestamp < cut + 0.05)]
    (v,) = decode_frames(kept).violations
    assert v.rule == "so-map-stopped" and v.bus == "CAN0" and v.board == "1"
    assert "SO map 1 of board 1: no frame for" in v.message and "period is 1.000 ms" in v.message
    assert cut + 0.05 - t0 <= v.t < cut + 0.052 - t0
    gone = [f for f in trace if not (f.channel == "CAN0" and f.arbitration_id == 0x3A1
                                     and f.timestamp > cut)]
    (v,) = decode_frames(gone).violations
    assert v.rule == "so-map-stopped" and "before its exchange ended" in v.message


def test_foreign_frames_are_reported() -> None:
    msgs = [can.Message(timestamp=0.0, arbitration_id=0x18FF0001, data=b"\x00",
                        is_extended_id=True),
            can.Message(timestamp=0.1, arbitration_id=0x7C0, data=b"", is_extended_id=False)]
    conv = decode_frames(msgs)
    assert [v.rule for v in conv.violations] == ["foreign-frame", "malformed"]
    assert "function: code 31 is unassigned" in conv.violations[1].message


# ============================================================================ command
def test_decode_command_text_and_exit_codes(traces, tmp_path: Path) -> None:
    r = ucom("decode", str(traces["init"]))
    assert r.exit_code == 0, r.stderr
    assert "bus CAN0: 43 frames" in r.stdout and "violations: none" in r.stdout
    r = ucom("decode", str(traces["run"]), "--trees", "armar3", "--bus", "CAN0",
             "--board", "CI map 2")
    assert r.exit_code == 0, r.stderr
    assert "3:Right Eye Target=1000 counts" in r.stdout and "CAN1" not in r.stdout
    broken = tmp_path / "broken.log"
    lines = traces["run"].read_text().splitlines()
    broken.write_text("\n".join(x for x in lines if " CAN2 3A1#" not in x) + "\n")
    r = ucom("decode", str(broken))
    assert r.exit_code == 1
    assert "so-map-stopped" in r.stdout and "1 protocol violation" in r.stderr


def test_decode_command_json(traces) -> None:
    r = ucom("decode", str(traces["flash"]), "--json")
    assert r.exit_code == 0, r.stderr
    data = json.loads(r.stdout)
    assert data["violations"] == [] and data["frames"] > 3000
    (bus,) = data["buses"]
    assert bus["name"] == "CAN0"
    boards = {b["board"]: b["messages"] for b in bus["boards"]}
    assert list(boards) == ["all", "1", "2", "3"]
    first = boards["1"][0]
    assert set(first) >= {"t", "dir", "function", "text", "fields"}
    assert first["function"] == "Init Ack" and first["dir"] == "board -> PC"
    assert first["fields"]["seq_id"] == 1


def test_decode_command_bad_input(tmp_path: Path) -> None:
    r = ucom("decode", str(tmp_path / "missing.asc"))
    assert r.exit_code == 3 and "missing.asc: no such file" in r.stderr
    bad = tmp_path / "bad.blf"
    bad.write_bytes(b"not a BLF file at all")
    r = ucom("decode", str(bad))
    assert r.exit_code == 3 and "bad.blf: cannot read as a CAN trace" in r.stderr
    other = tmp_path / "notes.txt2"
    other.write_text("hello")
    r = ucom("decode", str(other))
    assert r.exit_code == 3 and "notes.txt2" in r.stderr
    assert "Traceback" not in r.output


def test_decode_command_bad_trees(traces) -> None:
    r = ucom("decode", str(traces["init"]), "--trees", "nosuchrobot")
    assert r.exit_code == 3 and "nosuchrobot" in r.stderr
    r = ucom("decode", str(traces["init"]), "--trees", "armar3", "--trees", "lauron4")
    assert r.exit_code == 3 and "--trees" in r.stderr
    r = ucom("decode", str(traces["init"]), "--bus", "CAN9")
    assert r.exit_code == 3 and "no bus 'CAN9'" in r.stderr
