"""The CiA 402 drive of a UCoM joint (``ucom_tools.gateway.cia402``): every transition and
its statusword, the modes (PP handshake and target reached, PV, HM, CSP), halt, quick
stop, faults with their EMCYs, software limits; and canopen's own BaseNode402 driving it,
by its transition tables and over an SDO server on a virtual bus.

Time is passed in (seconds): every window and time-out is checked to the millisecond.
The expected statuswords are IEC 61800-7-201's values, written out here (not taken from
the module)."""

from __future__ import annotations

import itertools
import threading
import time
from dataclasses import replace
from typing import Any, ClassVar

import canopen
import pytest
from canopen.objectdictionary import ObjectDictionary, ODVariable
from canopen.profiles.p402 import BaseNode402, Homing
from canopen.profiles.p402 import State402 as P402

from ucom_tools.edgelists.armar3 import Command
from ucom_tools.gateway.cia402 import Drive402
from ucom_tools.gateway.cia402_objects import (
    ERROR_RESET,
    SUPPORTED_MODES,
    DriveConfig,
    DriveFault,
    DriveOutputs,
    Emcy,
    FaultCause,
    JointReport,
    ObjectValues,
    State402,
)

S = State402
REMOTE = 0x0200
VOLTAGE = 0x0010
# IEC 61800-7-201 statusword of each state (bits 0-3, 5, 6), with bit 9 remote and bit 4
# voltage enabled (the joint's board runs)
SOD = 0x0040 | VOLTAGE | REMOTE
RTSO = 0x0021 | VOLTAGE | REMOTE
SO = 0x0023 | VOLTAGE | REMOTE
OE = 0x0027 | VOLTAGE | REMOTE
QSA = 0x0007 | VOLTAGE | REMOTE
FRA = 0x000F | VOLTAGE | REMOTE
FAULT = 0x0008 | VOLTAGE | REMOTE
TARGET_REACHED, LIMIT, BIT12, BIT13 = 0x0400, 0x0800, 0x1000, 0x2000

EYE = DriveConfig(max_velocity=500, min_position=-10000, max_position=10000,
                  reset_offset=-12725, reset_pwm=-7000)
"""The right eye's tree (head_right.tree)."""


class Bench:
    """One drive, the objects the master wrote, what the joint reports, the time."""

    def __init__(self, config: DriveConfig = EYE, **objects: int) -> None:
        self.drive = Drive402(config)
        self.objects = replace(config.defaults(), **objects)
        self.joint = JointReport(position=100, velocity=0, valid=True)
        self.faults: tuple[DriveFault, ...] = ()
        self.now = 0.0
        self.out = self.step()

    def step(self, dt: float = 0.0, *, sync: bool = False) -> DriveOutputs:
        self.now += dt
        self.out = (self.drive.on_sync if sync else self.drive.update)(
            self.now, self.objects, self.joint, self.faults)
        return self.out

    def write(self, **objects: int) -> DriveOutputs:
        """The master writes objects (each write is an update)."""
        self.objects = replace(self.objects, **objects)
        return self.step()

    def cw(self, controlword: int) -> DriveOutputs:
        return self.write(controlword=controlword)

    def report(self, dt: float = 0.0, **joint: Any) -> DriveOutputs:
        """The joint reports new values, ``dt`` after the last update."""
        self.joint = replace(self.joint, **joint)
        return self.step(dt)

    def enable(self, mode: int | None = None) -> DriveOutputs:
        if mode is not None:
            self.write(modes_of_operation=mode)
        for controlword in (0x06, 0x07, 0x0F):
            self.cw(controlword)
        assert self.out.state is S.OPERATION_ENABLED
        return self.out


def status(out: DriveOutputs, mask: int = 0xFFFF) -> int:
    return out.statusword & mask


# ---------------------------------------------------------------- the state machine
def test_start_is_transition_0_then_1_once_the_joint_reports() -> None:
    bench = Bench()
    assert bench.out.transitions == (0, 1) and bench.out.state is S.SWITCH_ON_DISABLED
    assert bench.out.statusword == SOD
    quiet = Drive402(EYE)
    out = quiet.update(0.0, EYE.defaults(), JointReport(valid=False))
    assert out.transitions == (0,) and out.state is S.NOT_READY_TO_SWITCH_ON
    assert out.statusword == REMOTE  # 0x0000: not ready, no voltage
    assert out.command == Command.OFF
    out = quiet.update(0.01, EYE.defaults(), JointReport(valid=False))
    assert out.transitions == () and out.state is S.NOT_READY_TO_SWITCH_ON
    out = quiet.update(0.02, EYE.defaults(), JointReport(position=7, valid=True))
    assert out.transitions == (1,) and out.statusword == SOD and out.target == 7


