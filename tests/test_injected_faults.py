"""Injected faults on the board side, in virtual time: REJOIN, a power loss, a reset of the
DSP, bus-off, a cut cable and the emergency stop, each as the hardware does it - what the
board is and shows meanwhile, what it sends (and does not), what it answers when it
returns, where its joint is and what its sensors read (``man/ucom-protocol.7``, INIT
CHAIN, Rejoin; ``ucom(1)``, SCENARIOS).

The PC side is the product's exchange (:class:`tests.runtime_rig.RunHost`) on ARMAR-III's
CAN0 (neck, head left, head right), whose boards start their program by AutoStart; a
:class:`Wire` node on the bus keeps every frame that ends on it."""

from __future__ import annotations

import math
from collections.abc import Iterator

import can
import pytest

from tests.conftest import chain_topology
from tests.runtime_rig import RunHost, programmed
from ucom_tools.config.scenario import FaultKind, InjectedFault, Scenario
from ucom_tools.edgelists import armar3
from ucom_tools.edgelists.armar3 import Command
from ucom_tools.edgelists.model import EdgeKind
from ucom_tools.errors import InputError
from ucom_tools.ops.robot import ConnectSpec, open_robot
from ucom_tools.protocol.bootloader import BootloaderClient
from ucom_tools.protocol.link import Link
from ucom_tools.virtual.board.ucom import VirtualBoard
from ucom_tools.virtual.canbus import VirtualUcomBus
from ucom_tools.virtual.fleet import Fleet
from ucom_tools.virtual.hardware.fpga import QuadratureDecoder
from ucom_tools.virtual.programs.armar3 import Armar3Model
from ucom_tools.wire import mca
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import BoardState, InitAckKind, InitOp, ReadyReason
from ucom_tools.wire.fpga import Reg
from ucom_tools.wire.ids import ALL, Function, encode_id, fixed, seq

HEAD_RIGHT = 3
"""CAN0 board 3: the right eye is its Motor A (joint sensor: Encoder 0, motor: Encoder 1)."""
PRESCALER = [e.name for e in armar3.SPEC.of(EdgeKind.PAR)].index("Encoder Prescaler(BitMask)")
"""PAR index of the encoder prescalers (the eyes' trees: 4 for every axis)."""
_FROM_BOARD = {f.value for f in Function if f.direction.name == "BOARD_TO_HOST"}


class Wire:
    """Every frame that ends on a bus: (end time in us, identifier, data).  Listen-only, as
    a bus analyser: it acknowledges nothing."""

    listening = False

    def __init__(self) -> None:
        self.frames: list[tuple[float, int, bytes]] = []

    def on_frame(self, arbitration_id: int, data: bytes, t_end: float) -> None:
        self.frames.append((t_end, arbitration_id, bytes(data)))

    def since(self, t: float) -> list[tuple[float, int, bytes]]:
        return [f for f in self.frames if f[0] >= t]


def from_board(h: RunHost, n: int, frames: list[tuple[float, int, bytes]],
               ) -> list[tuple[float, int, bytes]]:
    """The frames board ``n`` sent: its SO maps, its generic frames (board -> PC functions
    with its seq ID) and those of a board without a number (0)."""
    maps = {mca.MapFrame(Function.MCA_SENSOR_OUTPUT, p.number, b"\0\0").arbitration_id()
            for p in h.plan.so_maps if p.board == n}
    return [f for f in frames if f[1] in maps or (
        f[1] >> 6 in _FROM_BOARD and not f[1] & 0x20 and f[1] & 0x1F in (n, 0))]


@pytest.fixture
def can0() -> Iterator[tuple[RunHost, Wire]]:
    """CAN0 running its exchange, the right eye moved to 1000 counts and settled."""
    h = RunHost(programmed("armar3", autostart=True), "CAN0")
    wire = Wire()
    h.fleet.bus("CAN0").attach(wire)
    h.bring_up()
    h.set_ci(HEAD_RIGHT, "MotorA Target", 1000)
    h.run(600)
    yield h, wire
    h.close()


