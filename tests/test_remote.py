"""The run-time part (RemotePart, ``ucom remote``) against the virtual fleet, over the
real code path: the mapping check, defaults on the boards, values by robot-wide name,
the safe end, loss, recording."""

from __future__ import annotations

import csv
import json
import re
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest
from click.testing import CliRunner

from tests.helpers import HeldBack, served_in_process
from tests.runtime_rig import programmed, robot_of
from ucom_tools.cli.main import cli
from ucom_tools.config.attrtree.robot import bind
from ucom_tools.edgelists.armar3 import SPEC
from ucom_tools.edgelists.model import EdgeKind
from ucom_tools.errors import InputError, UcomError
from ucom_tools.ops.remote import RemotePart
from ucom_tools.ops.remote.report import MappingError
from ucom_tools.virtual.bus.loss import LossyBus
from ucom_tools.wire import mca
from ucom_tools.wire.fpga import Reg
from ucom_tools.wire.ids import Function, decode_id, seq

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture
def part() -> Iterator[RemotePart]:
    fleet = programmed("armar3")
    robot = robot_of(fleet)
    p = RemotePart(robot, bind(robot.topology))
    yield p
    p.close()
    robot.close()


def _runtime(part: RemotePart, bus: str, n: int):
    fleet = part.robot.buses[bus].bus.fleet  # type: ignore[attr-defined]
    return fleet.boards[bus][n - 1].application.runtime


# ---------------------------------------------------------------------- the API
def test_start_writes_the_tree_defaults_and_they_read_back(part) -> None:
    report = part.start()
    assert report.ok and len(report.boards) == 11
    trees = bind(part.robot.topology)
    eyes = trees.board("CAN0", 2)
    x = part.exchanges["CAN0"]
    records = x.configured[3].edges.par
    live = x.mca.dump(seq(3), mca.Kind.PAR, 0, len(records), records)
    for e in eyes.edges:
        if e.kind.value == "PAR" and e.default is not None:
            spec = SPEC.of(EdgeKind.PAR)[e.index - 33]
            assert live[e.index - 33] == spec.raw(e.default.text), e.unique
    # PAR values by name: what was written, in the edge's unit
    gain = SPEC.of(EdgeKind.PAR)[5]
    assert part["RightEye P"] == gain.value(gain.raw(eyes.edge("RightEye P").default.text))


def test_a_value_set_by_name_moves_the_right_axis_of_the_right_board(part) -> None:
    part.start()
    part["Right Eye Target"] = 1000
    part.run(0.6)
    assert abs(part["Right Eye Joint Sensor"] - 1000) <= 5
    assert part["Left Eye Joint Sensor"] == 0
    assert part["Neck Pitch Joint Sensor"] == 0
    eyes = part.robot.buses["CAN0"].bus.fleet.boards["CAN0"][2]  # type: ignore[attr-defined]
    assert eyes.fpga.registers[Reg.OUTPUT_ENABLE] != 0
    assert part.stats.missed == 0 and part.stats.cycles >= 600


def test_names_are_checked_before_anything_is_sent(part) -> None:
    part.start()
    with pytest.raises(InputError, match="did you mean 'Right Eye Target'"):
        part["Right Eye Targt"] = 1
    with pytest.raises(InputError, match="Eyes/AD Channel 6"):
        part["AD Channel 6"]
    with pytest.raises(InputError, match="outside"):
        part["Right Eye Target"] = 40000
    with pytest.raises(InputError, match="decimal places"):
        part["RightEye P"] = 0.0000001
    with pytest.raises(InputError, match="is SO; only CI/PAR edges"):
        part["Right Eye Joint Sensor"] = 3
    assert part.exchanges["CAN0"].ci[(3, 3)] == 0