def _to(bench: Bench, state: State402, quick_stop_option: int = 6) -> None:
    """Bring the bench's drive to ``state`` (with the joint standing still)."""
    bench.write(quick_stop_option=quick_stop_option)
    path = {S.SWITCH_ON_DISABLED: (), S.READY_TO_SWITCH_ON: (0x06,),
            S.SWITCHED_ON: (0x06, 0x07), S.OPERATION_ENABLED: (0x06, 0x07, 0x0F),
            S.QUICK_STOP_ACTIVE: (0x06, 0x07, 0x0F, 0x02)}[state]
    for controlword in path:
        bench.cw(controlword)
    assert bench.out.state is state


TRANSITIONS = [
    # (from, controlword, transitions, to, statusword)
    (S.SWITCH_ON_DISABLED, 0x06, (2,), S.READY_TO_SWITCH_ON, RTSO),
    (S.READY_TO_SWITCH_ON, 0x07, (3,), S.SWITCHED_ON, SO),
    (S.READY_TO_SWITCH_ON, 0x0F, (3, 4), S.OPERATION_ENABLED, OE),
    (S.SWITCHED_ON, 0x0F, (4,), S.OPERATION_ENABLED, OE),
    (S.OPERATION_ENABLED, 0x07, (5,), S.SWITCHED_ON, SO),
    (S.SWITCHED_ON, 0x06, (6,), S.READY_TO_SWITCH_ON, RTSO),
    (S.READY_TO_SWITCH_ON, 0x00, (7,), S.SWITCH_ON_DISABLED, SOD),
    (S.READY_TO_SWITCH_ON, 0x02, (7,), S.SWITCH_ON_DISABLED, SOD),
    (S.OPERATION_ENABLED, 0x06, (8,), S.READY_TO_SWITCH_ON, RTSO),
    (S.OPERATION_ENABLED, 0x0D, (9,), S.SWITCH_ON_DISABLED, SOD),
    (S.SWITCHED_ON, 0x00, (10,), S.SWITCH_ON_DISABLED, SOD),
    (S.SWITCHED_ON, 0x03, (10,), S.SWITCH_ON_DISABLED, SOD),
    (S.OPERATION_ENABLED, 0x02, (11,), S.QUICK_STOP_ACTIVE, QSA),
    (S.QUICK_STOP_ACTIVE, 0x00, (12,), S.SWITCH_ON_DISABLED, SOD),
    (S.QUICK_STOP_ACTIVE, 0x0F, (16,), S.OPERATION_ENABLED, OE),
    # no transition: commands a state does not take, and bit 7 set
    (S.SWITCH_ON_DISABLED, 0x0F, (), S.SWITCH_ON_DISABLED, SOD),
    (S.SWITCH_ON_DISABLED, 0x07, (), S.SWITCH_ON_DISABLED, SOD),
    (S.OPERATION_ENABLED, 0x80, (), S.OPERATION_ENABLED, OE),
    (S.OPERATION_ENABLED, 0x0F, (), S.OPERATION_ENABLED, OE),
    (S.QUICK_STOP_ACTIVE, 0x06, (), S.QUICK_STOP_ACTIVE, QSA),
]


@pytest.mark.parametrize(("start", "controlword", "steps", "end", "word"), TRANSITIONS)
def test_each_transition_by_its_command_and_its_statusword(
        start: State402, controlword: int, steps: tuple[int, ...], end: State402,
        word: int) -> None:
    bench = Bench()
    _to(bench, start)
    out = bench.cw(controlword)
    assert (out.transitions, out.state) == (steps, end)
    # the mode's bits (no mode yet: 10, 12, 13 stay 0; at standstill a brake reports 10)
    assert status(out, ~TARGET_REACHED) == word
    enabled = end in (S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE)
    assert (out.command != Command.OFF) == enabled
    if enabled:  # holds where the joint stands
        assert (out.command, out.target) == (Command.POSITION, 100)


def test_fault_reaction_fault_and_reset_transitions_13_14_15() -> None:
    bench = Bench()
    _to(bench, S.OPERATION_ENABLED)
    bench.faults = (DriveFault(FaultCause.BOARD_LOST),)
    out = bench.step(0.001)
    assert (out.transitions, out.statusword, out.command) == ((13,), FRA, Command.OFF)
    out = bench.step(0.001)
    assert (out.transitions, out.statusword, out.command) == ((14,), FAULT, Command.OFF)
    bench.faults = ()
    out = bench.cw(0x80)
    assert (out.transitions, out.statusword, out.state) == ((15,), SOD, S.SWITCH_ON_DISABLED)


def test_enable_operation_waits_for_the_joints_values() -> None:
    bench = Bench()
    _to(bench, S.SWITCHED_ON)
    bench.report(valid=False)
    out = bench.cw(0x0F)
    assert out.state is S.SWITCHED_ON and out.command == Command.OFF
    assert out.statusword == SO & ~VOLTAGE
    bench.cw(0x07)
    assert bench.cw(0x06).state is S.READY_TO_SWITCH_ON
    out = bench.cw(0x0F)  # switch on + enable operation: only switch on
    assert (out.transitions, out.state) == ((3,), S.SWITCHED_ON)
    out = bench.report(valid=True)  # the command is a level: it acts now
    assert (out.transitions, out.state) == ((4,), S.OPERATION_ENABLED)


