"""The run-time exchange end to end: the armar3 program on virtual ARMAR-III boards, the
host's clients and the start sequence (``man/ucom-protocol.7``, RUN TIME), every frame
over the simulated buses on one fleet clock."""

from __future__ import annotations

import math
from collections.abc import Iterator
from decimal import Decimal

import pytest

from tests.runtime_rig import RunHost, bring_up_robot, programmed, run_robot
from ucom_tools.config.attrtree.match import compare, spec_edges
from ucom_tools.config.attrtree.robot import bind
from ucom_tools.edgelists import armar3, lauron4
from ucom_tools.edgelists.model import EdgeKind
from ucom_tools.errors import BoardError, InputError
from ucom_tools.ops.exchange import ExchangeError, configure
from ucom_tools.virtual.board.runtime import CAN_ERROR_FLASH_US, FRAME_COST_US, OVERRUN_FLASH_US
from ucom_tools.virtual.programs import armar3 as armar3_model
from ucom_tools.wire import mca
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import BoardState, ErrorCode
from ucom_tools.wire.fpga import Reg
from ucom_tools.wire.ids import ALL, Function, encode_id, seq


@pytest.fixture
def can0() -> Iterator[RunHost]:
    h = RunHost(programmed("armar3"), "CAN0")
    yield h
    h.close()


def _errors(h: RunHost, until_s: float = 0.02) -> list[tuple[int, m.Error]]:
    """Errors the boards sent within ``until_s`` (the queue is emptied)."""
    h.mca.pump(h.now() + until_s)
    out = []
    sub = h.mca._sub
    while sub.queue:
        raw = sub.queue.popleft()
        if raw.arbitration_id >> 6 == Function.ERROR:
            address, err = m.decode(raw.arbitration_id, bytes(raw.data))
            assert isinstance(err, m.Error)
            out.append((address.number, err))
    return out


# ---------------------------------------------------------------------- start sequence
def test_a_started_program_announces_itself_stopped_with_its_edge_counts(can0) -> None:
    readies = can0.start_programs()
    assert sorted(readies) == [1, 2, 3]
    for ready in readies.values():
        assert (ready.state, ready.answers, ready.ci, ready.so, ready.par) == (
            mca.RunState.STOPPED, Function.MCA_READY, 13, 20, 38)
    # stopped: every output stage off, whatever the program's defaults say
    for b in can0.boards:
        assert b.fpga.read(Reg.OUTPUT_ENABLE) == 0


def test_descriptions_are_exactly_the_programs_edges_and_match_the_trees(can0) -> None:
    can0.start_programs()
    edges = can0.mca.describe(seq(2))
    for kind in mca.Kind:
        specs = armar3.SPEC.of(EdgeKind(kind))
        got = edges.of(kind)
        assert [r.name for r in got] == [e.name for e in specs]
        assert [(r.width, r.signed, r.exponent, r.minimum, r.maximum, r.unit) for r in got] \
            == [(e.width, e.signed, e.exponent, e.minimum, e.maximum, e.unit) for e in specs]
    longest = max(armar3.SPEC.edges, key=lambda e: len(e.name)).name
    assert longest == "Set Joint Moving Direction(BitMask)"  # 35 characters, 7 segments
    trees = bind(can0.fleet.topology)
    for n in (1, 2, 3):
        block = trees.board("CAN0", n - 1)
        assert compare(block, [(EdgeKind(k), r.name) for k in mca.Kind
                               for r in can0.mca.describe(seq(n)).of(k)]) is None


def test_lost_description_segments_are_asked_for_again_edge_by_edge(can0) -> None:
    can0.start_programs()
    sim = can0.fleet.bus("CAN0")
    lost: list[bytes] = []

    def drop(node: object, arbitration_id: int, data: bytes) -> bool:
        # the host misses the first transmission of two segments (PAR 3, CI 0)
        if arbitration_id >> 6 == Function.MCA_DUMPIO_DESCR and data[:2] in (
                bytes((0x80 | 0, 3)), bytes((0x00 | 0, 0))) and data not in lost \
                and node not in can0.boards:
            lost.append(bytes(data))
            return True
        return False

    sim.drop = drop
    before = sim.stats.by_function[Function.MCA_DUMPIO_DESCR_REQUEST]
    edges = can0.mca.describe(seq(1))
    assert len(lost) == 2
    assert edges.par[3].name == "Set Joint Moving Direction(BitMask)"
    assert edges.ci[0].name == "MotorA Command"
    # one request for all, then one per edge that did not arrive whole
    assert sim.stats.by_function[Function.MCA_DUMPIO_DESCR_REQUEST] - before == 3