def test_a_tree_with_a_renamed_edge_or_for_another_program_starts_nothing(tmp_path) -> None:
    fleet = programmed("armar3")
    robot = robot_of(fleet)
    trees = bind(robot.topology)
    text = (ROOT / "attribute_trees/armar3/head_right.tree").read_text()
    renamed = tmp_path / "head_right.tree"
    renamed.write_text(text.replace("3:MotorA Target ==>", "3:MotorA Targets ==>"))
    from ucom_tools.ops.remote.part import robot_trees
    own = robot_trees(robot, [str(renamed)])
    part = RemotePart(robot, own)
    try:
        report = part.check()
        bad = [b for b in report.boards if not b.ok]
        assert [(b.bus, b.board) for b in bad] == [("CAN0", 3)]
        assert bad[0].differences[0].line == text.splitlines().index(
            "      3:MotorA Target ==> Right Eye Target") + 1
        with pytest.raises(MappingError):
            part.start()
        assert all(rt.state is mca.RunState.STOPPED for b in fleet.boards.values() for rt in
                   [x.application.runtime for x in b])
        # --force starts the ten others
        part.start(force=True)
        part.run(0.05)
        states = {(bus, n + 1): b.application.runtime.state
                  for bus, bs in fleet.boards.items() for n, b in enumerate(bs)}
        assert states.pop(("CAN0", 3)) is mca.RunState.STOPPED
        assert set(states.values()) == {mca.RunState.RUNNING}
    finally:
        part.close()
        robot.close()
    assert trees.ok


def test_stop_and_a_vanished_pc_leave_no_joint_driving(part) -> None:
    part.start()
    part["Neck Yaw Target"] = 3000
    part.run(0.05)
    neck = part.robot.buses["CAN0"].bus.fleet.boards["CAN0"][0]  # type: ignore[attr-defined]
    assert neck.fpga.registers[Reg.OUTPUT_ENABLE] == 0b111
    assert part.stop() == []
    assert neck.application.runtime.state is mca.RunState.STOPPED
    assert neck.fpga.registers[Reg.OUTPUT_ENABLE] == 0
    # start again, then the PC stops calling cycle(): the watchdog stops every board
    part.report = None
    part.start()
    part.run(0.05)
    fleet = neck.bus.clock
    with fleet.lock:
        fleet.run_until(fleet.now + 100_000)
    for bs in part.robot.buses["CAN0"].bus.fleet.boards.values():  # type: ignore[attr-defined]
        for b in bs:
            assert b.application.runtime.state is mca.RunState.LATCHED
            assert b.fpga.registers[Reg.OUTPUT_ENABLE] == 0


def test_one_percent_frame_loss_does_not_stop_the_exchange() -> None:
    fleet = programmed("armar3")
    seeds = iter(range(100))
    robot = robot_of(fleet, wrap=lambda bus: LossyBus(bus, loss=0.01, seed=next(seeds)))
    part = RemotePart(robot, bind(robot.topology))
    try:
        assert part.start().ok
        part["Right Eye Target"] = 800
        part["Left Eye Target"] = -800
        part.run(1.0)
        assert abs(part["Right Eye Joint Sensor"] - 800) <= 5
        assert abs(part["Left Eye Joint Sensor"] + 800) <= 5
        states = {b.application.runtime.state for bs in fleet.boards.values() for b in bs}
        assert states == {mca.RunState.RUNNING}
        lost = sum(sum(h.bus.dropped.values()) for h in robot.buses.values())  # type: ignore[attr-defined]
        assert lost > 100  # it did lose frames
    finally:
        part.close()
        robot.close()


def test_values_are_reported_as_they_change(part) -> None:
    seen: list[tuple[float, str, object]] = []
    part.on_values = lambda t, ref, v: seen.append((t, ref.qualified, v))
    part.start()
    part["Right Eye Target"] = 300
    part.run(0.3)
    sensor = [v for _, name, v in seen if name == "Eyes/Right Eye Joint Sensor"]
    assert sensor[0] == 0 and abs(sensor[-1] - 300) <= 5
    assert ("Eyes/Right Eye Target", 300) in [(n, v) for _, n, v in seen]
    times = [t for t, name, _ in seen if name == "Eyes/Right Eye Joint Sensor"]
    assert times == sorted(times)