def now_us(h: RunHost) -> float:
    return h.fleet.clock.now


def rejoin(h: RunHost, wire: Wire, n: int) -> list[m.InitAck]:
    """Init Request REJOIN n to board n's serial; the Init Acks that came within 5 ms."""
    board = h.boards[n - 1]
    t = now_us(h)
    h.link.send_raw(encode_id(Function.INIT_REQUEST, ALL),
                    m.InitRequest(InitOp.REJOIN, n, board.identity.serial).encode())
    h.run(5)
    acks = []
    for _, ident, data in wire.since(t):
        if ident >> 6 == Function.INIT_ACK:
            _, ack = m.decode(ident, data)
            assert isinstance(ack, m.InitAck)
            acks.append(ack)
    return acks


def joint_count(board: VirtualBoard, prescale: int = 4) -> int:
    """What an absolute joint sensor on channel 0 reads behind ``prescale``: the plant's
    joint position in edges from its start, divided toward zero."""
    assert board.plant is not None
    axis = board.plant.axes[0]  # type: ignore[attr-defined]
    return int((axis.joint_edges - axis.joint_origin) / prescale)


def back_up(h: RunHost, wire: Wire, n: int) -> dict[str, int]:
    """What the board answers when it is back after losing its RAM, asked as the protocol
    page says: REJOIN, Start (its AutoStart program is running already), MCA Start QUERY
    (STOPPED, unconfigured); then its joint sensor and motor encoder (SO Encoder 0 and 1,
    read back) once its tree's encoder prescaler is written again, before anything could
    move the joint."""
    (ack,) = rejoin(h, wire, n)
    assert (ack.kind, ack.seq_id) == (InitAckKind.ASSIGNED, n)
    (started,) = h.boot.start(seq(n))
    assert started.started and started.state is BoardState.RUNNING_FLASH
    assert h.mca.query(seq(n)).state is mca.RunState.STOPPED
    edges = h.configured[n].edges  # the program's records, as described before
    h.mca.write(seq(n), mca.Kind.PAR, PRESCALER, [0x444],  # the eyes' trees' value
                edges.par)
    h.run(3)  # a cycle takes it
    joint, motor = h.mca.dump(seq(n), mca.Kind.SO, 0, 2, edges.so)
    return {"joint": joint, "motor": motor}


# ---------------------------------------------------------------------- REJOIN
def test_rejoin_numbers_only_the_board_with_that_serial_and_answers_at_its_reply_time(
        ) -> None:
    fleet = chain_topology(3)
    bus = VirtualUcomBus("CAN0", fleet=fleet)
    try:
        link = Link(bus, "CAN0")
        sim = fleet.bus("CAN0")
        wire = Wire()
        sim.attach(wire)
        boards = fleet.boards["CAN0"]
        pins = [(b.in_drive, b.out_drive) for b in boards]
        t = sim.now
        link.send_raw(encode_id(Function.INIT_REQUEST, ALL),
                      m.InitRequest(InitOp.REJOIN, 7, boards[1].identity.serial).encode())
        sent_end = wire.frames[-1][0]
        sim.run_until(t + 5000)
        answers = [f for f in wire.since(t) if f[1] >> 6 == Function.INIT_ACK]
        assert [b.seq_id for b in boards] == [0, 7, 0]
        assert [(b.in_drive, b.out_drive) for b in boards] == pins  # no pin moved
        ((t_ack, ident, data),) = answers
        assert ident == encode_id(Function.INIT_ACK, seq(7))
        _, ack = m.decode(ident, data)
        assert (ack.kind, ack.seq_id, ack.serial) == (InitAckKind.ASSIGNED, 7,
                                                      boards[1].identity.serial)
        # at its reply time after the request ended (then the ack's own bits on the wire)
        reply = boards[1].timing.reply_us
        assert reply <= t_ack - sent_end <= reply + 200
        # a serial nobody has: no answer, nothing changes
        t = sim.now
        link.send_raw(encode_id(Function.INIT_REQUEST, ALL),
                      m.InitRequest(InitOp.REJOIN, 2, 0xDEADBEEF).encode())
        sim.run_until(t + 5000)
        assert [f for f in wire.since(t) if f[1] >> 6 == Function.INIT_ACK] == []
        assert [b.seq_id for b in boards] == [0, 7, 0]
    finally:
        bus.shutdown()