def test_disable_voltage_by_the_device_switches_the_joint_off() -> None:
    """NMT stop: the gateway's own disable voltage."""
    bench = Bench()
    _to(bench, S.OPERATION_ENABLED)
    bench.drive.disable_voltage()
    out = bench.step(0.001)
    assert (out.transitions, out.state, out.command) == ((9,), S.SWITCH_ON_DISABLED,
                                                         Command.OFF)
    assert bench.step(0.001).transitions == ()  # once: 0x0F does not enable again
    assert bench.cw(0x06).state is S.READY_TO_SWITCH_ON


# ---------------------------------------------------------------- canopen's BaseNode402
def _named(word: int) -> str:
    """The state canopen's BaseNode402 reads from a statusword."""
    for name, (mask, bits) in P402.SW_MASK.items():
        if word & mask == bits:
            return name
    return "UNKNOWN"


def _set_state(bench: Bench, target: str) -> list[str]:
    """canopen's ``BaseNode402.state = target``: each step by its transition table, each
    checked as its ``_change_state`` checks it; the states passed."""
    seen = []
    for _ in range(8):
        current = _named(bench.out.statusword)
        seen.append(current)
        if current == target:
            return seen
        step = (target if (current, target) in P402.TRANSITIONTABLE
                else P402.next_state_indirect(current))
        out = bench.cw(P402.TRANSITIONTABLE[(current, step)])
        assert _named(out.statusword) == step, (current, step, hex(out.statusword))
    pytest.fail(f"{target} not reached: {seen}")


def test_basenode402_state_setter_reaches_operation_enabled() -> None:
    bench = Bench()
    assert _set_state(bench, "OPERATION ENABLED") == [
        "SWITCH ON DISABLED", "READY TO SWITCH ON", "SWITCHED ON", "OPERATION ENABLED"]


def test_basenode402_reset_from_fault_then_operation_enabled() -> None:
    bench = Bench()
    _set_state(bench, "OPERATION ENABLED")
    bench.faults = (DriveFault(FaultCause.MASTER_HEARTBEAT),)
    bench.step(0.001)
    bench.step(0.001)
    assert _named(bench.out.statusword) == "FAULT"
    bench.cw(P402.CW_DISABLE_VOLTAGE)  # reset_from_fault's first write
    out = bench.cw(P402.TRANSITIONTABLE[("FAULT", "SWITCH ON DISABLED")])
    assert _named(out.statusword) == "FAULT"  # refused: the cause lasts
    bench.faults = ()
    bench.cw(P402.CW_DISABLE_VOLTAGE)
    assert _set_state(bench, "OPERATION ENABLED") == [
        "FAULT", "SWITCH ON DISABLED", "READY TO SWITCH ON", "SWITCHED ON",
        "OPERATION ENABLED"]


@pytest.mark.parametrize(("start", "end"), [
    pair for pair, word in P402.TRANSITIONTABLE.items()
    if "START" not in pair and pair[0] not in ("NOT READY TO SWITCH ON",
                                              "FAULT REACTION ACTIVE", "FAULT")])
def test_every_commanded_transition_of_basenode402s_table(start: str, end: str) -> None:
    bench = Bench()
    _set_state(bench, "OPERATION ENABLED")
    if start == "QUICK STOP ACTIVE":
        bench.write(quick_stop_option=6)
        bench.cw(P402.CW_QUICK_STOP)
    else:
        _set_state(bench, start)
    assert _named(bench.out.statusword) == start
    out = bench.cw(P402.TRANSITIONTABLE[(start, end)])
    assert _named(out.statusword) == end


def _od() -> ObjectDictionary:
    od = ObjectDictionary()
    for index, name, data_type, access, default in [
            (0x6040, "Controlword", 0x06, "rw", 0), (0x6041, "Statusword", 0x06, "ro", 0),
            (0x6060, "Modes of operation", 0x02, "rw", 0),
            (0x6061, "Modes of operation display", 0x02, "ro", 0),
            (0x607A, "Target position", 0x04, "rw", 0),
            (0x6502, "Supported drive modes", 0x07, "ro", SUPPORTED_MODES)]:
        var = ODVariable(name, index, 0)
        var.data_type, var.access_type, var.default = data_type, access, default
        od.add_object(var)
    return od