# ---------------------------------------------------------------------- the command
@pytest.fixture(scope="module")
def flashed(tmp_path_factory) -> Path:
    state = tmp_path_factory.mktemp("armar3")
    r = CliRunner().invoke(cli, ["flash", str(ROOT / "firmware_images/armar3.fl.S"),
                                 "--virtual", "armar3", "--state", str(state)])
    assert r.exit_code == 0, r.stderr
    return state


def ucom(*args: str) -> tuple[int, str, str]:
    r = CliRunner().invoke(cli, list(args))
    return r.exit_code, r.stdout, r.stderr


def test_run_for_json_has_every_edge_and_the_loop_figures(flashed) -> None:
    code, out, err = ucom("remote", "run", "armar3", "--virtual", "armar3", "--state",
                          str(flashed), "--for", "0.4", "--set", "Right Eye Target=700",
                          "--set", "Eyes/RightEye I=0.0004", "--json")
    assert code == 0, err
    data = json.loads(out)
    assert data["started"] and not data["interrupted"] and data["not_stopped"] == []
    assert len(data["boards"]) == 11
    eyes = next(b for b in data["boards"] if b["prefix"] == "Eyes")
    values = {e["name"]: (e["kind"], e["value"]) for e in eyes["edges"]}
    texts = {e["name"]: e["text"] for e in eyes["edges"]}
    assert len(values) == 71
    assert values["Right Eye Target"] == ("CI", 700)  # JSON numbers, typed
    assert values["RightEye I"] == ("PAR", 0.0004) and texts["RightEye I"] == "0.000400"
    assert abs(values["Right Eye Joint Sensor"][1] - 700) <= 20
    run = data["run"]
    assert run["cycles"] >= 400 and run["missed"] == 0 and run["virtual_time"]
    # the loop's rate over its run: the boards' stop afterwards is no time of the loop's
    assert run["rate_hz"] == pytest.approx(1000.0, abs=3.0)
    assert 0.6 < run["bus_load"]["CAN0"] < 0.7
    assert run["planned_load"]["CAN0"]["nominal"] == pytest.approx(0.6328, abs=1e-4)


def test_the_loop_asks_for_a_short_time_slice_on_real_buses_and_gives_it_back(
        flashed, tmp_path) -> None:
    """At normal priority over socketcand the loop's thread runs with a 0.1 ms time slice
    where the kernel grants one (said in the run's figures), and has its own back after
    the run; in virtual time nothing waits for the wall, and no slice is asked for."""
    import shutil
    import threading

    from ucom_tools.ops.realtime import short_slice, thread_slice
    probe: dict[str, int | None] = {}
    t = threading.Thread(target=lambda: probe.update(given=short_slice()))
    t.start()
    t.join(timeout=10)
    granted = probe["given"] is not None  # the probe's thread ended with its slice
    state = Path(shutil.copytree(flashed, tmp_path / "state"))
    before = thread_slice()
    with served_in_process("armar3", state) as (_, port):
        code, out, err = ucom("remote", "run", "armar3", "-i", "socketcand", "--host",
                              "127.0.0.1", "--port", str(port), "--bus", "CAN0", "--for",
                              "0.3", "--json")
    assert code == 0, err
    assert json.loads(out)["run"]["realtime"] == (
        "normal, time slice 0.1 ms" if granted else "normal")
    assert thread_slice() == before  # this thread ran the loop: its slice is back
    code, out, err = ucom("remote", "run", "armar3", "--virtual", "armar3", "--state",
                          str(state), "--for", "0.1", "--json")
    assert code == 0, err
    assert json.loads(out)["run"]["realtime"] == "normal"