def test_rejoin_renumbers_a_running_program_and_leaves_its_run_state(can0) -> None:
    h, wire = can0
    board = h.boards[0]
    before = h.runtime(1).state
    (ack,) = rejoin(h, wire, 1)  # its own number again: it answers, nothing else changes
    assert (ack.kind, ack.seq_id) == (InitAckKind.ASSIGNED, 1)
    assert board.seq_id == 1 and h.runtime(1).state is before is mca.RunState.RUNNING
    assert h.mca.query(seq(1)).state is mca.RunState.RUNNING


# ---------------------------------------------------------------------- power-off
def test_power_off_silences_the_board_and_it_comes_back_unnumbered_with_its_joint(
        can0) -> None:
    h, wire = can0
    board = h.boards[HEAD_RIGHT - 1]
    so_before = h.so(HEAD_RIGHT, "Encoder 0")
    count_before = joint_count(board)
    angle_before = board.plant.joint_angle(0)  # type: ignore[union-attr]
    assert so_before is not None and abs(so_before - 1000) <= 2
    assert abs(count_before - so_before) <= 1
    t0 = now_us(h)
    text = h.fleet.inject(InjectedFault(FaultKind.POWER_OFF, "CAN0", HEAD_RIGHT, 0.2))
    assert text == "CAN0 board 3 (head right) powered off for 0.2 s"
    assert not board.powered and board.seq_id == 0 and board.application is None
    assert board.leds() == {"red": "off", "yellow": "off", "green": "off"}
    (shown,) = h.fleet.snapshot()["injected"]
    assert (shown["kind"], shown["target"], shown["until_s"] - shown["since_s"]) == (
        "power-off", "CAN0/3", pytest.approx(0.2))
    h.run(150)
    during = wire.since(t0)
    assert from_board(h, HEAD_RIGHT, during) == []  # silent at once
    assert from_board(h, 1, during) and from_board(h, 2, during)  # the others run on
    h.run(100)  # power returns at 0.2 s: AutoStart runs its program, STOPPED, no seq ID
    assert board.powered and board.seq_id == 0
    assert board.state is BoardState.RUNNING_FLASH
    assert board.application is not None and board.application.runtime is not None
    assert board.application.runtime.state is mca.RunState.STOPPED
    assert board.fpga.read(Reg.OUTPUT_ENABLE) == 0
    assert board.leds()["green"] == "blink"
    assert h.fleet.snapshot()["injected"] == []
    assert from_board(h, HEAD_RIGHT, wire.since(t0)) == []  # without a number: nothing
    # the joint held where it stood (the eye at rest, its stage off: nothing moves it)
    assert board.plant.joint_angle(0) == pytest.approx(angle_before, abs=1e-6)  # type: ignore[union-attr]
    readings = back_up(h, wire, HEAD_RIGHT)
    # the joint sensor is absolute: the same position; the motor encoder restarted at 0
    assert readings == {"joint": joint_count(board), "motor": 0}
    assert abs(readings["joint"] - so_before) <= 1
    # the other boards' exchange never stopped
    assert h.runtime(1).state is h.runtime(2).state is mca.RunState.RUNNING