def test_configure_writes_the_tree_defaults_exactly_and_they_read_back(can0) -> None:
    can0.start_programs()
    can0.configure_all()
    trees = bind(can0.fleet.topology)
    for n in (1, 2, 3):
        block = trees.board("CAN0", n - 1)
        edges = can0.configured[n].edges
        par = can0.mca.dump(seq(n), mca.Kind.PAR, 0, len(edges.par), edges.par)
        model = can0.runtime(n).model
        assert par == model.par
        for e in block.edges:
            if e.default is None or e.kind.value != "PAR":
                continue
            spec = armar3.SPEC.of(EdgeKind.PAR)[e.index - 33]
            text = e.default.text
            expected = int(text, 16) if "0x" in text.lower() else Decimal(text)
            assert spec.value(par[e.index - 33]) == expected, e.unique
    # the eyes' gain 0.0005 travels as raw 500 at exponent -6
    eyes = can0.configured[2].edges.par
    index = [r.name for r in eyes].index("MotorA P")
    assert (eyes[index].exponent, can0.runtime(2).model.par[index]) == (-6, armar3.SPEC.of(
        EdgeKind.PAR)[index].raw(trees.board("CAN0", 1).generic("MotorA P").default.text))


def test_a_tree_for_another_program_is_refused_before_anything_is_written(can0) -> None:
    can0.start_programs()
    leg = bind(programmed("lauron4").topology).board("CAN0", 0)
    assert compare(leg, spec_edges(armar3.SPEC)) is not None
    assert compare(leg, spec_edges(lauron4.SPEC)) is None
    sim = can0.fleet.bus("CAN0")
    writes = sim.stats.by_function[Function.MCA_PARAMETER]
    with pytest.raises(ExchangeError) as err:
        configure(can0.mca, seq(1), "CAN0 board 1", leg, can0.plan, tree_file="leg.tree")
    assert isinstance(err.value, InputError)
    assert "index 0" in str(err.value) and "Leg Mode" in str(err.value)
    assert str(err.value).startswith("leg.tree:")
    assert sim.stats.by_function[Function.MCA_PARAMETER] == writes


# ---------------------------------------------------------------------- bad input
def test_bad_input_is_refused_whole_and_reported(can0) -> None:
    can0.start_programs()
    edges = can0.mca.describe(seq(1))
    par = can0.runtime(1).model.par
    before = list(par)
    # unknown edge index
    with pytest.raises(BoardError, match="edge"):
        can0.mca.write(seq(1), mca.Kind.PAR, 38, [1], [*edges.par, edges.par[0]])
    # a value out of range (Max PWM 16001): nothing of the frame is taken
    with pytest.raises(BoardError, match="range"):
        can0.mca.write(seq(1), mca.Kind.PAR, 0, [2000, 16001], edges.par)
    assert par == before
    # a frame of the wrong length: half a 4-byte gain
    can0.link.send_raw(encode_id(Function.MCA_PARAMETER, seq(1)), bytes((5, 0, 1)))
    errs = _errors(can0)
    assert [(n, e.code, e.function) for n, e in errs] == [
        (1, ErrorCode.BAD_LENGTH, Function.MCA_PARAMETER)]
    assert par == before
    # a map naming an SO edge that is not there
    with pytest.raises(BoardError, match="map"):
        can0.mca.admin(seq(1), mca.AdminData.so_map(1, 1, [19, 20]))
    # a parameter while stopped is taken: the configuration happens before MCA Start
    can0.mca.write(seq(1), mca.Kind.PAR, 1, [12000], edges.par)
    assert par[1] == 12000
    # a reserved value (MCA Start operation 9)
    can0.link.send_raw(encode_id(Function.MCA_START, seq(1)), bytes((9,)))
    assert [(e.code, e.function) for _, e in _errors(can0)] == [
        (ErrorCode.BAD_VALUE, Function.MCA_START)]
    # a board's message (MCA Ready) is other boards' traffic to a board: ignored
    can0.link.send_raw(encode_id(Function.MCA_READY, seq(1)), bytes(8))
    assert _errors(can0) == []
    # after all that the board is fine and stopped
    assert can0.mca.query(seq(1)).state is mca.RunState.STOPPED