def test_run_text_says_what_the_joints_did(flashed) -> None:
    code, out, err = ucom("remote", "run", "armar3", "--virtual", "armar3", "--state",
                          str(flashed), "--for", "0.5", "--set", "Neck Yaw Target=-400")
    assert code == 0, err
    line = next(x for x in out.splitlines() if "Neck Yaw Joint Sensor" in x)
    last = int(line.split("│")[4])
    assert abs(last + 400) <= 5
    assert "cycles at" in out and "0 missed" in out
    assert "63.3% of the bus" in err  # the estimate before the start


def test_run_refuses_bad_names_values_and_periods_before_anything_runs(flashed) -> None:
    base = ("remote", "run", "armar3", "--virtual", "armar3", "--state", str(flashed),
            "--for", "0.1")
    code, _, err = ucom(*base, "--set", "Rigth Eye Target=1")
    assert code == 3 and "did you mean 'Right Eye Target'" in err
    code, _, err = ucom(*base, "--set", "Right Eye Target=99999")
    assert code == 3 and "outside" in err and "-32768..32767" in err
    code, _, err = ucom(*base, "--set", "Right Eye Target")
    assert code == 3 and "NAME=VALUE" in err
    code, _, err = ucom(*base, "--period", "Voltag A=1")
    assert code == 3 and "Voltage A" in err
    # every SO value every cycle: more than the bus can carry
    everything = [f"--period=Encoder {i}=1" for i in range(6)] + [
        f"--period=Voltage {a}=1" for a in "ABC"] + [
        f"--period=Motor{a} Reset Answer=1" for a in "ABC"] + [
        f"--period=Motor {a} Settled=1" for a in "ABC"]
    code, _, err = ucom(*base, *everything)
    assert code == 3 and "of the bus" in err


def test_check_lists_every_difference_of_a_tree_for_another_program(flashed, tmp_path) -> None:
    # a robot whose eyes board is given a LAURON-IV leg's tree
    topo = (ROOT / "ucom_tools/config/topologies/armar3.toml").read_text()
    topo = topo.replace('tree = "attribute_trees/armar3/head_right.tree"',
                        f'tree = "{ROOT}/attribute_trees/lauron4/front_left_leg.tree"')
    topo = topo.replace('tree = "attribute_trees/', f'tree = "{ROOT}/attribute_trees/')
    path = tmp_path / "armar3_wrong.toml"
    path.write_text(topo)
    code, out, err = ucom("remote", "check", "--virtual", str(path), "--state", str(flashed),
                          "--json")
    # the state directory was made for the bundled armar3: same boards (serials), so the
    # flashed programs are there
    data = json.loads(out)
    assert code == 1
    bad = [b for b in data["boards"] if not b["ok"]]
    assert [b["board"] for b in bad] == [3] and bad[0]["bus"] == "CAN0"
    assert len(bad[0]["differences"]) > 10  # every index listed
    assert all(d["line"] for d in bad[0]["differences"][:5])
    code, out, err = ucom("remote", "run", "--virtual", str(path), "--state", str(flashed),
                          "--for", "0.1")
    assert code == 1 and "do not match their trees" in err


def test_record_writes_a_log_python_can_reads_and_a_values_csv(flashed, tmp_path) -> None:
    log = tmp_path / "run.asc"
    code, _, err = ucom("remote", "run", "armar3", "--virtual", "armar3", "--state",
                        str(flashed), "--for", "0.2", "--set", "Right Eye Target=200",
                        "--record", str(log))
    assert code == 0, err
    frames = list(can.LogReader(str(log)))
    assert len(frames) > 1000
    functions = {f.arbitration_id >> 6 for f in frames}
    assert {13, 14, 20, 21, 23, 25, 26} <= functions  # CI maps and SO maps, the set-up
    with (tmp_path / "run.asc.values.csv").open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    sensor = [r for r in rows if r["name"] == "Right Eye Joint Sensor"]
    assert sensor and sensor[0]["prefix"] == "Eyes" and sensor[0]["kind"] == "SO"
    assert abs(int(sensor[-1]["value"]) - 200) <= 20
    assert any(r["name"] == "Right Eye Target" and r["value"] == "200" for r in rows)