def test_a_joint_coasts_while_its_board_is_off_and_reads_where_it_came_to_rest(can0) -> None:
    h, wire = can0
    board = h.boards[HEAD_RIGHT - 1]
    h.set_ci(HEAD_RIGHT, "MotorA Target", -9000)  # far: the eye runs at its top speed
    h.run(40)
    assert board.plant is not None
    moving = board.plant.joint_velocity(0)
    assert abs(moving) > 0.01
    at_cut = joint_count(board)
    h.fleet.inject(InjectedFault(FaultKind.POWER_OFF, "CAN0", HEAD_RIGHT, 0.8))
    h.run(900)
    # it coasted on (stage off: only friction stops it; while the board was off, the
    # plant caught up when its program started again), then stood; the motor encoder,
    # off meanwhile, counted none of it
    assert board.plant.joint_velocity(0) == 0.0
    coasted = joint_count(board) - at_cut
    assert coasted != 0 and math.copysign(1, coasted) == math.copysign(1, moving)
    assert back_up(h, wire, HEAD_RIGHT) == {"joint": joint_count(board), "motor": 0}


def test_a_homing_offset_is_gone_after_a_power_loss(can0) -> None:
    h, wire = can0
    board = h.boards[HEAD_RIGHT - 1]
    model = board.application.runtime.model  # type: ignore[union-attr]
    assert isinstance(model, Armar3Model)
    h.set_ci(HEAD_RIGHT, "MotorA Command", Command.OFF)  # stage off: the eye stays
    h.run(5)
    model.axes[0].set_joint(board, False, 30000)  # as homing writes it (Reset Offset)
    h.run(20)
    assert h.so(HEAD_RIGHT, "Encoder 0") == 30000
    h.fleet.inject(InjectedFault(FaultKind.POWER_OFF, "CAN0", HEAD_RIGHT, 0.05))
    h.run(80)
    readings = back_up(h, wire, HEAD_RIGHT)
    assert abs(readings["joint"] - 1000) <= 2  # the sensor's own position, no offset


# ---------------------------------------------------------------------- reset
def test_a_reset_is_a_power_cycle_without_the_pause_and_loses_the_seq_id(can0) -> None:
    h, wire = can0
    board = h.boards[HEAD_RIGHT - 1]
    reset_us = board.timing.reset_us
    t0 = now_us(h)
    text = h.fleet.inject(InjectedFault(FaultKind.RESET, "CAN0", HEAD_RIGHT))
    assert text == "CAN0 board 3 (head right) reset: silent for 0.002 s"
    assert not board.powered and board.seq_id == 0
    h.fleet.clock.run_until(t0 + reset_us - 1)
    assert not board.powered
    h.fleet.clock.run_until(t0 + reset_us)
    assert board.powered and board.seq_id == 0 and board.application is not None
    h.run(50)
    assert from_board(h, HEAD_RIGHT, wire.since(t0)) == []  # no number: nothing
    assert back_up(h, wire, HEAD_RIGHT)["motor"] == 0
    # a reset held longer: silent for the reset time plus 'for'
    t1 = now_us(h)
    h.fleet.inject(InjectedFault(FaultKind.RESET, "CAN0", HEAD_RIGHT, 0.1))
    h.fleet.clock.run_until(t1 + 100_000 + reset_us - 1)
    assert not board.powered
    h.fleet.clock.run_until(t1 + 100_000 + reset_us)
    assert board.powered