class SdoDrive:
    """The drive behind canopen's LocalNode (its SDO server), on a python-can virtual
    bus: each write of 0x6040, 0x6060, 0x607A is an update; 0x6041 and 0x6061 are read
    from the last one."""

    WRITTEN: ClassVar = {0x6040: "controlword", 0x6060: "modes_of_operation",
                         0x607A: "target_position"}

    def __init__(self, channel: str) -> None:
        self.lock = threading.Lock()
        self.bench = Bench()
        self.network = canopen.Network()
        self.network.connect(interface="virtual", channel=channel)
        node = canopen.LocalNode(5, _od())
        node.add_write_callback(self._written)
        node.add_read_callback(self._read)
        self.network.add_node(node)

    def _written(self, index: int, subindex: int, od: Any, data: bytes) -> None:
        if index in self.WRITTEN:
            with self.lock:
                self.bench.now = time.monotonic()
                self.bench.write(**{self.WRITTEN[index]: od.decode_raw(data)})

    def _read(self, index: int, subindex: int, od: Any) -> int | None:
        with self.lock:
            return {0x6041: self.bench.out.statusword,
                    0x6061: self.bench.out.mode_display}.get(index)


def test_canopens_basenode402_drives_it_over_sdo() -> None:
    channel = f"cia402-{time.monotonic_ns()}"
    served = SdoDrive(channel)
    master = canopen.Network()
    master.connect(interface="virtual", channel=channel)
    try:
        node = BaseNode402(5, _od())
        master.add_node(node)
        node.sdo.RESPONSE_TIMEOUT = 1.0
        node.setup_402_state_machine(read_pdos=False)  # no PDOs: SDO for everything
        node.state = "OPERATION ENABLED"
        assert node.state == "OPERATION ENABLED"
        node.op_mode = "PROFILED POSITION"
        assert node.op_mode == "PROFILED POSITION"
        node.sdo[0x607A].raw = 1000
        node.controlword = 0x1F
        assert node.statusword & BIT12  # set-point acknowledge
        with served.lock:
            assert (served.bench.out.command, served.bench.out.target) == (
                Command.POSITION, 1000)
        node.controlword = 0x0F
        assert not node.statusword & BIT12
        with served.lock:
            served.bench.faults = (DriveFault(FaultCause.SYNC_TIMEOUT),)
            served.bench.step()
            served.bench.step()
        assert node.state == "FAULT"
        with served.lock:
            served.bench.faults = ()
        node.reset_from_fault()
        assert node.state == "OPERATION ENABLED"
        node.state = "SWITCH ON DISABLED"
        with served.lock:
            assert served.bench.out.command == Command.OFF
    finally:
        master.disconnect()
        served.network.disconnect()


# ---------------------------------------------------------------- modes of operation
def test_supported_modes_and_a_mode_not_supported_keeps_the_display() -> None:
    assert SUPPORTED_MODES == 0xA5
    bench = Bench()
    assert bench.out.mode_display == 0
    for asked, shown in [(1, 1), (2, 1), (7, 1), (3, 3), (-1, 3), (0, 3), (6, 6), (9, 6),
                         (8, 8), (10, 8)]:
        assert bench.write(modes_of_operation=asked).mode_display == shown, asked


def test_profile_position_handshake_and_target_reached_by_window_and_time() -> None:
    bench = Bench(position_window=5, position_window_time=20)
    out = bench.enable(1)
    assert (out.command, out.target) == (Command.POSITION, 100)
    bench.write(target_position=1000)
    assert bench.out.target == 100  # nothing until bit 4 rises
    out = bench.cw(0x1F)
    assert (out.command, out.target) == (Command.POSITION, 1000)
    assert status(out, BIT12 | TARGET_REACHED) == BIT12
    assert status(bench.cw(0x1F), BIT12) == BIT12  # still acknowledged while bit 4 is 1
    assert status(bench.cw(0x0F), BIT12) == 0
    bench.report(0.1, position=994)
    assert status(bench.report(0.05), TARGET_REACHED) == 0  # outside the window
    bench.report(0.001, position=996)
    assert status(bench.report(0.019), TARGET_REACHED) == 0  # 19 ms
    assert status(bench.report(0.001), TARGET_REACHED) == TARGET_REACHED  # 20 ms
    assert status(bench.report(0.001, position=1006), TARGET_REACHED) == 0
    bench.report(0.001, position=1004)
    assert status(bench.report(0.020), TARGET_REACHED) == TARGET_REACHED


def test_a_set_point_while_moving_waits_in_the_buffer_or_replaces_with_bit_5() -> None:
    bench = Bench(position_window=5, position_window_time=10)
    bench.enable(1)
    bench.write(target_position=2000)
    bench.cw(0x1F)
    bench.cw(0x0F)
    bench.write(target_position=3000)
    out = bench.cw(0x1F)  # bit 5 0: buffered (acknowledged), the move goes on
    assert out.target == 2000 and status(out, BIT12) == BIT12
    bench.cw(0x0F)
    bench.write(target_position=4000)
    out = bench.cw(0x1F)  # the buffer is full: not acknowledged
    assert out.target == 2000 and status(out, BIT12) == 0
    bench.report(0.01, position=2000)
    out = bench.report(0.01)  # 2000 reached: 3000 from the buffer, 4000 into it
    assert out.target == 3000 and status(out, BIT12 | TARGET_REACHED) == BIT12
    bench.cw(0x0F)
    bench.write(target_position=-500)
    out = bench.cw(0x3F)  # bit 5: change set immediately
    assert out.target == -500 and status(out, BIT12) == BIT12
    bench.cw(0x2F)
    bench.report(0.01, position=-500)
    assert status(bench.report(0.01), TARGET_REACHED) == TARGET_REACHED  # buffer emptied