def test_recorded_values_set_and_sensed_share_the_frames_time_base(flashed, tmp_path,
                                                                  ) -> None:
    log = tmp_path / "run.blf"
    code, _, err = ucom("remote", "run", "armar3", "--virtual", "armar3", "--state",
                        str(flashed), "--for", "0.3", "--set", "Right Eye Target=200",
                        "--record", str(log))
    assert code == 0, err
    with (tmp_path / "run.blf.values.csv").open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    times = [float(r["timestamp"]) for r in rows]
    target = next(float(r["timestamp"]) for r in rows if r["name"] == "Right Eye Target")
    assert min(times) <= target <= max(times) and max(times) - min(times) < 1.0
    frames = [f.timestamp for f in can.LogReader(str(log))]
    assert frames[0] <= target <= frames[-1]  # the set is where its frame is


def test_the_readme_example_moves_an_eye(flashed, capsys) -> None:
    readme = (ROOT / "README.md").read_text()
    block = next(b.split("```", 1)[0] for b in readme.split("```python\n")[1:]
                 if "RemotePart.open" in b)
    exec(compile(block.replace('"/tmp/a3"', repr(str(flashed))), "README.md", "exec"), {})
    printed = capsys.readouterr().out.strip()
    assert abs(int(printed) - 1000) <= 2


# ---------------------------------------------------------------------- the live view
def test_the_live_view_sets_values_by_name_and_quits(part) -> None:
    from prompt_toolkit.input import create_pipe_input
    from prompt_toolkit.output import DummyOutput

    from ucom_tools.cli.live import LiveView

    part.start()
    with create_pipe_input() as pipe:
        view = LiveView.local(part, pt_input=pipe, pt_output=DummyOutput())
        pipe.send_text("Right Eye Target 500\r")
        pipe.send_text("set Eyes/RightEye I=0.0004\r")
        pipe.send_text("Right Eye Targt 1\r")  # a typo: a message, nothing set
        pipe.send_text("q\r")
        view.run()
    assert part["Right Eye Target"] == 500
    assert str(part["RightEye I"]) == "0.000400"
    assert view.message.startswith("! no edge called 'Right Eye Targt'")
    assert part.stats.cycles > 0  # the loop ran beside the view
    text = view.render(200)
    assert "Right Eye Joint Sensor" in text and "Eyes - CAN0 board 3" in text


def test_names_complete_and_commands_parse() -> None:
    from prompt_toolkit.completion import CompleteEvent
    from prompt_toolkit.document import Document

    from ucom_tools.cli.live import NameCompleter, parse_command

    c = NameCompleter(["Right Eye Target", "Right Eye Target Vel", "Eyes/AD Channel 6"])
    got = [x.text for x in c.get_completions(Document("set right eye t"), CompleteEvent())]
    assert got == ["Right Eye Target ", "Right Eye Target Vel "]
    assert [x.text for x in c.get_completions(Document("chan"), CompleteEvent())] == [
        "Eyes/AD Channel 6 "]
    assert parse_command("set Right Eye Target 1000") == ("Right Eye Target", "1000")
    assert parse_command("Right Eye Target=-5") == ("Right Eye Target", "-5")
    assert parse_command("  ") is None
    with pytest.raises(ValueError):
        parse_command("Target")


def test_check_with_a_tree_file_of_ones_own_names_its_line(flashed, tmp_path) -> None:
    text = (ROOT / "attribute_trees/armar3/head_right.tree").read_text()
    mine = tmp_path / "eyes.tree"
    mine.write_text(text.replace("22:AD Channel 6 ==>", "22:AD Channel 5 ==>"))
    code, out, err = ucom("remote", "check", str(mine), "--virtual", "armar3", "--state",
                          str(flashed))
    assert code == 1
    line = text.splitlines().index("      22:AD Channel 6 ==> AD Channel 6") + 1
    assert f"{mine}:{line}: index 22: the tree maps SO 'AD Channel 5'" in "".join(
        out.splitlines())
    code, _, err = ucom("remote", "check", str(ROOT / "attribute_trees/lauron4/camera_head"
                                                      ".tree"), "--virtual", "armar3",
                        "--state", str(flashed))
    assert code == 3 and "CameraHead" in err and "no board of ARMAR-III has prefix" in err


