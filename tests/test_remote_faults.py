"""The PC notices a lost board and reacts (``man/ucom-protocol.7``, RUN TIME, Faults):
every kind of fault of the virtual fleet (``Fleet.inject``) against ``RemotePart`` in
virtual time, over the real code path; the policies ``stop`` and ``hold``; ``rejoin``,
with every joint held where it stands; ``ucom remote run --on-fault``; one served run
on the wall clock."""

from __future__ import annotations

import json
import re
import shutil
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import can
import pytest
from click.testing import CliRunner

from tests.helpers import served_in_process
from tests.runtime_rig import programmed, robot_of
from ucom_tools.cli.main import cli
from ucom_tools.config.attrtree.robot import bind
from ucom_tools.config.scenario import FaultKind, InjectedFault
from ucom_tools.errors import InputError
from ucom_tools.ops.remote import RemotePart
from ucom_tools.ops.remote.faults import BoardFault, BoardLost, LostBoardWrite, lost_after
from ucom_tools.ops.remote.watch import QUIET_MIN_S
from ucom_tools.virtual.bus.loss import LossyBus
from ucom_tools.virtual.fleet import Fleet
from ucom_tools.wire import mca
from ucom_tools.wire.ids import Function

ROOT = Path(__file__).resolve().parent.parent
PERIOD = 0.001
LIMIT = lost_after(PERIOD)  # ARMAR-III's joints: 1 ms maps, so 5 ms
EYES = ("CAN0", 3)


@contextmanager
def running(policy: str = "stop", *, rejoin: bool = False, topology: str = "armar3",
            wrap: Callable[[can.BusABC], can.BusABC] | None = None,
            ) -> Iterator[tuple[Fleet, RemotePart]]:
    fleet = programmed(topology)
    robot = robot_of(fleet, wrap=wrap)
    part = RemotePart(robot, bind(robot.topology), on_fault=policy, rejoin=rejoin)
    try:
        part.start()
        yield fleet, part
    finally:
        part.close()
        robot.close()


def fault(kind: str, bus: str | None = "CAN0", board: int | None = 3,
          seconds: float = 0.3) -> InjectedFault:
    k = FaultKind(kind)
    if k.target == "robot":
        bus = board = None
    elif k.target == "bus":
        board = None
    return InjectedFault(k, bus, board, for_s=seconds)


def states(fleet: Fleet) -> dict[tuple[str, int], mca.RunState | None]:
    out = {}
    for bus, boards in fleet.boards.items():
        for n, b in enumerate(boards, 1):
            app = b.application
            out[(bus, n)] = app.runtime.state if app and app.runtime else None
    return out


def last_frame(part: RemotePart, bus: str, board: int) -> float:
    """When the board's last SO map came (the end of the frame on the bus, on the loop's
    clock: in virtual time the frames' stamps are the fleet's epoch plus its clock)."""
    x = part.exchanges[bus]
    fleet = part.robot.buses[bus].bus.fleet  # type: ignore[attr-defined]
    return max(x.mca.image.stamps[m.number] for m in x.plan.maps_of(board)) - fleet.epoch


def noticed(part: RemotePart, *, frames: bool = True,
            ) -> dict[tuple[str, int], tuple[BoardFault, float]]:
    """Each lost event as it happens, with the board's last frame then (in virtual time,
    ``frames``) (a fault hook)."""
    seen: dict[tuple[str, int], tuple[BoardFault, float]] = {}

    def hook(f: BoardFault) -> None:
        if f.event == "lost":
            seen[(f.bus, f.board)] = (f, last_frame(part, f.bus, f.board) if frames
                                      else 0.0)
    part.fault_hooks.append(hook)
    return seen


def stall(part: RemotePart, seconds: float) -> None:
    """The PC's loop away for ``seconds``: the fleet's clock runs on, every bus's frames
    are taken meanwhile (its dispatcher's pump), no cycle is sent."""
    until = part._clock() + seconds
    for h in part.robot.buses.values():
        h.link.dispatcher.pump(until)


def sensors(part: RemotePart, bus: str, board: int) -> dict[str, int]:
    """The joint sensors of a board's joints (raw), by name."""
    out = {}
    for ref in part.names:
        if (ref.bus, ref.board) == (bus, board) and ref.generic in (
                "Encoder 0", "Encoder 2", "Encoder 4") and part.cyclic(ref):
            raw = part.raw(ref)
            assert raw is not None
            out[part.names.name_of(ref)] = raw
    return out