def test_relative_set_points_add_to_the_preceding_one() -> None:
    bench = Bench()
    bench.enable(1)
    bench.write(target_position=300)
    assert bench.cw(0x5F).target == 400  # bit 6: 100 (held) + 300
    bench.cw(0x4F)
    assert bench.cw(0x7F).target == 700  # immediately, relative to 400
    bench.cw(0x0F)
    bench.write(target_position=-50)
    assert bench.cw(0x1F).target == 700  # absolute, but 700 not reached: buffered
    bench.cw(0x0F)
    bench.report(0.001, position=700)
    assert bench.report(0.02).target == -50


def test_software_limits_clamp_the_target_and_raise_bit_11() -> None:
    bench = Bench(min_position_limit=-500, max_position_limit=500)
    bench.enable(1)
    bench.write(target_position=1000)
    out = bench.cw(0x1F)
    assert out.target == 500 and status(out, LIMIT) == LIMIT
    bench.report(0.001, position=500)
    out = bench.report(0.02)
    assert status(out, LIMIT | TARGET_REACHED) == LIMIT | TARGET_REACHED
    bench.cw(0x0F)
    bench.write(target_position=-600)
    assert bench.cw(0x1F).target == -500
    bench.cw(0x0F)
    bench.write(target_position=200)
    out = bench.cw(0x3F)
    assert out.target == 200 and status(out, LIMIT) == 0
    out = bench.report(0.001, position=-501)  # the joint itself outside 0x607D
    assert status(out, LIMIT) == LIMIT
    assert status(bench.cw(0x00), LIMIT) == LIMIT  # in any state
    # beyond the Target edge's range (16 bit) when 0x607D is wider
    wide = Bench(min_position_limit=-100000, max_position_limit=100000)
    wide.enable(1)
    wide.write(target_position=-70000)
    assert wide.cw(0x1F).target == -32768
    # min > max: no software limits (the edge's range only)
    off = Bench(min_position_limit=10, max_position_limit=-10)
    off.enable(1)
    off.write(target_position=5000)
    out = off.cw(0x1F)
    assert out.target == 5000 and status(out, LIMIT) == 0


def test_profile_velocity_sets_max_velocity() -> None:
    bench = Bench()
    assert bench.out.max_velocity == 500  # the tree's (0x6081 default 500 000 counts/s)
    for counts_per_s, raw in [(250_000, 250), (1, 1), (1499, 1), (1500, 2), (0, 0),
                              (10**9, 32767)]:
        assert bench.write(profile_velocity=counts_per_s).max_velocity == raw


def test_halt_brakes_then_holds_and_resumes() -> None:
    bench = Bench()
    bench.enable(1)
    bench.write(target_position=5000)
    bench.cw(0x1F)
    bench.report(0.1, position=2000, velocity=3000)
    out = bench.cw(0x11F)
    assert (out.command, out.target_vel) == (Command.VELOCITY, 0)
    assert status(out, TARGET_REACHED) == 0
    out = bench.report(0.05, position=2300, velocity=51)
    assert out.command == Command.VELOCITY
    out = bench.report(0.01, position=2301, velocity=50)
    assert (out.command, out.target) == (Command.POSITION, 2301)
    assert status(out, TARGET_REACHED) == TARGET_REACHED
    assert bench.report(0.01, position=2290, velocity=-400).target == 2301  # holds
    out = bench.cw(0x01F)
    assert (out.command, out.target) == (Command.POSITION, 5000)


def test_profile_velocity_mode() -> None:
    bench = Bench(velocity_window=50, velocity_window_time=20, velocity_threshold=50,
                  velocity_threshold_time=10)
    bench.write(target_velocity=2000)
    out = bench.enable(3)
    assert (out.command, out.target_vel) == (Command.VELOCITY, 2000)
    assert status(out, TARGET_REACHED | BIT12) == 0
    assert status(bench.report(0.01), BIT12) == BIT12  # speed 0 for 10 ms
    bench.report(0.05, velocity=1949)
    assert status(bench.report(0.05), TARGET_REACHED) == 0
    bench.report(0.001, velocity=1951)
    out = bench.report(0.02)
    assert status(out, TARGET_REACHED | BIT12) == TARGET_REACHED
    out = bench.write(target_velocity=-100000)
    assert out.target_vel == -32768 and status(out, LIMIT) == LIMIT
    bench.write(target_velocity=500)
    out = bench.report(0.001, position=10000)  # at Max Position, asked onwards
    assert status(out, LIMIT) == LIMIT
    out = bench.write(target_velocity=-500)
    assert status(out, LIMIT) == 0
    out = bench.cw(0x10F)
    assert (out.command, out.target_vel) == (Command.VELOCITY, 0)