def test_the_summary_marks_a_value_the_board_clipped_to_its_encoding(flashed) -> None:
    code, out, err = ucom("remote", "run", "armar3", "--virtual", "armar3", "--state",
                          str(flashed), "--for", "0.3", "--set", "Neck Yaw Target=-2000",
                          "--set", "Right Eye Target=100")
    assert code == 0, err
    rows = {line.split("│")[2].strip(): line for line in out.splitlines() if "│" in line}
    assert "-32768*" in rows["Neck Yaw Velocity"]  # faster than int16 counts/s can say
    assert "*" not in rows["Right Eye Joint Sensor"]  # a small move: nothing clipped
    assert "*" not in rows["Neck Yaw Voltage"]  # 0 V is its range's end, not clipping
    assert "the most the edge's encoding can carry" in out


def test_a_loop_that_stalls_past_the_watchdog_is_told_which_boards_stopped(part) -> None:
    from ucom_tools.wire.codes import ErrorCode
    part.start()
    part["Right Eye Target"] = 300
    for _ in range(20):
        part.cycle()
    assert part.events == []  # cycling: nothing to report
    for h in part.robot.buses.values():  # the PC's program stalls 200 ms: no MCA Alive
        h.link.dispatcher.pump(h.link.clock() + 0.2)
    assert part.stats.longest_gap_s == pytest.approx(0.001)  # one period each so far
    part.cycle()
    assert part.stats.longest_gap_s >= 0.2  # the loop was away: no MCA Alive meanwhile
    stopped = {(e.bus, e.board) for e in part.events if e.stopped_motors}
    configured = {(bus, n) for bus, x in part.exchanges.items() for n in x.configured}
    assert stopped == configured
    e = next(e for e in part.events if e.stopped_motors)
    assert e.code is ErrorCode.WATCHDOG and e.text.startswith(
        "its watchdog stopped every motor: no MCA Alive for ")
    assert 0.05 <= e.time <= 0.3 and e.where.startswith(f"{e.bus} board {e.board}")


def test_run_exits_1_naming_the_boards_whose_watchdog_stopped_them(flashed, monkeypatch,
                                                                   ) -> None:
    from ucom_tools.virtual.canbus import VirtualUcomBus
    from ucom_tools.wire.ids import Function
    cyclic = {"n": 0}

    def stalled(ident: int) -> bool:  # the PC stops sending its cycles after a while:
        if ident >> 6 == Function.MCA_ALIVE or (  # from the 200th frame of the loop on
                ident >> 6 == Function.MCA_CONTROLLER_INPUT and ident & 0x20):  # (CI maps
            cyclic["n"] += 1  # and MCA Alive) none reaches the bus; requests still do
            return cyclic["n"] >= 200
        return False

    def patch(name: str) -> None:  # the bus's way in for the PC's frames, both of them
        real = getattr(VirtualUcomBus, name, None)
        if real is None:
            return

        def send(self: VirtualUcomBus, *args: object, **kwargs: object) -> None:
            first = args[0]
            ident = first.arbitration_id if isinstance(first, can.Message) else first
            assert isinstance(ident, int)
            if not stalled(ident):
                real(self, *args, **kwargs)
        monkeypatch.setattr(VirtualUcomBus, name, send)

    patch("send")
    patch("send_data")
    code, out, err = ucom("remote", "run", "armar3", "--virtual", "armar3", "--state",
                          str(flashed), "--for", "0.3", "--json")
    assert code == 1, err
    events = json.loads(out)["events"]
    assert {e["where"] for e in events if e["stopped_motors"]} >= {
        "CAN0 board 3 (head right)", "CAN3 board 1 (platform)"}
    assert all(e["error"] == "WATCHDOG" for e in events if e["stopped_motors"])
    # the loop kept its deadlines (the frames were lost on the way): not blamed on it
    assert json.loads(out)["run"]["longest_gap_ms"] == pytest.approx(1.0)
    code, out, err = ucom("remote", "run", "armar3", "--virtual", "armar3", "--state",
                          str(flashed), "--for", "0.3")
    assert code == 1
    assert "ucom: CAN0 board 3 (head right) at " in err
    assert "its watchdog stopped every motor: no MCA Alive for " in err
    assert "did not run for" not in err