def test_ci_map_values_are_range_checked_slot_by_slot(can0) -> None:
    can0.bring_up()
    model = can0.runtime(1).model
    # CI map 1 feeds board 1's Targets A-C (slots 0-2); Command is 0..3, Target any int16:
    # so range-check a Command map instead
    can0.mca.admin(seq(1), mca.AdminData.ci_map(9, [0, 1, 2, mca.NO_EDGE]))
    can0.mca.send_map(9, mca.pack_values([(2, True)] * 3, [1, 3, 3]))
    _errors(can0)
    assert model.ci[:3] == [1, 3, 3]
    can0.mca.send_map(9, mca.pack_values([(2, True)] * 3, [0, 7, 0]))  # slot 1: 7 > 3
    errs = _errors(can0)
    # function byte 0x80 | 13: about a CI map frame; detail map << 8 | slot
    assert [(e.code, e.function, e.detail) for _, e in errs] == [
        (ErrorCode.OUT_OF_RANGE, 0x80 | Function.MCA_CONTROLLER_INPUT, 9 << 8 | 1)]
    assert model.ci[:3] == [1, 3, 3]  # nothing of the frame taken
    # a frame too short for the map's last slot is refused whole; the error repeats only
    # every 1000th time, as a map frame comes every cycle
    for _ in range(5):
        can0.mca.send_map(9, mca.pack_values([(2, True)] * 2, [2, 2]))
    assert [(e.code, e.function, e.detail) for _, e in _errors(can0)] == []
    assert can0.runtime(1).stats.map_errors == 6
    assert model.ci[:3] == [1, 3, 3]
    assert can0.boards[0].leds()["red"] == "on"  # a frame it could not take


def test_a_ci_map_reaches_exactly_the_boards_that_defined_it_as_they_change(can0) -> None:
    """The bus offers a CI map frame only to the boards whose program defined the map (a
    CAN controller's acceptance filter, cached per identifier) and follows each change at
    once: the map dropped by one board and defined by another, the maps cleared."""
    can0.bring_up()
    one, two = can0.runtime(1).model, can0.runtime(2).model

    def send(values: list[int]) -> None:
        can0.mca.send_map(9, mca.pack_values([(2, True)] * 3, values))
        assert _errors(can0) == []

    can0.mca.admin(seq(1), mca.AdminData.ci_map(9, [0, 1, 2, mca.NO_EDGE]))
    send([1, 2, 3])
    assert one.ci[:3] == [1, 2, 3]
    can0.mca.admin(seq(1), mca.AdminData.ci_map(9, [mca.NO_EDGE] * 4))
    can0.mca.admin(seq(2), mca.AdminData.ci_map(9, [0, 1, 2, mca.NO_EDGE]))
    send([3, 1, 2])
    assert (one.ci[:3], two.ci[:3]) == ([1, 2, 3], [3, 1, 2])
    can0.mca.admin(seq(2), mca.AdminData(mca.AdminOp.CLEAR_MAPS))
    send([0, 3, 3])
    assert (one.ci[:3], two.ci[:3]) == ([1, 2, 3], [3, 1, 2])
    can0.mca.admin(seq(1), mca.AdminData.ci_map(9, [2, 1, 0, mca.NO_EDGE]))
    send([2, 0, 1])
    assert (one.ci[:3], two.ci[:3]) == ([1, 0, 2], [3, 1, 2])


# ---------------------------------------------------------------------- control over CAN
def test_a_target_step_over_can_arrives_without_overshoot_and_settles(can0) -> None:
    can0.bring_up()
    can0.run(20)
    start = can0.so(2, "Encoder 0")
    assert start is not None and abs(start) <= 1
    can0.set_ci(2, "MotorA Target", 1000)
    trace: list[int] = []
    settled_at = None

    def watch(k: int) -> None:
        nonlocal settled_at
        trace.append(can0.so(2, "Encoder 0") or 0)

    can0.run(600, each=watch)
    assert max(trace) - 1000 <= 20  # the eyes' defaults: at most 2 % overshoot
    assert next(k for k, x in enumerate(trace) if x >= 900) < 220  # one map a cycle late
    assert abs(can0.so(2, "Encoder 0") - 1000) <= armar3_model.SETTLED_COUNTS
    assert can0.runtime(2).model.so[armar3.SPEC.of(EdgeKind.SO).index(
        next(e for e in armar3.SPEC.of(EdgeKind.SO) if e.name == "Motor A Settled"))] == 1
    # the other eye did not move; its map kept coming
    assert can0.so(3, "Encoder 0") == 0
    assert can0.mca.image.counts[can0.plan.maps_of(3)[0].number] >= 600