def test_a_reset_board_with_a_fixed_id_announces_itself_a_commanded_reset_keeps_the_seq_id(
        ) -> None:
    fleet = chain_topology(2, extra={1: "fixed_id = 12"})
    bus = VirtualUcomBus("CAN0", fleet=fleet)
    try:
        client = BootloaderClient(Link(bus, "CAN0"))
        client.init_chain()
        boards = fleet.boards["CAN0"]
        assert [b.seq_id for b in boards] == [1, 2]
        replies = client.reset(seq(2))  # function 0: the seq ID stays
        assert [r.message.reason for r in replies] == [ReadyReason.BOOT]
        assert boards[1].seq_id == 2
        sim = fleet.bus("CAN0")
        wire = Wire()
        sim.attach(wire)
        t = sim.now
        fleet.inject(InjectedFault(FaultKind.RESET, "CAN0", 2))
        sim.run_until(t + 10_000)
        assert boards[1].seq_id == 0
        readies = [f for f in wire.since(t) if f[1] >> 6 == Function.READY]
        assert [f[1] for f in readies] == [encode_id(Function.READY, fixed(12))]
        _, ready = m.decode(readies[0][1], readies[0][2])
        assert ready.reason is ReadyReason.BOOT and ready.value32 == boards[1].identity.serial
        assert readies[0][0] >= t + boards[1].timing.reset_us
    finally:
        bus.shutdown()


# ---------------------------------------------------------------------- bus-off
def test_a_short_bus_off_loses_the_boards_frames_and_the_exchange_goes_on(can0) -> None:
    h, wire = can0
    board = h.boards[HEAD_RIGHT - 1]
    runtime = h.runtime(HEAD_RIGHT)
    cycles = runtime.stats.cycles
    t0 = now_us(h)
    text = h.fleet.inject(InjectedFault(FaultKind.BUS_OFF, "CAN0", HEAD_RIGHT, 0.02))
    assert text == "CAN0 board 3 (head right) bus-off for 0.02 s"
    assert board.leds()["red"] == "on" and board.bus_off and board.powered
    h.run(15)
    assert from_board(h, HEAD_RIGHT, wire.since(t0)) == []
    assert runtime.stats.cycles - cycles >= 14  # its program runs on
    h.run(40)
    assert not board.bus_off and board.leds()["red"] == "off"
    assert board.seq_id == HEAD_RIGHT and runtime.state is mca.RunState.RUNNING
    assert from_board(h, HEAD_RIGHT, wire.since(t0 + 20_000))  # its maps again
    assert abs(h.so(HEAD_RIGHT, "Encoder 0") - 1000) <= 2  # type: ignore[operator]


def test_a_long_bus_off_lets_the_watchdog_stop_the_motors_and_its_error_is_lost(can0) -> None:
    h, wire = can0
    board = h.boards[HEAD_RIGHT - 1]
    runtime = h.runtime(HEAD_RIGHT)
    t0 = now_us(h)
    h.fleet.inject(InjectedFault(FaultKind.BUS_OFF, "CAN0", HEAD_RIGHT, 0.2))
    h.run(100)
    # no MCA Alive reached it for the watchdog time: LATCHED, every motor off
    assert runtime.state is mca.RunState.LATCHED
    assert board.fpga.read(Reg.OUTPUT_ENABLE) == 0
    assert board.leds()["red"] == "on"
    h.run(150)
    assert not board.bus_off
    sent = from_board(h, HEAD_RIGHT, wire.since(t0))
    assert [f for f in sent if f[0] < t0 + 200_000] == []
    assert not [f for f in sent if f[1] >> 6 == Function.ERROR  # Error WATCHDOG was lost
                and f[2][1] == Function.MCA_ALIVE]
    assert board.leds()["red"] == "on"  # the latch holds: red stays lit
    # RAM and seq ID kept: it answers at once, latched, until MCA Start
    assert h.mca.query(seq(HEAD_RIGHT)).state is mca.RunState.LATCHED
    assert h.mca.start(seq(HEAD_RIGHT)).state is mca.RunState.RUNNING


