"""Recording a run (``RunRecorder``: frames into a python-can log, value changes into
FILE.values.csv) and plotting the values (``ucom remote plot``)."""

from __future__ import annotations

import csv
import json
import os
import threading
import time
from collections.abc import Iterator
from decimal import Decimal
from pathlib import Path

import can
import pytest
from click.testing import CliRunner

from ucom_tools.cli.main import UcomGroup
from ucom_tools.cli.plot import PLOT_EXTRA, plot
from ucom_tools.config.attrtree.model import TreeEdgeKind
from ucom_tools.errors import InputError
from ucom_tools.trace.logs import LogError
from ucom_tools.trace.record import VALUES_HEADER, RunRecorder, read_values, values_path
from ucom_tools.wire import mca

CLI = UcomGroup("ucom", commands={"remote": UcomGroup("remote", commands={"plot": plot})})


def run(*args: str) -> tuple[int, str, str]:
    r = CliRunner().invoke(CLI, ["remote", "plot", *args])
    return r.exit_code, r.stdout, r.stderr


def frames() -> list[can.Message]:
    """Frames of two buses: standard and extended IDs, 0-8 data bytes, Rx and Tx."""
    out = []
    for i in range(24):
        out.append(can.Message(
            timestamp=1000.0 + i * 0.000_25, arbitration_id=(0x12345 + i) if i % 3 == 0
            else 0x100 + i, is_extended_id=i % 3 == 0, data=bytes(range(i, i + i % 9)),
            channel="CAN0" if i % 2 else "CAN1", is_rx=i % 4 != 1))
    return out


def rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="", encoding="utf-8") as f:
        reader = csv.reader(f)
        header = next(reader)
        assert tuple(header) == VALUES_HEADER
        return [dict(zip(header, row, strict=True)) for row in reader]


# ----------------------------------------------------------------------------- frames
@pytest.mark.parametrize("ext", [".asc", ".blf", ".log", ".csv", ".log.gz"])
def test_frames_read_back_with_logreader(tmp_path: Path, ext: str) -> None:
    path = tmp_path / f"run{ext}"
    sent = frames()
    with RunRecorder(path) as rec:
        for msg in sent:
            rec.on_message_received(msg)
        assert not path.exists()  # the file appears whole, when the recording ends
    assert rec.frames == len(sent) and rec.rows == 0
    assert sorted(os.listdir(tmp_path)) == sorted([path.name, path.name + ".values.csv"])
    back = list(can.LogReader(path))
    assert len(back) == len(sent)
    for a, b in zip(sent, back, strict=True):
        assert (b.arbitration_id, b.is_extended_id, bytes(b.data)) == \
            (a.arbitration_id, a.is_extended_id, bytes(a.data))
        assert b.timestamp - back[0].timestamp == pytest.approx(
            a.timestamp - sent[0].timestamp, abs=2e-6)
        if ext in (".asc", ".blf"):
            assert b.channel == rec.channels[str(a.channel)]
            assert b.is_rx == a.is_rx
        elif ext.startswith(".log"):
            assert b.channel == a.channel  # the bus name, verbatim
    if ext in (".asc", ".blf"):
        assert rec.channels == {"CAN1": 1, "CAN0": 0}
    # the caller's frames are not changed (other listeners see the same objects)
    assert {m.channel for m in sent} == {"CAN0", "CAN1"}


def test_bus_names_without_a_number_get_channels_of_their_own(tmp_path: Path) -> None:
    path = tmp_path / "run.asc"
    with RunRecorder(path) as rec:
        for name in ("left", "CAN1", "right", "can1", "left"):
            rec.on_message_received(can.Message(arbitration_id=1, channel=name))
    assert rec.channels == {"left": 0, "CAN1": 1, "right": 2, "can1": 3}
    assert [m.channel for m in can.LogReader(path)] == [0, 1, 2, 3, 0]


def test_notifier_feeds_frames_from_bus_reader_threads(tmp_path: Path) -> None:
    path = tmp_path / "run.log"
    tx = can.Bus(interface="virtual", channel="rec-test")
    rx = can.Bus(interface="virtual", channel="rec-test")
    try:
        with RunRecorder(path) as rec:
            notifier = can.Notifier(rx, [rec], timeout=0.01)
            try:
                for i in range(50):
                    tx.send(can.Message(arbitration_id=i, data=[i], is_extended_id=False))
                deadline = time.monotonic() + 5
                while rec.frames < 50 and time.monotonic() < deadline:
                    time.sleep(0.01)
            finally:
                notifier.stop()  # stops its listeners: closes the recorder
            assert rec.closed
    finally:
        tx.shutdown()
        rx.shutdown()
    assert [m.arbitration_id for m in can.LogReader(path)] == list(range(50))