def _homing_state(out: DriveOutputs) -> str:
    """The homing state canopen's BaseNode402 reads from a statusword."""
    name = "?"
    for key, (mask, bits) in Homing.STATES.items():
        if out.statusword & mask == bits:
            name = key
    return name


def test_homing_by_the_programs_homing_and_its_reset_answer() -> None:
    bench = Bench()
    out = bench.enable(6)
    assert _homing_state(out) == "INTERRUPTED"  # not started
    assert (out.command, out.target) == (Command.POSITION, 100)
    assert (out.reset_offset, out.reset_pwm) == (-12725, -7000)  # the tree's
    out = bench.cw(0x1F)
    assert out.command == Command.HOMING and _homing_state(out) == "IN PROGRESS"
    assert _homing_state(bench.report(0.1)) == "IN PROGRESS"  # Reset Answer 0: before
    bench.report(0.1, reset_answer=1, position=-20, velocity=-800)
    out = bench.report(1.0, reset_answer=2, position=-12725, velocity=0)
    assert out.command == Command.HOMING and _homing_state(out) == "ATTAINED"
    out = bench.report(0.02)
    assert _homing_state(out) == "TARGET REACHED"
    out = bench.cw(0x0F)  # POSITION where it stands, within the limits as the program
    assert (out.command, out.target) == (Command.POSITION, -10000)  # clamps it
    assert _homing_state(out) == "TARGET REACHED" and status(out, LIMIT) == LIMIT


def test_homing_again_from_a_homed_axis_waits_for_the_runs_own_answer() -> None:
    bench = Bench()
    bench.report(reset_answer=2)
    bench.enable(6)
    bench.cw(0x1F)
    assert _homing_state(bench.report(0.299)) == "IN PROGRESS"  # the old 2
    assert _homing_state(bench.report(0.001)) == "ATTAINED"  # homed again, at once
    bench.cw(0x0F)
    bench.report(reset_answer=-1)
    bench.cw(0x1F)
    assert _homing_state(bench.report(0.1, reset_answer=2)) == "ATTAINED"  # changed


def test_homing_failure_interruption_and_refusal() -> None:
    bench = Bench()
    bench.enable(6)
    bench.cw(0x1F)
    bench.report(0.1, reset_answer=1, velocity=-600)
    out = bench.report(0.1, reset_answer=-1)
    assert _homing_state(out) == "ERROR VELOCITY IS NOT ZERO"
    out = bench.report(0.01, velocity=0)
    assert _homing_state(out) == "ERROR VELOCITY IS ZERO" and out.command == Command.HOMING
    assert bench.cw(0x0F).command == Command.POSITION
    bench.report(reset_answer=2)
    bench.cw(0x1F)
    out = bench.report(0.1, reset_answer=1, position=50)
    out = bench.cw(0x0F)  # bit 4 back to 0 while under way: interrupted
    assert _homing_state(out) == "INTERRUPTED"
    assert (out.command, out.target) == (Command.POSITION, 50)
    bench.cw(0x1F)
    bench.report(0.1, velocity=-300)
    out = bench.cw(0x11F)  # halt interrupts it too
    assert _homing_state(out) == "INTERRUPTED" and out.command == Command.VELOCITY
    bench.cw(0x0F)
    bench.report(0.1, velocity=0)
    for method in (35, 1, 0):
        bench.write(homing_method=method)
        out = bench.cw(0x1F)
        assert _homing_state(out) == "ERROR VELOCITY IS ZERO" and out.command != Command.HOMING
        bench.cw(0x0F)
    wheel = Bench(replace(EYE, reset_pwm=0))  # an axis that cannot home
    wheel.enable(6)
    assert _homing_state(wheel.cw(0x1F)) == "ERROR VELOCITY IS ZERO"
    far = Bench(home_offset=40000)  # outside Reset Offset's range
    far.enable(6)
    assert _homing_state(far.cw(0x1F)) == "ERROR VELOCITY IS ZERO"


def test_homing_method_signs_reset_pwm() -> None:
    bench = Bench()
    assert [bench.write(homing_method=m).reset_pwm for m in (-1, -3, -4, 35)] == [
        -7000, -7000, 7000, -7000]
    out = bench.write(home_offset=-40000)
    assert out.reset_offset == -32768