# ---------------------------------------------------------------------- cable
def test_a_cut_cable_loses_the_frames_both_ways_and_the_watchdogs_fire(can0) -> None:
    h, _ = can0
    sim = h.fleet.bus("CAN0")
    received = []
    assert h.can.state is can.BusState.ACTIVE
    text = h.fleet.inject(InjectedFault(FaultKind.CABLE, "CAN0", None, 0.1))
    assert text == "CAN0 cut from the PC for 0.1 s"
    assert h.can.state is can.BusState.PASSIVE  # nobody acknowledges the PC
    # the boards still hear each other: a board's frame is acknowledged
    assert sim.acknowledged(h.boards[0])
    sent = sim.stats.function_counts[Function.MCA_SENSOR_OUTPUT]
    t0 = now_us(h)
    while now_us(h) < t0 + 80_000:
        msg = h.can.recv(0.001)
        if msg is not None:
            received.append(msg)
    h.run(1)
    assert received == []  # nothing of the boards reaches the PC ...
    assert sim.stats.function_counts[Function.MCA_SENSOR_OUTPUT] > sent  # ... they sent
    # ... and nothing of the PC reaches them: every watchdog fired
    assert all(h.runtime(n).state is mca.RunState.LATCHED for n in (1, 2, 3))
    h.run(30)
    assert h.can.state is can.BusState.ACTIVE and not sim.cable_cut
    assert h.mca.query(seq(2)).state is mca.RunState.LATCHED


def test_a_host_alone_with_unpowered_boards_is_error_passive(can0) -> None:
    h, _ = can0
    h.fleet.inject(InjectedFault(FaultKind.ESTOP, None, None, 0.05))
    assert h.can.state is can.BusState.PASSIVE
    h.run(60)
    assert h.can.state is can.BusState.ACTIVE


# ---------------------------------------------------------------------- estop
def test_the_emergency_stop_powers_every_board_off_and_on_each_joint_where_it_stood(
        ) -> None:
    fleet = programmed("armar3", autostart=True)
    hosts = [RunHost(fleet, bus) for bus in fleet.buses]
    wire = Wire()
    fleet.bus("CAN0").attach(wire)
    try:
        for h in hosts:
            h.start_programs()
            h.configure_all()
        for h in hosts:
            h.start_exchange()
        hosts[0].set_ci(HEAD_RIGHT, "MotorA Target", 1000)
        for _ in range(500):
            for h in hosts:
                h.exchange.pump(h.now() + 0.001)
        boards = [b for bs in fleet.boards.values() for b in bs]
        angles = [b.plant.joint_angle(0) for b in boards]  # type: ignore[union-attr]
        text = fleet.inject(InjectedFault(FaultKind.ESTOP, None, None, 0.5))
        assert text == ("emergency stop: all 11 boards of ARMAR-III (CAN0, CAN1, CAN2, "
                        "CAN3) powered off for 0.5 s")
        assert not any(b.powered for b in boards)
        assert all(h.can.state is can.BusState.PASSIVE for h in hosts)
        fleet.run_for(0.51)
        assert all(b.powered and b.seq_id == 0 for b in boards)
        assert all(b.application is not None for b in boards)  # AutoStart
        assert [b.plant.joint_angle(0) for b in boards] == pytest.approx(angles, abs=1e-6)  # type: ignore[union-attr]
        assert back_up(hosts[0], wire, HEAD_RIGHT) == {"joint": joint_count(boards[2]), "motor": 0}
    finally:
        for h in hosts:
            h.close()


def test_faults_that_overlap_add_up(can0) -> None:
    h, _ = can0
    board = h.boards[0]
    h.fleet.inject(InjectedFault(FaultKind.POWER_OFF, "CAN0", 1, 0.1))
    h.fleet.inject(InjectedFault(FaultKind.ESTOP, None, None, 0.2))
    h.run(150)
    assert not board.powered  # its own power-off ended, the emergency stop holds it
    h.run(60)
    assert board.powered and h.boards[1].powered
    assert len(h.fleet.snapshot()["injected"]) == 0