# ---------------------------------------------------------------------- detection
KINDS = ["power-off", "reset", "bus-off", "cable", "estop"]


@pytest.mark.parametrize("kind", KINDS)
def test_each_kind_of_fault_is_noticed_by_the_rule(kind: str) -> None:
    """A board none of whose maps came for 5 ms (3 periods of its 1 ms maps, at least
    5 ms) is lost, and no sooner: measured from its last frame, as soon as a frame of
    another board of its bus stamped 5 ms after it has come (their maps come every
    millisecond) and the loop's next drain took it; a bus whose interface reports
    error-passive (a cut cable, every board off) is every board's fault at once."""
    with running("hold") as (fleet, part):
        lost = noticed(part)
        part.run(0.3)
        assert part.faults == [] and part.lost == {}
        t0 = part._clock()
        fleet.inject(fault(kind))
        part.run(0.02)
        expected = {EYES} if kind in ("power-off", "reset", "bus-off") else \
            {("CAN0", n) for n in (1, 2, 3)} if kind == "cable" else set(states(fleet))
        assert set(lost) == expected == set(part.lost)
        for (bus, n), (f, last) in lost.items():
            at = f.time + part.stats.started_clock
            if f.seen.startswith("the bus failing"):  # at once: the first cycle after it
                assert at - t0 <= PERIOD + 1e-9, f
                assert "error-passive" in f.seen
            else:
                assert LIMIT - 1e-9 <= at - last < LIMIT + 2 * PERIOD, (f, at - last)
                assert re.fullmatch(r"silence: none of its SO maps for 5\.[0-9] ms", f.seen)
            assert f.where.startswith(f"{bus} board {n} (") and f.event == "lost"
            assert part.lost[(bus, n)].since == f.time
        others = set(states(fleet)) - expected
        assert all(states(fleet)[k] is mca.RunState.RUNNING for k in others)


def test_a_watchdog_that_stopped_a_board_is_what_its_loss_names() -> None:
    """A board whose watchdog stopped it (no MCA Alive reached it) sends Error WATCHDOG,
    then no maps: its lost event names the Error, the last thing it said (both boards of
    CAN3 at once: nothing from that bus at all, so after the quiet time)."""
    armed = {"on": False}

    def wrap(bus: can.BusABC) -> can.BusABC:
        name = bus.channel_info
        return LossyBus(bus, drop=lambda d, msg: armed["on"] and d == "tx" and "CAN3" in name
                        and msg.arbitration_id >> 6 == Function.MCA_ALIVE)
    with running("hold", wrap=wrap) as (_, part):
        part.run(0.1)
        armed["on"] = True
        part.run(0.1)
        assert part.lost == {}  # both silent: no other board of CAN3 tells how long
        part.run(QUIET_MIN_S)
        assert set(part.lost) == {("CAN3", 1), ("CAN3", 2)}
        for f in part.faults:
            assert f.seen.startswith("its watchdog stopped every motor: no MCA Alive for "), f


def test_one_percent_frame_loss_makes_no_board_lost() -> None:
    seeds = iter(range(100))
    with running(wrap=lambda bus: LossyBus(bus, loss=0.01, seed=next(seeds))) as (
            fleet, part):
        part.run(2.0)  # under the stop policy a single false loss would raise
        assert part.faults == []
        assert sum(sum(h.bus.dropped.values())  # type: ignore[attr-defined]
                   for h in part.robot.buses.values()) > 500
        fleet.inject(fault("power-off"))  # and a real one is noticed
        with pytest.raises(BoardLost):
            part.run(0.02)


def test_a_stall_of_the_loop_is_no_silence_of_the_boards() -> None:
    """The PC's loop held 30 ms (less than the boards' watchdog, 50 ms, less the 10 ms
    between two MCA Alive; the clock runs on: the boards send meanwhile, the next drain
    takes it all): nobody is lost; a board that stops in the middle of such a stall is
    lost at the first cycle after it, its bus-mates' frames stamped 20 ms after its
    last."""
    with running() as (fleet, part):
        part.run(0.1)
        for _ in range(3):
            stall(part, 0.03)
            part.run(0.01)
        assert part.faults == [] and part.stats.missed >= 3 * 28
        stall(part, 0.02)
        fleet.inject(fault("power-off"))  # (no maps from it at the end of the stall)
        stall(part, 0.02)
        cycles = part.stats.cycles
        with pytest.raises(BoardLost, match="CAN0 board 3"):
            part.run(0.05)
        assert part.stats.cycles - cycles == 1
        assert re.fullmatch(r"silence: none of its SO maps for (19|20)\.[0-9] ms",
                            part.faults[0].seen), part.faults