def test_cyclic_synchronous_position_takes_the_target_at_each_sync() -> None:
    bench = Bench(following_error_window=100, following_error_time_out=10)
    bench.write(target_position=900)
    out = bench.enable(8)
    assert (out.command, out.target) == (Command.POSITION, 100)  # holds until a SYNC
    assert status(out, BIT12 | BIT13) == 0
    out = bench.step(0.01, sync=True)
    assert out.target == 900 and status(out, BIT12 | BIT13) == BIT12
    assert bench.write(target_position=950).target == 900  # taken at the next SYNC only
    assert status(bench.step(0.009), BIT13) == 0  # 800 behind for 9 ms ...
    assert status(bench.step(0.001, sync=True), BIT13) == BIT13  # ... and 10 ms
    assert bench.out.target == 950
    assert status(bench.report(0.001, position=940), BIT13) == 0
    bench.write(target_position=20000)
    out = bench.step(0.01, sync=True)
    assert out.target == 10000 and status(out, LIMIT) == LIMIT
    bench.report(0.001, velocity=500)
    out = bench.cw(0x10F)
    assert status(out, BIT12) == 0 and out.command == Command.VELOCITY
    bench.write(target_position=1000)
    bench.joint = replace(bench.joint, velocity=0)
    out = bench.step(0.01, sync=True)  # standstill: holds, the SYNC's target ignored
    assert (out.command, out.target) == (Command.POSITION, 940)
    out = bench.cw(0x0F)
    assert (out.target, status(out, BIT12)) == (940, 0)  # where it stopped, until a SYNC
    assert bench.step(0.01, sync=True).target == 1000


def test_a_mode_chosen_while_enabled_is_entered_at_once() -> None:
    bench = Bench()
    bench.enable(6)
    bench.cw(0x1F)
    assert bench.report(0.1, reset_answer=1, position=-300).command == Command.HOMING
    out = bench.write(modes_of_operation=1)
    assert (out.mode_display, out.command, out.target) == (1, Command.POSITION, -300)
    bench.write(target_velocity=700)
    out = bench.write(modes_of_operation=3)
    assert (out.command, out.target_vel) == (Command.VELOCITY, 700)
    out = bench.write(modes_of_operation=2)  # not supported: PV goes on
    assert (out.mode_display, out.command) == (3, Command.VELOCITY)


# ---------------------------------------------------------------- quick stop
@pytest.mark.parametrize("option", [1, 2, 3, 4, -5, 99])
def test_quick_stop_brakes_then_switch_on_disabled(option: int) -> None:
    bench = Bench(quick_stop_option=option)
    bench.enable(3)
    bench.write(target_velocity=3000)
    bench.report(0.1, velocity=3000)
    out = bench.cw(0x0B)
    assert (out.transitions, out.statusword) == ((11,), QSA)
    assert (out.command, out.target_vel) == (Command.VELOCITY, 0)
    assert bench.cw(0x0F).state is S.QUICK_STOP_ACTIVE  # no 16 with these options
    out = bench.report(0.05, velocity=40, position=400)
    assert (out.transitions, out.state, out.command) == ((12,), S.SWITCH_ON_DISABLED,
                                                         Command.OFF)


@pytest.mark.parametrize("option", [5, 6, 7, 8])
def test_quick_stop_brakes_then_stays_and_holds(option: int) -> None:
    bench = Bench(quick_stop_option=option)
    bench.enable(1)
    bench.report(0.1, velocity=-2000)
    assert bench.cw(0x02).command == Command.VELOCITY
    out = bench.report(0.05, velocity=0, position=77)
    assert (out.state, out.command, out.target) == (S.QUICK_STOP_ACTIVE, Command.POSITION, 77)
    assert bench.report(0.05, position=70).target == 77
    out = bench.cw(0x0F)
    assert (out.transitions, out.state) == ((16,), S.OPERATION_ENABLED)
    assert (out.command, out.target) == (Command.POSITION, 70)  # PP anew: where it stands


def test_quick_stop_at_standstill_is_shown_for_one_update() -> None:
    """Option 2 with the joint standing: complete at once, but QUICK STOP ACTIVE is
    shown until the next update (canopen's state setter waits to see it)."""
    bench = Bench()
    bench.enable(1)
    out = bench.cw(0x02)
    assert (out.transitions, out.state, out.command) == ((11,), S.QUICK_STOP_ACTIVE,
                                                         Command.POSITION)
    out = bench.step(0.001)
    assert (out.transitions, out.state, out.command) == ((12,), S.SWITCH_ON_DISABLED,
                                                         Command.OFF)


def test_quick_stop_option_0_switches_off_at_once() -> None:
    bench = Bench(quick_stop_option=0)
    bench.enable(3)
    bench.report(0.1, velocity=3000)
    out = bench.cw(0x02)
    assert (out.transitions, out.state, out.command) == ((11, 12), S.SWITCH_ON_DISABLED,
                                                         Command.OFF)