def test_a_gain_change_over_can_acts_in_the_next_cycle(can0) -> None:
    can0.bring_up()
    can0.set_ci(2, "MotorA Target", 2000)
    can0.run(30)
    rt = can0.runtime(2)
    fpga = can0.boards[1].fpga
    assert fpga.read(Reg.PWM0) != 0  # on its way
    edges = can0.configured[2].edges.par
    vp = [r.name for r in edges].index("MotorA Velocity P")
    can0.mca.write(seq(2), mca.Kind.PAR, vp, [0, 0, 0], edges)  # velocity P, I, D
    assert rt.model.par[vp:vp + 3] == [0, 0, 0]  # acknowledged: taken
    cycles = rt.stats.cycles
    while rt.stats.cycles < cycles + 1:
        can0.mca.pump(can0.now() + 0.0001)
    assert fpga.read(Reg.PWM0) == 0  # the next cycle's velocity loop has no gain


# ---------------------------------------------------------------------- watchdog
def test_the_watchdog_stops_every_motor_latches_and_only_mca_start_releases(can0) -> None:
    can0.bring_up()
    for n in (1, 2, 3):
        for a in "ABC":
            can0.set_ci(n, f"Motor{a} Target", 3000)
    can0.run(50)
    fpga = can0.boards[0].fpga
    assert fpga.read(Reg.OUTPUT_ENABLE) == 0b111 and fpga.read(Reg.PWM0) != 0
    # the PC stops sending Alive (its CI maps keep coming: they do not count)
    can0.stop_alive()
    runtimes = [can0.runtime(n) for n in (1, 2, 3)]
    while any(rt.state is not mca.RunState.LATCHED for rt in runtimes):
        can0.run(1)
    for rt in runtimes:  # within the watchdog time and one cycle
        assert rt.latched_at is not None
        assert mca.ALIVE_DEFAULT_MS * 1000 < rt.latched_at - rt.last_alive <= \
            mca.ALIVE_DEFAULT_MS * 1000 + 1000
    for b in can0.boards:
        assert b.fpga.read(Reg.OUTPUT_ENABLE) == 0
        assert [b.fpga.read(Reg.PWM0 + k) for k in range(3)] == [0, 0, 0]
        assert b.leds()["red"] == "on"
    errs = _errors(can0)
    assert {(n, e.code) for n, e in errs} >= {(n, ErrorCode.WATCHDOG) for n in (1, 2, 3)}
    # latched: CI refused (reported once), Alive alone does not release
    target = can0.runtime(1).model.ci[3]
    can0.set_ci(1, "MotorA Target", -3000)
    can0.run(200)
    assert can0.runtime(1).model.ci[3] == target
    assert can0.runtime(1).state is mca.RunState.LATCHED
    assert fpga.read(Reg.OUTPUT_ENABLE) == 0
    refusals = [e for n, e in _errors(can0) if n == 1 and e.code is ErrorCode.LATCHED]
    assert can0.mca.query(seq(1)).flags & mca.FLAG_LATCHED_BY_WATCHDOG
    # explicit restart
    assert can0.mca.start(seq(1)).state is mca.RunState.RUNNING
    can0.run(30)
    assert fpga.read(Reg.OUTPUT_ENABLE) == 0b111
    assert can0.boards[0].leds()["red"] == "off"
    assert can0.runtime(1).model.ci[3] == -3000
    assert len(refusals) <= 1


def test_a_vanished_pc_leaves_no_joint_driving(can0) -> None:
    can0.bring_up()
    can0.set_ci(1, "MotorA Target", 5000)
    can0.run(20)
    sim = can0.fleet.bus("CAN0")
    can0.close()  # the PC is gone mid-motion: nobody reads, nobody sends
    sim.run_until(sim.now + 200_000)
    for b in can0.boards:
        assert b.application is not None and b.application.runtime is not None
        assert b.application.runtime.state is mca.RunState.LATCHED
        assert b.fpga.read(Reg.OUTPUT_ENABLE) == 0