def test_several_threads_feeding_frames_and_values_add_up(tmp_path: Path) -> None:
    path = tmp_path / "run.blf"
    threads_n, per_thread = 8, 400
    start = threading.Barrier(threads_n)

    def feed(k: int, rec: RunRecorder) -> None:
        start.wait()
        for i in range(per_thread):
            rec.on_message_received(can.Message(
                timestamp=10.0 + i * 1e-3, arbitration_id=k * 1000 + i, data=[k, i % 256],
                channel=f"CAN{k % 4}", is_extended_id=False))
            rec.value(10.0 + i * 1e-3, f"CAN{k % 4}", k, f"B{k}", f"Edge {k}", "SO", i // 2)

    with RunRecorder(path) as rec:
        workers = [threading.Thread(target=feed, args=(k, rec)) for k in range(threads_n)]
        for w in workers:
            w.start()
        for w in workers:
            w.join()
    assert rec.frames == threads_n * per_thread
    assert rec.rows == threads_n * per_thread // 2
    back = list(can.LogReader(path))
    assert sorted(m.arbitration_id for m in back) == sorted(
        k * 1000 + i for k in range(threads_n) for i in range(per_thread))
    assert all(bytes(m.data)[0] == m.arbitration_id // 1000 for m in back)
    got = rows(values_path(path))
    assert len(got) == rec.rows
    for k in range(threads_n):
        mine = [int(r["value"]) for r in got if r["name"] == f"Edge {k}"]
        assert mine == list(range(per_thread // 2))  # each thread's rows in its order


# ----------------------------------------------------------------------------- values
def test_values_file_holds_only_changes_as_exact_decimal_text(tmp_path: Path) -> None:
    path = tmp_path / "run.asc"
    with RunRecorder(path) as rec:
        put = rec.value
        assert put(1.0, "CAN0", 1, "Eyes", "Right Eye Target", "CI", Decimal("1.50"))
        assert not put(1.001, "CAN0", 1, "Eyes", "Right Eye Target", "CI", Decimal("1.5"))
        assert not put(1.002, "CAN0", 1, "Eyes", "Right Eye Target", TreeEdgeKind.CI, 1.5)
        assert put(1.003, "CAN0", 1, "Eyes", "Right Eye Target", "CI", 2)
        # the same name on another board or bus is another signal: its first row is written
        assert put(1.003, "CAN0", 2, "Neck", "Right Eye Target", "CI", 2)
        assert put(1.003, "CAN1", 1, "Eyes", "Right Eye Target", "CI", 2)
        assert put(1.0041234567, "CAN0", 1, "Eyes", "Right Eye Joint Sensor", mca.Kind.SO,
                   0.00001)
        assert put(1.005, "CAN0", 1, "Eyes", "Right Eye Joint Sensor", "SO",
                   Decimal("-1.2E+3"))
        assert put(1.006, "CAN0", 1, "Eyes", "Right Eye Gain", TreeEdgeKind.PAR, 10**20)
        assert not put(1.007, "CAN0", 1, "Eyes", "Right Eye Gain", "PAR", Decimal("1E+20"))
        with pytest.raises(ValueError):
            put(1.008, "CAN0", 1, "Eyes", "Right Eye Gain", "XX", 1)
        with pytest.raises(ValueError):
            put(1.008, "CAN0", 1, "Eyes", "Right Eye Gain", "PAR", float("nan"))
    assert rec.rows == 7
    got = rows(values_path(path))
    assert [(r["timestamp"], r["bus"], r["board"], r["prefix"], r["name"], r["kind"],
             r["value"]) for r in got] == [
        ("1.000000", "CAN0", "1", "Eyes", "Right Eye Target", "CI", "1.50"),
        ("1.003000", "CAN0", "1", "Eyes", "Right Eye Target", "CI", "2"),
        ("1.003000", "CAN0", "2", "Neck", "Right Eye Target", "CI", "2"),
        ("1.003000", "CAN1", "1", "Eyes", "Right Eye Target", "CI", "2"),
        ("1.004123", "CAN0", "1", "Eyes", "Right Eye Joint Sensor", "SO", "0.00001"),
        ("1.005000", "CAN0", "1", "Eyes", "Right Eye Joint Sensor", "SO", "-1200"),
        ("1.006000", "CAN0", "1", "Eyes", "Right Eye Gain", "PAR", "100000000000000000000"),
    ]
    assert values_path(path).name == "run.asc.values.csv"


def test_a_lost_boards_values_are_marked_stale_until_they_come_again(tmp_path: Path,
                                                                    ) -> None:
    path = tmp_path / "run.log"
    with RunRecorder(path) as rec:
        rec.value(1.0, "CAN0", 3, "Eyes", "Right Eye Joint Sensor", "SO", 7)
        rec.value(1.0, "CAN0", 3, "Eyes", "Right Eye Target", "CI", 5)
        rec.value(1.0, "CAN0", 1, "Neck", "Neck Yaw Joint Sensor", "SO", 1)
        assert rec.lost(1.5, "CAN0", 3) == 2  # a row for each of its edges so far
        assert not rec.fresh(1.6, "CAN0", 1, "Neck", "Neck Yaw Joint Sensor", "SO", 1)
        assert rec.fresh(1.7, "CAN0", 3, "Eyes", "Right Eye Joint Sensor", "SO", 7)
        assert not rec.fresh(1.8, "CAN0", 3, "Eyes", "Right Eye Joint Sensor", "SO", 7)
        assert rec.value(1.9, "CAN0", 3, "Eyes", "Right Eye Target", "CI", 5)  # same, valid
    got = [(r["timestamp"], r["name"], r["value"], r["valid"])
           for r in rows(values_path(path))]
    assert got == [("1.000000", "Right Eye Joint Sensor", "7", "1"),
                   ("1.000000", "Right Eye Target", "5", "1"),
                   ("1.000000", "Neck Yaw Joint Sensor", "1", "1"),
                   ("1.500000", "Right Eye Joint Sensor", "7", "0"),
                   ("1.500000", "Right Eye Target", "5", "0"),
                   ("1.700000", "Right Eye Joint Sensor", "7", "1"),
                   ("1.900000", "Right Eye Target", "5", "1")]
    values = read_values(values_path(path))
    assert values.series["Eyes/Right Eye Joint Sensor"].stale == [(1.5, 1.7)]
    assert values.series["Eyes/Right Eye Joint Sensor"].points == [(1.0, 7), (1.7, 7)]
    assert values.series["Neck/Neck Yaw Joint Sensor"].stale == []


def test_values_files_of_earlier_versions_are_all_valid_and_a_bad_flag_is_named(
        tmp_path: Path) -> None:
    old = tmp_path / "old.values.csv"
    old.write_text("timestamp,bus,board,prefix,name,kind,value\n"
                   "1.0,CAN0,3,Eyes,Right Eye Target,CI,5\n")
    s = read_values(old).series["Eyes/Right Eye Target"]
    assert s.points == [(1.0, 5)] and s.stale == []
    bad = tmp_path / "bad.values.csv"
    bad.write_text(",".join(VALUES_HEADER) + "\n1.0,CAN0,3,Eyes,Right Eye Target,CI,5,yes\n")
    with pytest.raises(InputError, match=r"bad.values.csv:2: valid: 'yes' is not 0 or 1"):
        read_values(bad)


def test_names_with_commas_and_quotes_survive_the_csv(tmp_path: Path) -> None:
    path = tmp_path / "run.log"
    with RunRecorder(path) as rec:
        rec.value(0.5, "CAN0", 3, 'Arm "L"', "Elbow, inner", "SO", 7)
    values = read_values(values_path(path))
    assert list(values.series) == ['Arm "L"/Elbow, inner']


# ----------------------------------------------------------------------------- errors
@pytest.mark.parametrize("name", ["run.xyz", "run", "run.blf.gz", "run.mp4"])
def test_unsupported_extension_is_refused_before_anything_is_written(
        tmp_path: Path, name: str) -> None:
    with pytest.raises(InputError) as e:
        RunRecorder(tmp_path / name)
    assert e.value.key == "record"
    assert ".asc" in str(e.value) and ".blf" in str(e.value) and ".log" in str(e.value)
    assert os.listdir(tmp_path) == []


def test_missing_directory_is_refused(tmp_path: Path) -> None:
    with pytest.raises(InputError) as e:
        RunRecorder(tmp_path / "no" / "such" / "run.blf")
    assert e.value.key == "record" and "does not exist" in str(e.value)
    assert os.listdir(tmp_path) == []


def test_a_directory_as_file_is_refused(tmp_path: Path) -> None:
    (tmp_path / "run.asc").mkdir()
    with pytest.raises(InputError):
        RunRecorder(tmp_path / "run.asc")
    assert os.listdir(tmp_path) == ["run.asc"]


def test_input_error_in_the_block_discards_other_errors_keep(tmp_path: Path) -> None:
    path = tmp_path / "run.asc"
    with pytest.raises(InputError), RunRecorder(path) as rec:
        rec.on_message_received(can.Message(arbitration_id=1, channel="CAN0"))
        raise InputError("bad tree")
    assert os.listdir(tmp_path) == []  # exit code 3: nothing written
    with pytest.raises(RuntimeError), RunRecorder(path) as rec:
        rec.on_message_received(can.Message(arbitration_id=1, channel="CAN0"))
        raise RuntimeError("the run failed")
    assert [m.arbitration_id for m in can.LogReader(path)] == [1]


def test_close_is_idempotent_and_late_frames_are_ignored(tmp_path: Path) -> None:
    path = tmp_path / "run.csv"
    rec = RunRecorder(path)
    rec.on_message_received(can.Message(arbitration_id=5))
    rec.close()
    rec.close()
    rec.on_message_received(can.Message(arbitration_id=6))  # a reader still delivering
    with pytest.raises(ValueError):
        rec.value(0.0, "CAN0", 1, "Eyes", "X", "SO", 1)
    assert rec.frames == 1
    assert [m.arbitration_id for m in can.LogReader(path)] == [5]


def test_existing_file_is_replaced_only_by_a_complete_recording(tmp_path: Path) -> None:
    path = tmp_path / "run.log"
    path.write_text("old\n")
    path.chmod(0o640)
    rec = RunRecorder(path)
    rec.on_message_received(can.Message(arbitration_id=7))
    assert path.read_text() == "old\n"
    rec.close()
    assert [m.arbitration_id for m in can.LogReader(path)] == [7]
    assert path.stat().st_mode & 0o777 == 0o640


def test_write_failure_removes_the_partial_files(tmp_path: Path) -> None:
    path = tmp_path / "run.asc"
    rec = RunRecorder(path)
    assert rec._frames is not None
    writer = rec._frames._writer
    assert writer is not None

    def fail(msg: can.Message) -> None:
        raise OSError(28, "No space left on device")

    writer.on_message_received = fail  # type: ignore[method-assign]
    rec.on_message_received(can.Message(arbitration_id=1))  # never raises in a reader
    deadline = time.monotonic() + 5  # the writer's thread meets the failure
    while rec._frames.failure is None and time.monotonic() < deadline:
        time.sleep(0.01)
    with pytest.raises(LogError, match="No space left"):
        rec.check()  # what the loop asks every cycle
    with pytest.raises(LogError, match="No space left"):
        rec.value(0.0, "CAN0", 1, "Eyes", "X", "SO", 1)
    with pytest.raises(LogError, match="No space left"):
        rec.close()
    assert os.listdir(tmp_path) == []


# ----------------------------------------------------------------------------- plot
@pytest.fixture
def recording(tmp_path: Path) -> Iterator[Path]:
    """A values file of two boards: the eyes' target and sensor, and two 'Target's."""
    path = tmp_path / "run.blf"
    with RunRecorder(path) as rec:
        for i in range(101):
            t = 500.0 + i * 0.01
            rec.value(t, "CAN0", 1, "Eyes", "Right Eye Target", "CI",
                      Decimal(i // 20) / 4)
            rec.value(t, "CAN0", 1, "Eyes", "Right Eye Joint Sensor", "SO",
                      Decimal(min(i, 60)) / 100)
            rec.value(t, "CAN0", 2, "Neck", "Target", "CI", i // 50)
            rec.value(t, "CAN1", 1, "Hip", "Target", "CI", -(i // 25))
    yield values_path(path)


def test_plot_png_is_written_by_matplotlib(recording: Path, tmp_path: Path) -> None:
    out = tmp_path / "plot.png"
    code, stdout, err = run(str(recording), "Eyes/Right Eye Target", "Right Eye Joint Sensor",
                            "-o", str(out))
    assert code == 0, err
    assert stdout == "" and "wrote" in err
    data = out.read_bytes()
    assert data.startswith(b"\x89PNG\r\n\x1a\n")
    assert b"IHDR" in data[:16 + 8] and b"Matplotlib" in data
    assert int.from_bytes(data[16:20], "big") == 1000  # width at 100 dpi
    assert not [n for n in os.listdir(tmp_path) if n.endswith(".tmp")]


def test_plot_png_bad_target_writes_nothing(recording: Path, tmp_path: Path) -> None:
    code, _, err = run(str(recording), "Neck/Target", "-o", str(tmp_path / "no" / "p.png"))
    assert code == 3 and "does not exist" in err
    code, _, err = run(str(recording), "Neck/Target", "-o", str(tmp_path / "p.pdf"))
    assert code == 3 and "*.png" in err
    assert sorted(os.listdir(tmp_path)) == ["run.blf", "run.blf.values.csv"]


def test_plot_in_the_terminal(recording: Path) -> None:
    code, out, err = run(str(recording), "Right Eye Target", "Neck/Target")
    assert code == 0, err
    assert "Eyes/Right Eye Target" in out and "Neck/Target" in out
    assert "\x1b[" not in out  # not a terminal: no colours
    lines = out.rstrip("\n").split("\n")
    assert len(lines) == 30 and max(len(line) for line in lines) <= 100


def test_plot_json_gives_the_changes(recording: Path) -> None:
    code, out, err = run(str(recording), "Neck/Target", "Eyes/Right Eye Target", "--json")
    assert code == 0, err
    data = json.loads(out)
    assert list(data) == ["Neck/Target", "Eyes/Right Eye Target"]
    assert data["Neck/Target"] == [[0.0, 0], [0.5, 1], [1.0, 2]]
    assert data["Eyes/Right Eye Target"] == [[0.0, 0], [0.2, 0.25], [0.4, 0.5], [0.6, 0.75],
                                             [0.8, 1], [1.0, 1.25]]


def test_plot_unknown_name_suggests_the_closest(recording: Path) -> None:
    code, out, err = run(str(recording), "Right Eye Targt")
    assert code == 3 and out == ""
    assert "closest: 'Eyes/Right Eye Target'" in err and "Traceback" not in err
    code, _, err = run(str(recording), "Eyes/Right Eye Sensor")
    assert code == 3 and "'Eyes/Right Eye Joint Sensor'" in err


def test_plot_ambiguous_bare_name_names_the_qualified_ones(recording: Path) -> None:
    code, out, err = run(str(recording), "Target")
    assert code == 3 and out == ""
    assert "'Neck/Target'" in err and "'Hip/Target'" in err and "PREFIX/NAME" in err
    code, out, _ = run(str(recording), "Hip/Target", "--json")
    assert code == 0 and list(json.loads(out)) == ["Hip/Target"]


@pytest.mark.parametrize(("text", "line", "what"), [
    ("timestamp,bus,board,prefix,name,kind,value\n1.0,CAN0,1,E,X,SO,1\n"
     "1.1,CAN0,1,E,X,SO,one\n", 3, "value: 'one'"),
    ("timestamp,bus,board,prefix,name,kind,value\nsoon,CAN0,1,E,X,SO,1\n", 2,
     "timestamp: 'soon'"),
    ("timestamp,bus,board,prefix,name,kind,value\n1.0,CAN0,x,E,X,SO,1\n", 2, "board: 'x'"),
    ("timestamp,bus,board,prefix,name,kind,value\n1.0,CAN0,1,E,X,OUT,1\n", 2, "kind"),
    ("timestamp,bus,board,prefix,name,kind,value\n1.0,CAN0,1,E\n", 2, "fields"),
    ("time,bus,board,prefix,name,kind,value\n1.0,CAN0,1,E,X,SO,1\n", 1, "timestamp"),
    ("", 1, "empty"),
])
def test_plot_malformed_csv_names_file_and_line(tmp_path: Path, text: str, line: int,
                                                what: str) -> None:
    path = tmp_path / "bad.values.csv"
    path.write_text(text)
    code, out, err = run(str(path), "X")
    assert code == 3 and out == ""
    assert f"{path}:{line}: " in err and what in err and "Traceback" not in err


def test_plot_missing_file(tmp_path: Path) -> None:
    code, _, err = run(str(tmp_path / "none.values.csv"), "X")
    assert code == 3 and "none.values.csv" in err


def test_plot_without_the_extra_says_how_to_install(
        recording: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    for module in ("matplotlib", "matplotlib.figure", "matplotlib.backends.backend_agg",
                   "plotext"):
        monkeypatch.setitem(__import__("sys").modules, module, None)
    code, _, err = run(str(recording), "Neck/Target", "-o", str(tmp_path / "p.png"))
    assert code == 3 and PLOT_EXTRA in " ".join(err.split())
    code, _, err = run(str(recording), "Neck/Target")
    assert code == 3 and "ucom-tools[plot]" in err
    code, out, _ = run(str(recording), "Neck/Target", "--json")  # JSON needs neither
    assert code == 0 and json.loads(out)["Neck/Target"][0] == [0.0, 0]
    assert not (tmp_path / "p.png").exists()