def test_a_board_or_bus_the_fleet_lacks_is_named_with_what_it_has(can0) -> None:
    h, _ = can0
    with pytest.raises(InputError, match=r"board: no board 4 on CAN0; its boards: "
                                         r"1 \(neck\), 2 \(head left\), 3 \(head right\)"):
        h.fleet.inject(InjectedFault(FaultKind.POWER_OFF, "CAN0", 4, 1.0))
    with pytest.raises(InputError, match="bus: no bus 'CAN9' in ARMAR-III; its buses: "
                                         "CAN0, CAN1, CAN2, CAN3"):
        h.fleet.inject(InjectedFault(FaultKind.CABLE, "CAN9", None, 1.0))


# ---------------------------------------------------------------------- the FPGA
def test_an_absolute_channel_reads_its_sensor_prescaled_and_keeps_a_written_offset() -> None:
    position = {"edges": 4005}
    d = QuadratureDecoder(absolute=lambda: position["edges"])
    d.reread()
    assert d.count == 4005
    d.rescale(4)
    assert d.count == 1001  # toward zero, like the counter's own prescaler
    position["edges"] = -4005
    d.feed(-8010)  # fed edges only make it read its sensor again
    assert d.count == (-1001) & 0xFFFF
    d.set(500)  # the program writes it (homing): an offset from here on
    position["edges"] = -4005 + 400
    d.feed(400)
    assert d.count == 600
    incremental = QuadratureDecoder(prescale=4)
    incremental.feed(4005)
    assert incremental.count == 1001 and QuadratureDecoder().absolute is None


# ---------------------------------------------------------------------- scenarios
SCENARIO = """\
[[fault]]
at = 0.1
kind = "power-off"
bus = "CAN0"
board = 3
for = 0.1

[[fault]]
at = 0.3
kind = "estop"
for = 0.05
"""


def test_a_scenario_counts_from_each_buses_own_first_mca_alive() -> None:
    base = programmed("armar3", autostart=True)
    fleet = Fleet(base.topology, scenario=Scenario.parse(SCENARIO, "s.toml"))
    can0, can1 = RunHost(fleet, "CAN0"), RunHost(fleet, "CAN1")
    try:
        assert set(fleet.injector.watchers) == set(fleet.buses)  # estop: on every bus
        can0.bring_up()
        t0 = fleet.injector.started["CAN0"]
        assert "CAN1" not in fleet.injector.started  # no MCA Alive there yet
        clock = fleet.clock
        board = fleet.boards["CAN0"][2]
        for t, powered in [(t0 + 100_000 - 1, True), (t0 + 100_000, False),
                           (t0 + 200_000 - 1, False), (t0 + 200_000, True)]:
            clock.run_until(t)
            assert board.powered is powered, t - t0
        clock.run_until(t0 + 250_000)
        can1.link.send_raw(encode_id(Function.MCA_ALIVE, ALL), b"")  # CAN1's exchange begins
        t1 = fleet.injector.started["CAN1"]
        assert t1 == pytest.approx(t0 + 250_000, abs=500)
        clock.run_until(t1 + 1)
        # once its first Alive came, a bus carries nothing of the scenario: no frame pays
        assert not any(type(n).__name__ == "_FirstAlive" for name in ("CAN0", "CAN1")
                       for n in fleet.bus(name).nodes)
        assert set(fleet.injector.watchers) == {"CAN2", "CAN3"}  # no exchange there yet
        clock.run_until(t0 + 300_000)  # the estop on CAN0, CAN1's still to come
        assert not any(b.powered for b in fleet.boards["CAN0"])
        assert all(b.powered for b in fleet.boards["CAN1"])
        clock.run_until(t1 + 300_000)
        assert not any(b.powered for b in fleet.boards["CAN1"])
        assert [a.fault.kind for a in fleet.injector.active] == [FaultKind.ESTOP]  # CAN1's
        assert all(b.powered for b in fleet.boards["CAN0"])
        clock.run_until(t1 + 350_000)
        assert all(b.powered for bs in fleet.boards.values() for b in bs)
        assert fleet.injector.active == []
    finally:
        can0.close()
        can1.close()