def test_mca_start_again_while_running_changes_nothing_and_a_stop_stops(can0) -> None:
    can0.bring_up()
    can0.set_ci(1, "MotorA Target", 500)
    can0.run(20)
    assert can0.mca.start(seq(1)).state is mca.RunState.RUNNING
    # a bootloader Start of the running program: answered, nothing changes; the wait for
    # its answers keeps the exchange's periodic frames (Alive) on time
    t0 = can0.now()
    (again,) = can0.boot.start(seq(1))
    assert can0.now() - t0 > 2 * mca.ALIVE_DEFAULT_MS / 1000  # a long wait
    assert again.ok and again.state is BoardState.RUNNING_FLASH
    assert can0.runtime(1).state is mca.RunState.RUNNING
    assert all(t.late == 0 for t in can0.exchange.tasks)
    assert can0.mca.start(seq(1), mca.StartOp.STOP).state is mca.RunState.STOPPED
    can0.run(2)
    assert can0.boards[0].fpga.read(Reg.OUTPUT_ENABLE) == 0


# ---------------------------------------------------------------------- loop, load, LEDs
def test_load_report_and_leds_follow_the_work(can0) -> None:
    can0.bring_up()
    can0.run(1100)
    status = can0.mca.app_status(seq(1))  # neck: three axes in POSITION
    assert (status.state, status.cycle_us, status.overruns) == (mca.RunState.RUNNING, 1000, 0)
    # 100 us base, 200 us per active axis, 4 us for the CI map frame it takes each cycle
    cost = armar3_model.BASE_US + 3 * armar3_model.AXIS_US + FRAME_COST_US
    assert status.load_permille == cost  # of 1000 us
    for a in "ABC":
        can0.ci[(1, armar3.SPEC.of(EdgeKind.CI).index(
            next(e for e in armar3.SPEC.of(EdgeKind.CI) if e.name == f"Motor{a} Command")))] \
            = armar3.Command.OFF
    edges = can0.configured[1].edges.ci
    can0.mca.write(seq(1), mca.Kind.CI, 0, [armar3.Command.OFF] * 3, edges)
    can0.run(2100)
    # 5.4.2: about 10 % with every controller off
    assert can0.mca.app_status(seq(1)).load_permille == armar3_model.BASE_US + FRAME_COST_US
    leds = can0.boards[0].leds()
    assert (leds["green"], leds["green_hz"], leds["yellow"], leds["red"]) == (
        "blink", "2.0", "off", "off")


def test_a_cycle_time_too_short_overruns_flashes_yellow_and_reports(can0) -> None:
    can0.bring_up()
    edges = can0.configured[1].edges.par
    # one axis alone fits 333 us (3 kHz); the neck's three do not
    can0.mca.write(seq(1), mca.Kind.PAR, 0, [333], edges)
    errs = _errors(can0, 0.01)
    overruns = [e for n, e in errs if n == 1 and e.code is ErrorCode.OVERRUN]
    work = armar3_model.BASE_US + 3 * armar3_model.AXIS_US  # and 4 us per frame taken
    assert overruns and overruns[0].function == 0xFF
    assert work - 333 < overruns[0].detail <= work + 3 * FRAME_COST_US - 333  # us late
    leds = can0.boards[0].leds()
    assert leds["yellow"] == "on" and float(leds["yellow_level"]) == 1.0
    status = can0.mca.app_status(seq(1))
    assert status.overruns > 0 and status.cycle_us == 333
    assert can0.mca.query(seq(1)).flags & mca.FLAG_OVERRUN
    can0.mca.write(seq(1), mca.Kind.CI, 1, [armar3.Command.OFF] * 2, can0.configured[1].edges.ci)
    count = can0.runtime(1).stats.overruns
    can0.mca.pump(can0.now() + OVERRUN_FLASH_US / 1e6 + 0.01)
    can0.mca.alive()
    assert can0.runtime(1).stats.overruns == count  # one axis: 300 us fits
    assert can0.boards[0].leds()["yellow"] == "off"
    assert can0.boards[0].leds()["green_hz"] == f"{1e6 / (2 * 250 * 333):.1f}"


def test_an_error_frame_on_the_bus_flashes_red(can0) -> None:
    can0.bring_up()
    sim = can0.fleet.bus("CAN0")
    sim.error_frame(sim.now + 100)
    can0.run(2)
    assert all(b.leds()["red"] == "on" for b in can0.boards)
    assert all(b.can_errors == 1 for b in can0.boards)
    can0.run(int(CAN_ERROR_FLASH_US / 1000) + 2)
    assert all(b.leds()["red"] == "off" for b in can0.boards)