# ---------------------------------------------------------------------- stop
def test_stop_stops_every_other_board_within_a_cycle_and_ends_the_run() -> None:
    with running() as (fleet, part):
        lost = noticed(part)
        part.run(0.2)
        fleet.inject(fault("power-off", "CAN1", 1))
        with pytest.raises(BoardLost) as caught:
            part.run(0.05)
        f, _ = lost[("CAN1", 1)]
        assert caught.value.faults == [f]
        assert str(caught.value) == (
            f"CAN1 board 1 (right shoulder front) lost at {f.time:.3f} s: {f.seen}; every "
            "other board was stopped")
        assert f.seen.startswith("silence: none of its SO maps for 5.")
        detected = part._clock()
        assert detected == pytest.approx(f.time + part.stats.started_clock)
        h = part.robot.buses["CAN0"]
        h.link.dispatcher.pump(detected + PERIOD)  # one cycle later: every motor off
        after = states(fleet)
        assert after.pop(("CAN1", 1)) is None  # powered off
        assert set(after.values()) == {mca.RunState.STOPPED}
        with pytest.raises(BoardLost):  # the run is over
            part.cycle()
        assert part.stop() == []  # the orderly stop: no problem, the lost board left out


def test_a_failed_bus_is_a_fault_of_every_board_on_it() -> None:
    """The adapter of CAN2 fails (python-can raises on receive): its boards are lost,
    naming the bus failing; under hold the other buses run on."""
    armed = {"on": False}

    def wrap(bus: can.BusABC) -> can.BusABC:
        name = bus.channel_info

        def drop(direction: str, msg: can.Message) -> bool:
            if armed["on"] and "CAN2" in name and direction == "rx":
                raise can.CanOperationError("the adapter is gone")
            return False
        return LossyBus(bus, drop=drop)
    with running("hold", wrap=wrap) as (fleet, part):
        part.run(0.1)
        armed["on"] = True
        part.run(0.1)
        assert set(part.lost) == {("CAN2", n) for n in (1, 2, 3)}
        assert all(f.seen.startswith("the bus failing: CAN2: cannot receive: the adapter "
                                     "is gone") for f in part.faults)
        assert part.stats.missed == 0
        assert {k: v for k, v in states(fleet).items() if k[0] != "CAN2"} == {
            k: mca.RunState.RUNNING for k in states(fleet) if k[0] != "CAN2"}
    armed["on"] = False
    with running("stop", wrap=wrap) as (fleet, part):
        part.run(0.1)
        armed["on"] = True
        with pytest.raises(BoardLost, match=r"CAN2 board 1 .* the bus failing"):
            part.run(0.1)


# ---------------------------------------------------------------------- hold
def test_hold_runs_the_others_on_and_refuses_writes_to_the_lost_board() -> None:
    with running("hold") as (fleet, part):
        part["Right Eye Target"] = 500
        part["Neck Yaw Target"] = 300
        part.run(0.4)
        fleet.inject(fault("power-off", seconds=5.0))
        part.run(0.3)
        assert set(part.lost) == {EYES} and part.lost[EYES].status == "lost"
        x = part.exchanges["CAN0"]
        held = dict(x.ci)
        with pytest.raises(LostBoardWrite, match=r"Eyes/Right Eye Target: CAN0 board 3 "
                           r"\(head right\) is lost since 0\.40\d s \(silence: .*\); "
                           "writes to it are refused until it rejoins"):
            part["Right Eye Target"] = 900
        with pytest.raises(InputError, match="refused"):  # PAR alike; the network
            part.set("RightEye P", 0.5)  # (share) reports it so, as a refused write
        assert x.ci == held  # nothing queued
        part["Neck Yaw Target"] = -300  # the others take writes
        part.run(0.5)
        assert abs(part["Neck Yaw Joint Sensor"] + 300) <= 5
        assert not part.valid("Right Eye Joint Sensor") and not part.valid("Right Eye Target")
        assert part.valid("Neck Yaw Joint Sensor") and part.valid("Neck Yaw Target")
        assert part.age("Right Eye Joint Sensor") == pytest.approx(0.8, abs=0.01)
        assert part.age("Neck Yaw Joint Sensor") < 0.002
        after = states(fleet)
        assert after.pop(EYES) is None
        assert set(after.values()) == {mca.RunState.RUNNING}
        assert part.stats.missed == 0 and part.events == []