# ---------------------------------------------------------------- faults
EMCYS = [
    (DriveFault(FaultCause.MASTER_HEARTBEAT), Emcy(0x8130, 0x11, bytes([1, 0, 0, 0, 0]))),
    (DriveFault(FaultCause.SYNC_TIMEOUT, detail=300), Emcy(0x8100, 0x11, bytes([2, 44, 1, 0, 0]))),
    (DriveFault(FaultCause.BUS_OFF), Emcy(0x8140, 0x11, bytes([3, 0, 0, 0, 0]))),
    (DriveFault(FaultCause.BOARD_LOST, detail=7), Emcy(0xFF01, 0x81, bytes([4, 7, 0, 0, 0]))),
    (DriveFault(FaultCause.BOARD_LATCHED, detail=52),
     Emcy(0xFF02, 0x81, bytes([5, 52, 0, 0, 0]))),
    (DriveFault(FaultCause.BOARD_ERROR, code=0x10, detail=0x01020304),
     Emcy(0xFF90, 0x81, bytes([6, 4, 3, 2, 1]))),
]


@pytest.mark.parametrize(("fault", "emcy"), EMCYS)
def test_each_cause_enters_fault_with_its_emcy(fault: DriveFault, emcy: Emcy) -> None:
    bench = Bench()
    bench.enable(3)
    bench.write(target_velocity=1000)
    bench.faults = (fault,)
    out = bench.step(0.001)
    assert (out.state, out.command, out.emcys) == (S.FAULT_REACTION_ACTIVE, Command.OFF,
                                                    (emcy,))
    assert (out.error_code, out.error_register) == (emcy.code, emcy.register)
    out = bench.step(0.001)
    assert (out.state, out.emcys, out.error_code) == (S.FAULT, (), emcy.code)
    out = bench.cw(0x80)  # refused: the cause lasts
    assert (out.state, out.transitions, out.emcys) == (S.FAULT, (), ())
    bench.faults = ()
    assert bench.step(0.001).state is S.FAULT  # no new edge, no reset
    assert bench.cw(0x80).state is S.FAULT  # bit 7 stayed 1: no edge
    bench.cw(0x00)
    out = bench.cw(0x80)
    assert (out.state, out.transitions, out.emcys) == (S.SWITCH_ON_DISABLED, (15,),
                                                        (ERROR_RESET,))
    assert (out.error_code, out.error_register, out.statusword) == (0, 0, SOD)


def test_a_new_cause_while_in_fault_sends_its_emcy_too() -> None:
    bench = Bench()
    lost, latched = DriveFault(FaultCause.BOARD_LOST), DriveFault(FaultCause.BOARD_LATCHED)
    bench.faults = (lost,)
    assert bench.step(0.001).emcys == (lost.emcy(),)
    assert bench.step(0.001).emcys == ()  # the same cause: sent once
    bench.faults = (lost, latched)
    out = bench.step(0.001)
    assert (out.emcys, out.error_code) == ((latched.emcy(),), 0xFF02)
    bench.faults = ()
    bench.step(0.001)
    bench.faults = (lost,)  # gone and back: a new occurrence
    assert bench.step(0.001).emcys == (lost.emcy(),)


def test_a_fault_before_the_joint_reports_and_an_event_fault() -> None:
    drive = Drive402(EYE)
    error = DriveFault(FaultCause.BOARD_ERROR, code=0x0B)
    out = drive.update(0.0, EYE.defaults(), JointReport(), (error,))
    assert out.transitions == (0, 13) and out.statusword == 0x000F | REMOTE
    out = drive.update(0.001, EYE.defaults(), JointReport(valid=True))  # the event passed
    assert (out.state, out.error_code) == (S.FAULT, 0xFF8B)
    out = drive.update(0.002, replace(EYE.defaults(), controlword=0x80),
                       JointReport(valid=True))
    assert out.state is S.SWITCH_ON_DISABLED


def test_faults_are_checked() -> None:
    with pytest.raises(ValueError, match=r"0\.\.127"):
        DriveFault(FaultCause.BOARD_ERROR, code=0x80)
    with pytest.raises(ValueError, match="UNSIGNED32"):
        DriveFault(FaultCause.BOARD_LOST, detail=-1)


def test_objects_default_to_the_trees_values() -> None:
    objects = EYE.defaults()
    assert (objects.profile_velocity, objects.min_position_limit,
            objects.max_position_limit, objects.home_offset) == (500_000, -10000, 10000,
                                                                 -12725)
    assert objects == replace(ObjectValues(), profile_velocity=500_000,
                              min_position_limit=-10000, max_position_limit=10000,
                              home_offset=-12725)


def test_every_controlword_keeps_the_axis_off_below_operation_enabled() -> None:
    """Whatever the master writes, in any order, the axis runs only in OPERATION ENABLED
    and QUICK STOP ACTIVE (a property over every sequence of the commands' patterns)."""
    words = (0x00, 0x02, 0x06, 0x07, 0x0F, 0x80, 0x1F, 0x10F)
    for sequence in itertools.product(words, repeat=4):
        bench = Bench(quick_stop_option=6)
        bench.write(modes_of_operation=1)
        for word in sequence:
            out = bench.cw(word)
            running = out.state in (S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE)
            assert (out.command != Command.OFF) == running, sequence
            assert _named(out.statusword) == out.state.text, sequence