def test_the_in_process_fleet_takes_a_scenario_through_python_can(tmp_path) -> None:
    path = tmp_path / "cable.toml"
    path.write_text('[[fault]]\nat = 0.01\nkind = "cable"\nbus = "CAN1"\nfor = 0.02\n')
    with can.Bus(interface="ucom_virtual", channel="armar3/CAN1", scenario=str(path)) as bus, \
            can.Bus(interface="ucom_virtual", channel="armar3/CAN1") as plain:
        assert bus.fleet is not plain.fleet  # the scenario is part of the shared fleet's key
        assert bus.fleet.scenario is not None and plain.fleet.scenario is None
        bus.send(can.Message(arbitration_id=encode_id(Function.MCA_ALIVE, ALL), data=b"",
                             is_extended_id=False))  # the exchange begins
        start = bus.fleet.injector.started["CAN1"]
        assert bus.recv(0.015) is None
        assert bus.state is can.BusState.PASSIVE and bus.fleet.bus("CAN1").cable_cut
        assert bus.fleet.clock.now - start == pytest.approx(15_000, abs=200)
        assert bus.recv(0.02) is None
        assert bus.state is can.BusState.ACTIVE
    robot = open_robot(ConnectSpec(virtual="armar3", scenario=path))
    try:
        fleets = {h.bus.fleet for h in robot.buses.values()}  # type: ignore[attr-defined]
        assert len(fleets) == 1 and next(iter(fleets)).scenario is not None
    finally:
        robot.close()


def test_a_lauron4_leg_reads_its_joint_absolute_after_a_power_loss() -> None:
    """LAURON-IV's leg program counts its joint sensors through prescaler 10 (0.01 deg);
    after a power loss they read where the joint is, the motor encoders from 0."""
    h = RunHost(programmed("lauron4", autostart=True), "CAN0")
    wire = Wire()
    h.fleet.bus("CAN0").attach(wire)
    try:
        h.bring_up()
        h.set_ci(1, "Leg Mode", 1)  # POSITION
        h.set_ci(1, "Axis1 Position Setpoint", 1000)  # 10 degrees forwards
        h.run(500)
        before = h.so(1, "Axis1 Position")
        assert before is not None and before > 500
        h.fleet.inject(InjectedFault(FaultKind.POWER_OFF, "CAN0", 1, 0.1))
        h.run(150)
        (ack,) = rejoin(h, wire, 1)
        assert ack.seq_id == 1 and h.boot.start(seq(1))[0].started
        assert h.mca.query(seq(1)).state is mca.RunState.STOPPED
        board = h.boards[0]
        leg = board.plant.joints  # type: ignore[union-attr]
        (after,) = h.mca.dump(seq(1), mca.Kind.SO, 0, 1, h.configured[1].edges.so)
        assert after == int((leg[0].joint_edges - leg[0].joint_origin) / 10)
        assert abs(after - before) <= 10  # where it was, but for its coasting
        assert board.fpga.quad[1].count == 0  # the motor encoder, incremental, from 0
    finally:
        h.close()


def test_remote_part_opens_the_virtual_fleet_with_a_scenario(tmp_path) -> None:
    from ucom_tools.ops.remote import RemotePart

    path = tmp_path / "s.toml"
    path.write_text(SCENARIO)
    part = RemotePart.open("armar3", virtual=True, scenario=path, start=False)
    try:
        fleets = {h.bus.fleet for h in part.robot.buses.values()}  # type: ignore[attr-defined]
        (fleet,) = fleets
        assert fleet.scenario.faults == Scenario.parse(SCENARIO).faults
    finally:
        part.close()
    with pytest.raises(can.CanInitializationError, match="scenario= is for the shared fleet"):
        VirtualUcomBus("CAN0", fleet=programmed("armar3"), scenario=path)