def test_a_board_whose_maps_come_again_is_back_as_it_was() -> None:
    """A bus-off shorter than the watchdog: the board ran on, its configuration and
    targets as they were; under hold it is back the moment its maps come again."""
    with running("hold") as (fleet, part):
        part["Right Eye Target"] = 400
        part.run(0.3)
        fleet.inject(fault("bus-off", seconds=0.03))
        part.run(0.2)
        lost, back = part.faults
        assert (lost.event, back.event) == ("lost", "rejoined") and part.lost == {}
        assert 0.030 - LIMIT <= back.time - lost.time <= 0.030 - LIMIT + 3 * PERIOD
        assert back.seen.startswith("its SO maps came again ") and back.seen.endswith(
            "s after the loss: it ran on, as configured, with the targets it had")
        assert states(fleet)[EYES] is mca.RunState.RUNNING
        part["Right Eye Target"] = 600  # writes are taken again
        part.run(0.5)
        assert abs(part["Right Eye Joint Sensor"] - 600) <= 5


# ---------------------------------------------------------------------- rejoin
@pytest.mark.parametrize("kind", KINDS)
def test_each_kind_rejoins_with_every_joint_where_it_stood(kind: str) -> None:
    with running("hold", rejoin=True) as (fleet, part):
        targets = {"Right Eye Target": 700, "Left Eye Target": -400, "Neck Yaw Target": 900,
                   "Right Elbow Target": 300, "Wheel 1 Target": -200}
        for name, value in targets.items():
            part[name] = value
        part.run(0.8)
        boards = sorted({(r.bus, r.board) for r in part.names})
        before = {b: sensors(part, *b) for b in boards}
        lost = noticed(part)
        at_loss: dict[tuple[str, int], dict[str, int]] = {}
        part.fault_hooks.append(lambda f: at_loss.setdefault(
            (f.bus, f.board), sensors(part, f.bus, f.board)) if f.event == "lost" else None)
        t0 = part._clock()
        fleet.inject(fault(kind))
        back = t0 + 0.3  # the fault's end
        late: list[float] = []
        part.run(1.5, lambda p: late.append(p.stats.late[-1]))
        assert part.lost == {}, part.lost
        rejoined = {(f.bus, f.board): f for f in part.faults if f.event == "rejoined"}
        assert set(rejoined) == set(lost) and lost
        # the run time's own clients kept no copy of the conversations' answers
        assert [x.mca.forget() for x in part.exchanges.values()] == [0] * 4
        for f in rejoined.values():
            assert f.time + part.stats.started_clock - back < 1.0, f  # back within 1 s
            assert f.answered is not None and f.answered < f.time
            assert "held where it stands" in f.seen
            assert "configured as at the start" in f.seen
            # its program's MCA Ready ends its Start: not Start's whole verdict window,
            # which waits for a reset too (0.15 s), then the edges, the configuration
            assert f.time - f.answered < 0.3, f
        # every joint where it stood at the loss (it coasts a little, unpowered)
        for b in boards:
            now = sensors(part, *b)
            for name, raw in now.items():
                assert abs(raw - at_loss.get(b, before[b])[name]) <= 10, (b, name)
        # the loop ran on undisturbed: every cycle on time (in virtual time a frame sent
        # on an idle bus takes its wire time: late by that, while every board is off),
        # nobody else stopped
        assert part.stats.missed == 0 and max(late) < 0.5 * PERIOD
        if kind not in ("cable", "estop"):
            assert max(late) < 1e-9
        assert [e for e in part.events if e.stopped_motors and
                (e.bus, e.board) not in lost] == []
        assert set(states(fleet).values()) == {mca.RunState.RUNNING}
        # and the joints are controlled again: a new target is followed
        part["Right Eye Target"] = 200
        part.run(0.6)
        assert abs(part["Right Eye Joint Sensor"] - 200) <= 5