def test_run_time_frames_before_a_program_runs_are_refused(can0) -> None:
    can0.boot.init_chain()
    can0.link.send_raw(encode_id(Function.MCA_START, seq(1)), bytes((1,)))
    assert [(e.code, e.function) for _, e in _errors(can0)] == [
        (ErrorCode.NOT_RUNNING, Function.MCA_START)]
    # a Parameter for a board in its bootloader
    can0.link.send_raw(encode_id(Function.MCA_PARAMETER, seq(2)), bytes((1, 0x2E, 0xE0)))
    assert [(n, e.code, e.function) for n, e in _errors(can0)] == [
        (2, ErrorCode.NOT_RUNNING, Function.MCA_PARAMETER)]
    can0.link.send_raw(encode_id(Function.MCA_ALIVE, ALL), b"")  # broadcast: silence
    assert _errors(can0) == []


# ---------------------------------------------------------------------- one fleet clock
def test_eleven_boards_on_four_buses_run_ten_seconds_in_step_every_cycle_on_time() -> None:
    fleet = programmed("armar3")
    hosts = bring_up_robot(fleet)
    runtimes = [h.runtime(n) for h in hosts for n in h.configured]
    assert len(runtimes) == 11

    joints = [(h, n, a) for h in hosts for n in h.configured for a in "ABC"]

    def move(k: int) -> None:  # every joint follows its own sine
        if k % 10 == 0:
            for j, (host, n, a) in enumerate(joints):
                host.set_ci(n, f"Motor{a} Target",
                            round(400 * math.sin(2 * math.pi * (0.3 + 0.05 * j) * k / 1000)))

    run_robot(hosts, 5)  # the maps of the first cycles arrive
    cycles = [rt.stats.cycles for rt in runtimes]
    counts = [dict(h.mca.image.counts) for h in hosts]
    t0 = fleet.clock.now
    try:
        run_robot(hosts, 10_000, each=move)
        elapsed_us = fleet.clock.now - t0
        assert elapsed_us == pytest.approx(10_000_000, abs=1)
        for rt, before in zip(runtimes, cycles, strict=True):
            assert rt.state is mca.RunState.RUNNING
            assert rt.stats.overruns == 0  # every cycle started on time
            assert rt.stats.cycles - before in (10_000, 10_001)
            assert rt.model.loop_us() == 1000.0
            assert rt.load() > 0.7  # every axis active
        # the buses ran in step: every 1 kHz map arrived once a millisecond on each bus
        for h, before in zip(hosts, counts, strict=True):
            for mp in h.plan.so_maps:
                if mp.period == 1:
                    # (a frame may end just after the window that ended just inside it
                    # 10 s earlier: arbitration delays differ by a frame time)
                    assert abs(h.mca.image.counts[mp.number] - before[mp.number] - 10_000) \
                        <= 1, (h.bus_name, mp)
        # and the joints followed
        for h in hosts:
            for n in h.configured:
                assert h.so(n, "Encoder 0") is not None
    finally:
        for h in hosts:
            h.close()


# ---------------------------------------------------------------------- the other program
def test_lauron4_legs_come_up_with_their_own_program_and_follow_a_set_point() -> None:
    h = RunHost(programmed("lauron4"), "CAN0")
    try:
        readies = h.start_programs()
        assert {(r.ci, r.so, r.par) for r in readies.values()} == {(11, 15, 30)}
        h.configure_all()
        h.start_exchange()
        assert len(h.plan.so_maps) == 27  # seven boards on one bus, folded to fit 31
        # a left leg (1), a right leg (4: alpha's motor mounted the other way round, which
        # its tree's Motor Direction undoes) and the camera head (7)
        for n in (1, 4, 7):
            h.set_ci(n, "Leg Mode", lauron4.LegMode.POSITION)  # not cyclic: written, acked
            assert h.runtime(n).model.ci[0] == lauron4.LegMode.POSITION
            h.set_ci(n, "Axis1 Position Setpoint", 1000)  # 10 degrees, in a CI map
        h.set_ci(1, "Axis2 Position Setpoint", 500)  # lift the foot (down is the ground)
        h.run(1500)
        for n in (1, 4, 7):
            assert abs(h.so(n, "Axis1 Position") - 1000) <= 10, n
        assert abs(h.so(1, "Axis2 Position") - 500) <= 10
        assert all(h.runtime(n).state is mca.RunState.RUNNING for n in range(1, 8))
        assert all(h.runtime(n).stats.overruns == 0 for n in range(1, 8))
    finally:
        h.close()