@pytest.mark.parametrize("cut", ["ctrl-c", "error"])
def test_a_start_cut_short_stops_the_boards_it_had_started(cut: str) -> None:
    """Ctrl-C (or an error) while the boards are started one by one: the part is
    running from the first MCA Start on, so its stop (``close``, the ``with`` block's
    end) stops the boards already started instead of leaving them to their watchdog
    (over a loaded machine's socketcand, a Ctrl-C in that window left them latched)."""
    fleet = programmed("armar3")
    fired = {"n": 0}

    def wrap(bus: can.BusABC) -> can.BusABC:
        def drop(direction: str, msg: can.Message) -> bool:  # board 2's start on CAN0
            if (direction == "tx" and not fired["n"] and not msg.is_extended_id
                    and decode_id(msg.arbitration_id) == (Function.MCA_START, seq(2))
                    and msg.data[:1] == bytes([mca.StartOp.START])):
                fired["n"] += 1
                raise KeyboardInterrupt if cut == "ctrl-c" else can.CanOperationError("cut")
            return False
        return LossyBus(bus, drop=drop)
    robot = robot_of(fleet, wrap=wrap)
    part = RemotePart(robot, bind(robot.topology))
    try:
        with pytest.raises((KeyboardInterrupt, UcomError, can.CanError)):
            part.start()
        assert fired["n"] == 1
        first = fleet.boards["CAN0"][0].application.runtime
        assert first is not None and first.state is mca.RunState.RUNNING  # started
        assert part.stop() == []
        for boards in fleet.boards.values():
            for board in boards:
                runtime = board.application.runtime if board.application else None
                assert runtime is None or runtime.state is mca.RunState.STOPPED, board
    finally:
        part.close()
        robot.close()


def test_a_slow_stop_of_one_board_does_not_let_the_others_watchdogs_fire() -> None:
    """The boards are stopped one by one, each asked and answered: when the first one's
    answer takes longer than the watchdog time (a transport with a margin to match), MCA
    Alive still goes out meanwhile, so the others are stopped by the PC, not by their
    watchdog."""
    fleet = programmed("armar3")
    armed = {"on": False}
    late: dict[str, bool] = {}  # each bus: its board 1's answer held back

    def wrap(bus: can.BusABC) -> can.BusABC:
        name = bus.channel_info

        def hold(msg: can.Message) -> bool:  # board 1's first MCA Ready once armed
            if (armed["on"] and name not in late and not msg.is_extended_id
                    and decode_id(msg.arbitration_id) == (Function.MCA_READY, seq(1))):
                late[name] = True
                return True
            return False
        return HeldBack(bus, hold, 0.08)  # 80 ms of bus time before it comes
    robot = robot_of(fleet, wrap=wrap)
    for h in robot.buses.values():
        h.link.margin = 0.25  # the wait for an answer outlasts the late one
    part = RemotePart(robot, bind(robot.topology))
    try:
        part.start()
        for _ in range(20):
            part.cycle()
        armed["on"] = True
        assert part.stop() == []
        assert len(late) == len(part.exchanges)  # on every bus the first answer came late
        assert [e for e in part.events if e.stopped_motors] == []
        for bus, x in part.exchanges.items():
            for n in x.configured:
                runtime = fleet.boards[bus][n - 1].application.runtime
                assert runtime is not None and runtime.state is mca.RunState.STOPPED
    finally:
        part.close()
        robot.close()