def test_a_rejoined_joint_holds_where_it_stands_not_where_it_was_sent() -> None:
    """The eye is on its way to 3000 (at 2000 counts/s) when its board loses power: it
    coasts to a stop somewhere short of it.  Rejoined, its target is where it stands, so
    it stays there (the old target, 3000, is not taken up again)."""
    with running("hold", rejoin=True) as (fleet, part):
        part["RightEye Max Velocity (x1000)"] = 2
        part["Right Eye Target"] = 3000
        part.run(0.4)
        moving = part["Right Eye Joint Sensor"]
        assert 300 < moving < 1500
        fleet.inject(fault("power-off", seconds=0.2))
        part.run(1.0)
        assert part.lost == {}
        x = part.exchanges["CAN0"]
        stands = part["Right Eye Joint Sensor"]
        assert abs(stands - 3000) > 300  # it stopped short of the old target
        assert x.ci[(3, 3)] == part["Right Eye Target"]  # what the PC sends, and holds
        assert abs(part["Right Eye Target"] - stands) <= 10
        assert x.ci[(3, 10)] == 0  # its velocity target
        part.run(1.0)
        assert abs(part["Right Eye Joint Sensor"] - stands) <= 10  # it holds there
        f = part.faults[-1]
        assert f.event == "rejoined" and f"Right Eye Target {part['Right Eye Target']}" \
            in f.seen


def test_a_homing_command_is_not_resumed_on_a_rejoin() -> None:
    with running("hold", rejoin=True) as (fleet, part):
        part["Right Eye Command"] = 2  # HOMING: the eye drives to its end stop
        part.run(0.05)
        fleet.inject(fault("power-off", seconds=0.1))
        part.run(1.0)
        assert part.lost == {}
        assert part["Right Eye Command"] == 0  # position control, where it stands
        assert part["Right Eye Reset Answer"] == 0  # no homing begun again


def test_a_leg_rejoins_holding_its_joints_without_a_reference_run() -> None:
    """lauron4: the position set points take the joints' positions, the velocity set
    points 0, and Reference Run the board's own value (0 after its power loss): the
    PC's larger count would start a reference run."""
    with running("hold", rejoin=True, topology="lauron4") as (fleet, part):
        leg = next(r for r in part.names if r.generic == "Axis1 Position Setpoint")
        bus, n = leg.bus, leg.board
        names = {r.generic: part.names.name_of(r) for r in part.names
                 if (r.bus, r.board) == (bus, n)}
        part[names["Leg Mode"]] = 1
        part[names["Axis1 Position Setpoint"]] = 1500
        part.run(1.0)
        part[names["Reference Run"]] = 3
        part.run(0.01)
        fleet.inject(fault("power-off", bus, n, 0.2))
        part.run(1.5)
        assert part.lost == {}
        stands = part[names["Axis1 Position"]]
        assert abs(part[names["Axis1 Position Setpoint"]] - stands) <= 20
        assert part[names["Axis1 Velocity Setpoint"]] == 0
        assert part[names["Reference Run"]] == 0 and part[names["Leg Mode"]] == 1
        part.run(0.5)
        assert abs(part[names["Axis1 Position"]] - stands) <= 20


# ---------------------------------------------------------------------- the command
@pytest.fixture(scope="module")
def flashed(tmp_path_factory) -> Path:
    state = tmp_path_factory.mktemp("armar3")
    r = CliRunner().invoke(cli, ["flash", str(ROOT / "firmware_images/armar3.fl.S"),
                                 "--virtual", "armar3", "--state", str(state)])
    assert r.exit_code == 0, r.stderr
    return state


def scenario(where: Path, text: str) -> str:
    """A scenario file of injected faults (``ucom(1)``, SCENARIOS) for ``--scenario``."""
    path = where / "faults.toml"
    path.write_text(text)
    return str(path)


POWER_OFF = """
[[fault]]
at = 0.2
kind = "power-off"
bus = "CAN0"
board = 3
for = {seconds}
"""
ESTOP = """
[[fault]]
at = 0.2
kind = "estop"
for = 0.3
"""


def ucom(*args: str) -> tuple[int, str, str]:
    r = CliRunner().invoke(cli, list(args))
    return r.exit_code, r.stdout, r.stderr