def test_a_loop_kept_from_running_past_the_watchdog_is_named_as_the_cause(
        flashed, tmp_path, monkeypatch) -> None:
    """Over a served bus (wall clock): the PC's loop is kept off the processor for 150 ms
    once (its 100th cycle); the boards' watchdog stops them, and the summary says the
    loop itself was away that long, which a dropped frame or a slow fleet would not."""
    import shutil
    state = Path(shutil.copytree(flashed, tmp_path / "state"))
    real = RemotePart.cycle
    calls = {"n": 0}

    def cycle(self: RemotePart):  # type: ignore[no-untyped-def]
        calls["n"] += 1
        if calls["n"] == 100:
            time.sleep(0.15)  # the fault itself: this machine keeps the loop away
        return real(self)
    monkeypatch.setattr(RemotePart, "cycle", cycle)
    with served_in_process("armar3", state) as (_, port):
        args = ("remote", "run", "armar3", "-i", "socketcand", "--host", "127.0.0.1",
                "--port", str(port), "--bus", "CAN0", "--for", "0.5")
        code, out, err = ucom(*args, "--json")
        assert code == 1, err
        run = json.loads(out)["run"]
        assert run["missed"] >= 140 and run["longest_gap_ms"] >= 150
        assert any(e["stopped_motors"] for e in json.loads(out)["events"])
        calls["n"] = 0
        code, out, err = ucom(*args)
        assert code == 1
        gap = re.search(r"\(the longest gap between two cycles ([0-9.]+) ms\)", out)
        assert gap is not None and float(gap[1]) >= 150, out
        text = " ".join(err.split())
        assert "its watchdog stopped every motor" in text
        away = re.search(r"ucom: the PC's loop itself did not run for ([0-9]+) ms at a time",
                         text)
        assert away is not None and int(away[1]) >= 150, text
        assert "(the boards' watchdog: 50 ms): this machine kept it from its deadlines; " \
            "--realtime runs it under SCHED_FIFO" in text


def test_a_rate_too_slow_for_the_watchdog_is_refused(flashed) -> None:
    code, _, err = ucom("remote", "run", "armar3", "--virtual", "armar3", "--state",
                        str(flashed), "--for", "0.1", "--rate", "50", "--watchdog", "10")
    assert code == 3
    assert ("--rate: at 50 Hz the loop sends MCA Alive every 20 ms, and the boards' "
            "watchdog (10 ms) wants it at least every 5 ms") in " ".join(err.split())


def test_ctrl_c_between_the_loops_sleeps_ends_the_run_at_once(flashed, tmp_path) -> None:
    """A Ctrl-C that comes while the loop computes rather than sleeps (a busy machine; here
    a rate it cannot keep, so it never sleeps) ends ``run`` at the next cycle: the compiled
    loop passes through the interpreter once a cycle, so that Python runs the signal
    handler (before, such a Ctrl-C waited for the end of the run: 'remote run --for 60'
    went on for a minute, seen on a loaded machine)."""
    import shutil
    import signal
    import threading
    state = Path(shutil.copytree(flashed, tmp_path / "state"))
    with served_in_process("armar3", state) as (_, port):  # noqa: SIM117 (port first)
        with RemotePart.open("armar3", interface="socketcand", host="127.0.0.1",
                             port=port, channels=("CAN0",), rate_hz=10_000.0) as part:
            timer = threading.Timer(0.3, signal.raise_signal, args=(signal.SIGINT,))
            started = time.monotonic()
            timer.start()
            try:
                with pytest.raises(KeyboardInterrupt):
                    part.run(10.0)
            finally:
                timer.cancel()
            assert time.monotonic() - started < 5.0