def test_run_stops_every_board_and_exits_1_naming_the_lost_one(flashed, tmp_path) -> None:
    args = ("remote", "run", "armar3", "--virtual", "armar3", "--state", str(flashed),
            "--for", "1", "--scenario", scenario(tmp_path, POWER_OFF.format(seconds=1)))
    code, out, err = ucom(*args, "--json")
    assert code == 1, err
    data = json.loads(out)
    (f,) = data["faults"]
    assert f["event"] == "lost" and f["where"] == "CAN0 board 3 (head right)"
    assert f["seen"].startswith("silence: none of its SO maps for 5.") and \
        f["answered"] is None
    assert data["lost"][0]["where"] == "CAN0 board 3 (head right)"
    assert data["run"]["cycles"] < 300  # the run ended there
    code, out, err = ucom(*args)
    assert code == 1
    text = " ".join(err.split())
    assert "ucom: CAN0 board 3 (head right) lost at 0.20" in text
    assert "ucom: --on-fault stop: every other board was stopped at 0.20" in text


def test_run_with_rejoin_exits_0_listing_the_faults(flashed, tmp_path) -> None:
    """The emergency stop: every board lost (its bus says nobody acknowledges), then
    every board back as power returns; the run exits 0 and lists them."""
    code, out, err = ucom("remote", "run", "armar3", "--virtual", "armar3", "--state",
                          str(flashed), "--for", "1.2", "--on-fault", "hold", "--rejoin",
                          "--scenario", scenario(tmp_path, ESTOP), "--json")
    assert code == 0, err
    data = json.loads(out)
    lost = [f for f in data["faults"] if f["event"] == "lost"]
    back = [f for f in data["faults"] if f["event"] == "rejoined"]
    assert len(lost) == len(back) == 11 and data["lost"] == []
    assert all(f["seen"].startswith("the bus failing: the interface reports CAN") for f in lost)
    assert all(f["answered"] < f["time"] < 0.5 + 1.0 for f in back)  # within 1 s of power
    # without --rejoin the board stays lost: exit 1, named
    code, out, err = ucom("remote", "run", "armar3", "--virtual", "armar3", "--state",
                          str(flashed), "--for", "0.6", "--on-fault", "hold", "--scenario",
                          scenario(tmp_path, POWER_OFF.format(seconds=0.2)))
    assert code == 1
    assert "ucom: CAN0 board 3 (head right) still lost at the end (since 0.20" in \
        " ".join(err.split())


def test_rejoin_without_hold_is_a_usage_error(flashed) -> None:
    code, _, err = ucom("remote", "run", "armar3", "--virtual", "armar3", "--state",
                        str(flashed), "--for", "0.1", "--rejoin")
    assert code == 2 and "--rejoin needs --on-fault hold" in err
    with pytest.raises(InputError, match="rejoin needs the hold policy"):
        RemotePart.open("armar3", virtual=True, state_dir=flashed, rejoin=True,
                        start=False)


# ---------------------------------------------------------------------- served
def test_served_a_stall_of_the_loop_loses_nobody_and_a_power_loss_is_noticed(
        flashed, tmp_path) -> None:
    """Over socketcand on the wall clock: the loop held 60 ms (the watchdog set to 200
    ms so the boards run on): the drain after it takes what came meanwhile, nobody is
    lost; then a board that loses power is, within the rule, and rejoins."""
    state = Path(shutil.copytree(flashed, tmp_path / "state"))
    with served_in_process("armar3", state) as (fleet, port), RemotePart.open(
            "armar3", interface="socketcand", channels=["CAN0"], host="127.0.0.1",
            port=port, alive_ms=200, on_fault="hold", rejoin=True) as part:
        lost = noticed(part, frames=False)
        part.run(0.2)
        time.sleep(0.06)  # the fault itself: the loop is kept away 60 ms
        part.run(0.2)
        assert part.stats.longest_gap_s >= 0.06
        assert part.faults == []
        fleet.inject(fault("power-off", seconds=0.2))
        deadline = time.monotonic() + 5
        while part.lost or not part.faults:
            assert time.monotonic() < deadline, part.faults
            part.cycle()
        part.run(0.1)
        (f, _), = lost.values()
        assert [x.event for x in part.faults] == ["lost", "rejoined"]
        assert f.where == "CAN0 board 3 (head right)"
        assert f.seen.startswith("silence: none of its SO maps for ")


# ---------------------------------------------------------------------- the pages
def test_the_protocol_page_says_the_rule_and_how_each_program_is_seeded() -> None:
    from ucom_tools.edgelists import armar3, lauron4
    from ucom_tools.edgelists.model import Seed
    from ucom_tools.ops.remote.faults import LOST_AFTER_MIN_S, LOST_PERIODS, REJOIN_EVERY_S
    page = (ROOT / "man/ucom-protocol.7").read_text()
    section = page[page.index("\n.SS Faults\n"):page.index("\n.SS Bad input\n")]
    text = " ".join(re.sub(r"\\f[BIRP]|\\&", "", section).replace("\\-", "-").split())
    assert (f"max({LOST_PERIODS} periods of its fastest map, "
            f"{LOST_AFTER_MIN_S * 1e3:g} ms)") in text
    assert (f"nothing came at all for {QUIET_MIN_S:g} s, or the boards' watchdog time "
            "(Admin Data ALIVE) if that is longer, of the host loop's own running time"
            in text)
    assert f"Every {REJOIN_EVERY_S * 1e3:g} ms Init Request REJOIN" in text
    for spec, program in ((armar3.SPEC, "armar3"), (lauron4.SPEC, "lauron4")):
        table = text[text.index(f" {program} "):]
        for seed in spec.seeds:  # named as the page does: MotorX, AxisN
            generic = re.sub(r"^Motor[ABC]", "MotorX", re.sub(r"^Axis\d", "AxisN", seed.ci))
            assert generic in table, seed
            if seed.seed is Seed.SENSOR:
                sensor = re.sub(r"^Axis\d", "AxisN", seed.sensor)
                assert sensor in table or "Encoder 0, 2, 4" in table, seed
            if seed.seed is Seed.ZERO:
                assert f"{generic} 0" in table, seed


def test_help_names_the_policies() -> None:
    code, out, _ = ucom("remote", "run", "--help")
    assert code == 0
    text = " ".join(out.split())
    assert "--on-fault [stop|hold]" in text and "--rejoin" in text


def test_served_an_emergency_stop_is_the_bus_failing_at_once_and_every_board_rejoins(
        flashed, tmp_path) -> None:
    """Over socketcand: every board off leaves the PC's frames unacknowledged; the served
    fleet says so with an error frame (``< error 020 ... >``), the bus turns error-passive
    and every board on it is lost in that cycle, not after the quiet time of a silent
    bus; when power returns every board rejoins."""
    state = Path(shutil.copytree(flashed, tmp_path / "state"))
    with served_in_process("armar3", state) as (fleet, port), RemotePart.open(
            "armar3", interface="socketcand", channels=["CAN0"], host="127.0.0.1",
            port=port, on_fault="hold", rejoin=True) as part:
        part.run(0.2)
        fleet.inject(fault("estop", seconds=0.3))
        deadline = time.monotonic() + 10
        while part.lost or len(part.faults) < 6:
            assert time.monotonic() < deadline, part.faults
            part.cycle()
        lost = [f for f in part.faults if f.event == "lost"]
        assert sorted(f.board for f in lost) == [1, 2, 3]
        assert all(f.seen == "the bus failing: the interface reports CAN0 error-passive"
                   for f in lost), lost
        assert len({f.time for f in lost}) == 1  # in one cycle
        assert sorted(f.board for f in part.faults if f.event == "rejoined") == [1, 2, 3]



def test_after_an_emergency_stop_a_power_loss_is_noticed_by_the_rule() -> None:
    """The silence of an emergency stop (every board lost, the buses error-passive) is
    explained: once the boards are back, a board that loses power is lost by its
    neighbours' frames, as before, not after the quiet time of a silent bus."""
    with running("hold", rejoin=True) as (fleet, part):
        part.run(0.3)
        fleet.inject(fault("estop", seconds=0.2))
        part.run(0.1)
        while part.lost:  # the last one back: at once, the next fault
            part.cycle()
        assert len(part.faults) == 22, part.faults
        lost = noticed(part)
        fleet.inject(fault("power-off", seconds=0.2))
        part.run(0.05)
        (f, last), = lost.values()
        assert f.seen.startswith("silence: none of its SO maps for "), f
        assert f.time + part.stats.started_clock - last < 2 * LIMIT, (f, last)
