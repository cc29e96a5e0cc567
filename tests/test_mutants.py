"""Mutant boards (``ucom_tools.virtual.board.mutants``): every defect of the catalogue, shown
through real frames by the real host clients (BootloaderClient, Programmer, McaClient).

Each defect has one test, run twice: on a board with the defect (the symptom the catalogue
names) and on the same fleet without it (what ``man/ucom-protocol.7`` specifies).  Then
the wiring: the topology key, the fleet-wide defect, and the catalogue itself.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator
from dataclasses import replace
from itertools import pairwise
from pathlib import Path

import pytest

from tests.helpers import image_words, plan_of, program
from ucom_tools.config import topology
from ucom_tools.config.topology import SOURCE_ROOT, parse
from ucom_tools.edgelists import armar3
from ucom_tools.edgelists.model import EdgeKind
from ucom_tools.errors import BoardError, InputError, TopologyError
from ucom_tools.protocol.bootloader import BootloaderClient
from ucom_tools.protocol.link import Link
from ucom_tools.protocol.mca import McaClient
from ucom_tools.protocol.timeouts import DEFAULT
from ucom_tools.virtual.board import mutants
from ucom_tools.virtual.board.ucom import VirtualBoard
from ucom_tools.virtual.canbus import VirtualUcomBus
from ucom_tools.virtual.fleet import Fleet
from ucom_tools.wire import mca
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import BoardState, ErrorCode, InitOp, ReadyReason, StatusOp
from ucom_tools.wire.digest import digest_of
from ucom_tools.wire.ids import ALL, Function, encode_id, seq

ROOT = Path(__file__).resolve().parent.parent
ARMAR3 = SOURCE_ROOT / "firmware_images" / "armar3.fl.S"
TESTED: set[str] = set()
"""The defects that have a test below (filled by :func:`both`)."""


def both(name: str) -> pytest.MarkDecorator:
    """Run a test on a conforming board and on a board with defect ``name``."""
    TESTED.add(name)
    return pytest.mark.parametrize("defect", [None, name], ids=["conforming", name])


def topology_text(n: int, defects: dict[int, str] | None = None) -> str:
    """A one-bus topology of ``n`` three-motor boards; ``defects[i]`` for board i."""
    text = 'name = "mutants"\n\n[[bus]]\nname = "CAN0"\nbitrate = 1000000\n'
    for i in range(n):
        text += f'\n[[bus.board]]\nplacement = "slot {i + 1}"\nboard = "3M"\n'
        if defects and i in defects:
            text += f'defect = "{defects[i]}"\n'
    return text


class Bench:
    """A host on bus CAN0 of a fleet: link, bootloader and run-time clients."""

    def __init__(self, fleet: Fleet) -> None:
        self.fleet = fleet
        self.can = VirtualUcomBus("CAN0", fleet=fleet)
        self.sim = self.can.sim
        self.link = Link(self.can, "CAN0")
        self.client = BootloaderClient(self.link)
        self.mca = McaClient(self.link)

    @property
    def boards(self) -> list[VirtualBoard]:
        return self.fleet.boards["CAN0"]

    def now(self) -> float:
        return self.link.clock()

    def wait(self, seconds: float) -> None:
        """Let ``seconds`` pass on the bus (frames are taken, nothing is answered)."""
        self.mca.pump(self.now() + seconds)

    def errors(self, quiet: float = 0.05) -> list[tuple[int, m.Error]]:
        """Errors received so far (and within ``quiet``): (board number, Error)."""
        return [(g.address.number, g.message) for g in self.link.drain(quiet)
                if isinstance(g.message, m.Error)]

    def started(self, n: int = 1) -> mca.McaReady:
        """Init, bootloader Start of board ``n``'s armar3 program and its MCA Ready."""
        self.client.init_chain()
        (result,) = self.client.start(seq(n))
        assert result.ok, result
        ready = self.mca.wait_ready(seq(n), DEFAULT.reply)
        assert ready is not None and ready.state is mca.RunState.STOPPED
        return ready

    def latency(self, request: m.BootMessage, answer: type) -> float:
        """Seconds from sending ``request`` to board 1 until its first ``answer`` frame
        (once the bus is quiet: nothing of an earlier answer is still queued)."""
        self.link.drain(0.01)
        t0 = self.now()
        self.link.send(request, seq(1))
        for got in self.link.until(t0 + 1.0):
            if isinstance(got.message, answer):
                return got.timestamp - self.fleet.epoch - t0
        raise AssertionError(f"no {answer.__name__} within 1 s")

    def mca_error(self) -> ErrorCode:
        """The code of the last Error the run-time client took."""
        return self.mca.errors[-1][1].code

    def close(self) -> None:
        self.mca.close()
        self.can.shutdown()


@pytest.fixture
def bench() -> Iterator[Callable[..., Bench]]:
    """``bench(n, defect=..., defects={i: name}, program=..., autostart=..., state_dir=...)``:
    a fleet of ``n`` boards (the fleet-wide ``defect`` and per-board ``defects``), with
    armar3 in flash when ``program``."""
    opened: list[Bench] = []

    def make(n: int = 1, *, defect: str | None = None, defects: dict[int, str] | None = None,
             program: bool = False, autostart: bool = False,
             state_dir: Path | None = None) -> Bench:
        topo = parse(topology_text(n, defects), "<mutants>")
        if program:
            topo = topo.with_flashed(ARMAR3, autostart=autostart)
        b = Bench(Fleet(topo, defect=defect, state_dir=state_dir))
        opened.append(b)
        return b

    yield make
    for b in opened:
        b.close()


RECORDS = {k: [mca.EdgeRecord(e.width, e.signed, e.exponent, e.minimum, e.maximum, e.name,
                              e.unit) for e in armar3.SPEC.of(EdgeKind(k))] for k in mca.Kind}
"""The armar3 program's edges as the host knows them from the protocol page."""


# ============================================================================ bootloader
@both(mutants.SEQ_FROM_ZERO)
def test_seq_from_zero(bench, defect) -> None:
    b = bench(2, defect=defect)
    init = b.client.init_chain()
    if defect:  # the first board answers as 0; the host never hears of number 1
        assert {a.seq_id for a in init.acks} == {0} and init.numbers == [0]
        assert [x.seq_id for x in b.boards] == [0, 0]
    else:
        assert [a.seq_id for a in init.acks] == [1, 2] and init.numbers == [1, 2]
    # the chain step by step: BEGIN, then NEXT 2 after the first Init Ack
    b.link.send(m.InitRequest(InitOp.BEGIN), ALL)
    first = [g for g in b.link.drain(0.01) if isinstance(g.message, m.InitAck)]
    b.link.send(m.InitRequest(InitOp.NEXT, 2), ALL)
    second = [g for g in b.link.drain(0.01) if isinstance(g.message, m.InitAck)]
    got = [(g.address.number, g.message.seq_id) for g in first + second]
    assert got == ([(0, 0), (1, 1)] if defect else [(1, 1), (2, 2)])


@both(mutants.INIT_TWICE)
def test_init_twice(bench, defect) -> None:
    b = bench(2, defects={0: defect} if defect else None)
    init = b.client.init_chain()
    assert init.numbers == [1, 2] and init.duplicates() == {}
    per_board = [sum(a.serial == x.identity.serial for a in init.acks) for x in b.boards]
    assert per_board == ([2, 1] if defect else [1, 1])
    assert b.sim.stats.by_function[Function.INIT_ACK] == (3 if defect else 2)


@both(mutants.INFO_SWAPPED)
def test_info_swapped(bench, defect) -> None:
    b = bench(defect=defect, program=True)
    b.client.init_chain()
    info = b.client.info(seq(1))
    serial, progid = b.boards[0].identity.serial, b.boards[0].nv.record.progid
    assert progid and progid != serial
    assert (info.serial, info.progid) == ((progid, serial) if defect else (serial, progid))
    assert info.name == "armar3.fl.S" and info.flash_valid  # the rest of the record is right


@both(mutants.WRONG_PROGID)
def test_wrong_progid(bench, defect) -> None:
    b = bench(defect=defect)
    plan = plan_of(image_words(600))
    result = program(b, plan)
    outcome = result.outcomes[seq(1)]
    reported = plan.progid + 1 if defect else plan.progid
    assert (outcome.verified, outcome.progid) == (not defect, reported)
    if defect:
        assert "board reports ProgID" in outcome.status
    assert b.client.info(seq(1)).progid == reported


@both(mutants.ACCEPT_BAD_PROGID)
def test_accept_bad_progid(bench, defect) -> None:
    b = bench(defect=defect)
    good = plan_of(image_words(600))
    bad = replace(good, progid=good.progid ^ 0x5A5A5A5A)  # META says another ProgID
    outcome = program(b, bad).outcomes[seq(1)]
    assert not outcome.verified and "PROGID" in outcome.status.upper()
    assert outcome.progid == good.progid  # what the board computed, in both cases
    assert b.client.info(seq(1)).flash_valid is bool(defect)
    b.client.reset()  # the conforming board is still in the transfer (Start: BUSY)
    assert b.client.info(seq(1)).flash_valid is bool(defect)
    (started,) = b.client.start(seq(1))
    if defect:
        assert started.started and started.state is BoardState.RUNNING_FLASH
    else:
        assert [e.code for e in started.errors] == [ErrorCode.NO_PROGRAM]


@both(mutants.LATE_ANSWER)
def test_late_answer(bench, defect) -> None:
    b = bench(2, defects={0: defect} if defect else None)
    b.client.init_chain()
    deadline = DEFAULT.reply
    late = mutants.LATE_FACTOR * deadline
    info = b.latency(m.InfoRequest(), m.InfoFrame)
    status = b.latency(m.SetStatus(StatusOp.PROG_ENABLE, 1), m.Ready)
    for seconds in (info, status):
        assert (late <= seconds < late + 0.001) if defect else seconds < deadline / 10
    assert b.boards[0].prog_enable  # done at once, only answered late
    # the host's client sees no answer within the deadline and asks again
    b.link.drain(0.2)
    before = b.sim.stats.by_function[Function.INFO_REQUEST]
    b.client.info(seq(1))
    assert b.sim.stats.by_function[Function.INFO_REQUEST] - before == (3 if defect else 1)
    # the other board keeps to its deadline
    b.link.drain(0.2)
    t0 = b.now()
    b.link.send(m.InfoRequest(), seq(2))
    got = next(g for g in b.link.until(t0 + 1.0)
               if isinstance(g.message, m.InfoFrame) and g.address == seq(2))
    assert got.timestamp - b.fleet.epoch - t0 < deadline / 10


@both(mutants.PROMISCUOUS)
def test_promiscuous(bench, defect) -> None:
    b = bench(2, defects={1: defect} if defect else None)
    b.client.init_chain()
    b.link.send(m.SetStatus(StatusOp.PROG_ENABLE, 1), seq(1))
    answers = sorted(g.address.number for g in b.link.drain(0.05)
                     if isinstance(g.message, m.Ready) and g.message.reason is ReadyReason.STATUS)
    assert answers == ([1, 2] if defect else [1])
    assert b.client.info(seq(2)).prog_enable is bool(defect)
    assert b.client.info(seq(1)).prog_enable


@both(mutants.IGNORE_INITOUT)
def test_ignore_initout(bench, defect) -> None:
    b = bench(2, defects={0: defect} if defect else None)
    b.client.init_chain()  # END: every board releases both pins
    assert b.client.status(seq(1)).pins & 0b0100 == 0
    (reply,) = b.client.set_status(seq(1), StatusOp.INIT_OUT, 1)
    assert reply.ok and reply.message.value16 == (StatusOp.INIT_OUT << 8 | 1)
    driven = bool(b.client.status(seq(1)).pins & 0b0100)  # bit 2: init output driven
    next_in = bool(b.client.status(seq(2)).pins & 0b0010)  # bit 1: init input measured set
    assert (driven, next_in) == ((False, False) if defect else (True, True))
    b.client.set_status(seq(1), StatusOp.INIT_IN, 1)  # INIT_IN still works
    assert b.client.status(seq(1)).pins & 0b0001


@both(mutants.AUTOSTART_LOST)
def test_autostart_lost(bench, defect, tmp_path: Path) -> None:
    b = bench(defect=defect, program=True, state_dir=tmp_path)
    b.client.init_chain()
    assert b.client.set_status(seq(1), StatusOp.AUTOSTART, 1)[0].ok
    (reply,) = b.client.reset()  # a warm reset keeps the flag: the program starts
    assert reply.message.state is (BoardState.BOOTLOADER if defect else
                                   BoardState.RUNNING_FLASH)
    assert b.client.set_status(seq(1), StatusOp.AUTOSTART, 1)[0].ok
    b.close()
    # the same state directory in a new fleet: the robot switched off and on again
    again = bench(defect=defect, state_dir=tmp_path)
    assert again.boards[0].state is (BoardState.BOOTLOADER if defect else
                                     BoardState.RUNNING_FLASH)
    again.client.init_chain()
    info = again.client.info(seq(1))
    assert (info.autostart, info.flash_valid) == (not defect, True)


@both(mutants.XRESET_KEEPS_AUTOSTART)
def test_xreset_keeps_autostart(bench, defect) -> None:
    b = bench(defect=defect, program=True)
    b.client.init_chain()
    assert b.client.set_status(seq(1), StatusOp.AUTOSTART, 1)[0].ok
    (reply,) = b.client.reset(clear_autostart=True)
    assert reply.message.state is (BoardState.RUNNING_FLASH if defect else
                                   BoardState.BOOTLOADER)
    assert b.client.info(seq(1)).autostart is bool(defect)
    (reply,) = b.client.reset()  # the next Reset: only the mutant starts it again
    assert reply.message.state is (BoardState.RUNNING_FLASH if defect else
                                   BoardState.BOOTLOADER)


@both(mutants.UNKNOWN_FUNCTION_SILENT)
def test_unknown_function_silent(bench, defect) -> None:
    b = bench(defect=defect)
    b.client.init_chain()
    for function in (28, 31):
        b.link.send_raw(encode_id(function, seq(1)), b"\x00")
        errors = [(e.code, e.function) for _, e in b.errors()]
        assert errors == ([] if defect else [(ErrorCode.UNKNOWN_FUNCTION, function)])
    b.link.send_raw(encode_id(Function.SET_STATUS, seq(1)), b"\x01\x01\x01")
    assert [e.code for _, e in b.errors()] == [ErrorCode.BAD_LENGTH]  # other errors stay


# ============================================================================ run time
@both(mutants.IGNORE_ALIVE)
def test_ignore_alive(bench, defect) -> None:
    b = bench(defect=defect, program=True)
    b.started()
    b.mca.admin(seq(1), mca.AdminData.so_map(1, 10, [0]))
    assert b.mca.start(seq(1)).state is mca.RunState.RUNNING
    b.wait(0.2)  # no MCA Alive: four watchdog times (50 ms)
    watchdog = [e for _, e in b.errors(0) if e.code is ErrorCode.WATCHDOG]
    state = b.mca.query(seq(1)).state
    assert (state, len(watchdog)) == ((mca.RunState.RUNNING, 0) if defect else
                                      (mca.RunState.LATCHED, 1))
    before = b.mca.image.counts.get(1, 0)
    b.wait(0.1)
    assert (b.mca.image.counts.get(1, 0) - before > 0) is bool(defect)  # SO maps keep coming


@both(mutants.SO_SLOW)
def test_so_slow(bench, defect) -> None:
    b = bench(defect=defect, program=True)
    b.started()
    stamps: dict[int, list[float]] = {1: [], 2: []}
    b.link.dispatcher.subscribe(
        lambda msg: msg.arbitration_id >> 6 == Function.MCA_SENSOR_OUTPUT, "test SO maps",
        on_frame=lambda msg: stamps[msg.arbitration_id & 0x1F].append(msg.timestamp))
    b.mca.admin(seq(1), mca.AdminData.so_map(1, 10, [0]))
    b.mca.admin(seq(1), mca.AdminData.so_map(2, 5, [1]))
    b.mca.start(seq(1))
    for _ in range(8):  # keep the watchdog fed: only the period is under test
        b.mca.alive()
        b.wait(0.025)
    gaps = {n: [round((t1 - t0) * 1000) for t0, t1 in pairwise(s)]
            for n, s in stamps.items()}
    assert len(gaps[1]) >= 15 and len(gaps[2]) >= 30
    if defect:  # 1.1 x the period, on the cycle grid
        assert set(gaps[1]) == {11}
        assert set(gaps[2]) == {5, 6} and abs(sum(gaps[2]) / len(gaps[2]) - 5.5) < 0.1
    else:
        assert (set(gaps[1]), set(gaps[2])) == ({10}, {5})


@both(mutants.DESCR_TRUNCATED)
def test_descr_truncated(bench, defect) -> None:
    b = bench(defect=defect, program=True)
    ready = b.started()
    edges = b.mca.describe(seq(1), (ready.ci, ready.so, ready.par))
    full = [e.name for e in armar3.SPEC.edges]
    got = [r.name for k in mca.Kind for r in edges.of(k)]
    assert got == ([n[:16] for n in full] if defect else full)
    assert edges.par[3].name == ("Set Joint Moving" if defect else
                                 "Set Joint Moving Direction(BitMask)")
    assert edges.par[3].maximum == 7 and edges.par[3].unit == ""  # the rest is right


@both(mutants.NO_RANGE_CHECK)
def test_no_range_check(bench, defect) -> None:
    b = bench(defect=defect, program=True)
    b.started()
    writes = [(mca.Kind.PAR, 1, 20000, 16000),  # Max PWM, 0..16000, default 16000
              (mca.Kind.CI, 0, 7, 0)]  # MotorA Command, 0..3, default 0
    for kind, index, raw, default in writes:
        records = RECORDS[kind]
        assert not records[index].minimum <= raw <= records[index].maximum
        if defect:
            b.mca.write(seq(1), kind, index, [raw], records)
            assert b.mca.dump(seq(1), kind, index, 1, records) == [raw]
        else:
            with pytest.raises(BoardError):
                b.mca.write(seq(1), kind, index, [raw], records)
            assert b.mca_error() is ErrorCode.OUT_OF_RANGE
            assert b.mca.dump(seq(1), kind, index, 1, records) == [default]
    b.mca.write(seq(1), mca.Kind.PAR, 1, [12000], RECORDS[mca.Kind.PAR])  # in range: taken
    # a CI map slot out of range: refused with Error OUT_OF_RANGE (0x8D), or taken
    b.mca.admin(seq(1), mca.AdminData.ci_map(1, [0, mca.NO_EDGE, mca.NO_EDGE, mca.NO_EDGE]))
    b.errors(0)  # the refusals above
    b.mca.send_map(1, (9).to_bytes(2, "big"))
    errors = [(e.code, e.function) for _, e in b.errors()]
    assert errors == ([] if defect else [(ErrorCode.OUT_OF_RANGE, 0x8D)])
    held = b.mca.dump(seq(1), mca.Kind.CI, 0, 1, RECORDS[mca.Kind.CI])
    assert held == ([9] if defect else [0])
    # LoopTime 0 (range 100..32000): the mutant takes it and keeps running, every cycle
    # overrunning in full; it never stops the fleet
    if defect:
        b.mca.write(seq(1), mca.Kind.PAR, 0, [0], RECORDS[mca.Kind.PAR])
    else:
        with pytest.raises(BoardError):
            b.mca.write(seq(1), mca.Kind.PAR, 0, [0], RECORDS[mca.Kind.PAR])
    b.mca.start(seq(1))
    b.mca.alive()
    b.wait(0.01)
    status = b.mca.app_status(seq(1))
    assert (status.cycle_us, status.overruns > 0) == ((0, True) if defect else (1000, False))
    assert b.boards[0].leds()["green"] == "blink"


@both(mutants.CI_WHILE_LATCHED)
def test_ci_while_latched(bench, defect) -> None:
    b = bench(defect=defect, program=True)
    b.started()
    b.mca.start(seq(1))
    b.wait(0.1)  # no MCA Alive: the watchdog latches
    assert b.mca.query(seq(1)).state is mca.RunState.LATCHED
    records = RECORDS[mca.Kind.CI]
    if defect:
        b.mca.write(seq(1), mca.Kind.CI, 3, [100], records)
    else:
        with pytest.raises(BoardError):
            b.mca.write(seq(1), mca.Kind.CI, 3, [100], records)
        assert b.mca_error() is ErrorCode.LATCHED
    assert b.mca.dump(seq(1), mca.Kind.CI, 3, 1, records) == ([100] if defect else [0])
    assert b.mca.query(seq(1)).state is mca.RunState.LATCHED  # the latch holds in both
    assert b.boards[0].fpga.outputs_enabled() == 0  # and the motors stay off


@both(mutants.DUMP_OFF_BY_ONE)
def test_dump_off_by_one(bench, defect) -> None:
    b = bench(defect=defect, program=True)
    b.started()
    par = RECORDS[mca.Kind.PAR]
    got = b.mca.dump(seq(1), mca.Kind.PAR, 0, 2, par)
    assert got == ([16000, 0] if defect else [1000, 16000])  # LoopTime, Max PWM
    # a 4-byte edge after a 2-byte one: the next value is wrapped to the edge's width
    b.mca.write(seq(1), mca.Kind.PAR, 5, [50_000_000], par)  # MotorA P
    got = b.mca.dump(seq(1), mca.Kind.PAR, 4, 2, par)
    wrapped = int.from_bytes((50_000_000 & 0xFFFF).to_bytes(2, "big"), "big")
    assert got == ([wrapped, 0] if defect else [273, 50_000_000])
    last = len(par) - 1
    assert b.mca.dump(seq(1), mca.Kind.PAR, last, 1, par) == ([0] if defect else [-32768])


@both(mutants.READY_COUNTS_WRONG)
def test_ready_counts_wrong(bench, defect) -> None:
    b = bench(defect=defect, program=True)
    announced = b.started()
    queried = b.mca.query(seq(1))
    so = len(RECORDS[mca.Kind.SO])
    for ready in (announced, queried):
        assert (ready.ci, ready.so, ready.par) == (13, so + 1 if defect else so, 38)
    if defect:  # the host asks for the edge that is not there
        with pytest.raises(BoardError):
            b.mca.describe(seq(1))
        assert b.mca_error() is ErrorCode.UNKNOWN_EDGE
    else:
        assert len(b.mca.describe(seq(1)).so) == so


@both(mutants.DIGEST_UNKNOWN)
def test_digest_unknown(bench, defect) -> None:
    b = bench(defect=defect, program=True)
    b.started()
    want = digest_of(RECORDS[mca.Kind.CI] + RECORDS[mca.Kind.SO] + RECORDS[mca.Kind.PAR])
    if defect:  # an older program: DLC 1 is a wrong length; the records are still there
        assert b.mca.digest(seq(1)) is None
        assert b.mca_error() is ErrorCode.BAD_LENGTH
        assert b.mca.errors[-1][1].function == Function.MCA_DUMPIO_DESCR_REQUEST
    else:
        assert b.mca.digest(seq(1)) == want == 0x0E506B11
    assert b.mca.describe(seq(1)).digest() == want


@both(mutants.DIGEST_WRONG)
def test_digest_wrong(bench, defect) -> None:
    b = bench(defect=defect, program=True)
    b.started()
    want = b.mca.describe(seq(1)).digest()
    assert b.mca.digest(seq(1)) == (want ^ 1 if defect else want)
    assert b.mca.errors == []


# ============================================================================ wiring
def test_the_topology_key_makes_a_board_a_mutant(tmp_path: Path) -> None:
    path = tmp_path / "robot.toml"
    path.write_text(topology_text(3, {1: mutants.PROMISCUOUS}))
    topo = topology.load(str(path))
    assert [x.defect for x in topo.bus("CAN0").boards] == [None, mutants.PROMISCUOUS, None]
    fleet = Fleet(topo)
    assert [x.defect for x in fleet.boards["CAN0"]] == [None, mutants.PROMISCUOUS, None]
    boards = fleet.snapshot()["buses"][0]["boards"]
    assert [x.get("defect") for x in boards] == [None, mutants.PROMISCUOUS, None]
    assert "defect" not in boards[0]  # a conforming board's entry is as it always was


def test_the_old_topology_key_fault_still_makes_a_mutant(tmp_path: Path) -> None:
    path = tmp_path / "robot.toml"
    path.write_text(topology_text(2, {1: mutants.PROMISCUOUS}).replace("defect =", "fault ="))
    assert [x.defect for x in topology.load(str(path)).bus("CAN0").boards] == [
        None, mutants.PROMISCUOUS]
    path.write_text(topology_text(2, {1: mutants.PROMISCUOUS}).replace(
        'defect = "promiscuous"', 'defect = "promiscuous"\nfault = "so-slow"'))
    with pytest.raises(TopologyError, match="old name of 'defect'") as info:
        topology.load(str(path))
    assert info.value.key == "bus[1].board[2].fault"
    path.write_text(topology_text(1).replace('board = "3M"\n', 'board = "3M"\nfaults = 1\n'))
    with pytest.raises(TopologyError) as unknown:
        topology.load(str(path))
    assert "defect" in unknown.value.reason and "fault," not in unknown.value.reason


@pytest.mark.parametrize("value, reason", [
    ('"seq-from-one"', "unknown defect 'seq-from-one'; known: seq-from-zero, init-twice"),
    ("3", "expected a string, got 3"),
])
def test_an_unknown_defect_in_a_topology_names_file_line_and_key(tmp_path: Path, value: str,
                                                                reason: str) -> None:
    path = tmp_path / "robot.toml"
    path.write_text(topology_text(2).replace('board = "3M"\n', 'board = "3M"\n'
                                             f"defect = {value}\n"))
    with pytest.raises(TopologyError) as info:
        topology.load(str(path))
    err = info.value
    assert (err.file, err.line, err.key) == (str(path), 10, "bus[1].board[1].defect")
    assert reason in err.reason
    assert str(err).startswith(f"{path}:10: bus[1].board[1].defect: ")
    if "unknown" in reason:
        assert all(name in err.reason for name in mutants.NAMES)


def test_a_fleet_wide_defect_goes_to_every_board_without_its_own(bench) -> None:
    b = bench(3, defect=mutants.UNKNOWN_FUNCTION_SILENT, defects={2: mutants.INIT_TWICE})
    assert b.fleet.defect == mutants.UNKNOWN_FUNCTION_SILENT
    assert [x.defect for x in b.boards] == [mutants.UNKNOWN_FUNCTION_SILENT] * 2 + [
        mutants.INIT_TWICE]
    init = b.client.init_chain()
    assert [a.seq_id for a in init.acks] == [1, 2, 3, 3]  # board 3: its own defect
    for n in (1, 2, 3):
        b.link.send_raw(encode_id(29, seq(n)), b"")
    assert [(n, e.code) for n, e in b.errors()] == [(3, ErrorCode.UNKNOWN_FUNCTION)]
    loaded = Fleet.load("armar3", defect=mutants.SO_SLOW)
    assert {x.defect for bus in loaded.boards.values() for x in bus} == {mutants.SO_SLOW}
    assert {x.defect for bus in Fleet.load("rosi").boards.values() for x in bus} == {None}


def test_an_unknown_fleet_defect_is_bad_input_listing_the_known_ones() -> None:
    topo = parse(topology_text(1), "<mutants>")
    for make in (lambda: Fleet(topo, defect="slow"),
                 lambda: Fleet.load("armar3", defect="slow"),
                 lambda: Fleet.load("no-such-robot", defect="slow")):
        with pytest.raises(InputError) as info:
            make()
        assert not isinstance(info.value, TopologyError)
        assert info.value.reason == "unknown defect 'slow'; known: " + ", ".join(mutants.NAMES)


def test_the_catalogue_lists_exactly_the_implemented_defects() -> None:
    assert mutants.NAMES == (
        "seq-from-zero", "init-twice", "info-swapped", "wrong-progid", "accept-bad-progid",
        "ignore-alive", "so-slow", "late-answer", "promiscuous", "ignore-initout",
        "descr-truncated", "no-range-check", "ci-while-latched", "autostart-lost",
        "xreset-keeps-autostart", "unknown-function-silent", "dump-off-by-one",
        "ready-counts-wrong", "digest-unknown", "digest-wrong")
    assert set(mutants.NAMES) == TESTED  # each has its test above
    assert mutants.defects() == mutants.CATALOGUE
    page = (ROOT / "man" / "ucom-protocol.7").read_text()
    headings = set(re.findall(r"^\.S[HS] (.+)$", page, re.M))
    text = mutants.listing()
    for f in mutants.defects():
        assert f.name and f.title and f.symptom and "\n" not in f.title
        section = re.split(r",| \(| and ", f.section)[0]
        assert section in headings, (f.name, f.section)
        assert set(f.as_dict()) == {"name", "title", "section", "symptom"}
        assert f"{f.name}: {f.title}" in text and f.symptom in text
    assert mutants.check(None) is None and mutants.check("so-slow") == "so-slow"


def test_the_manual_documents_the_topology_key_with_every_defect() -> None:
    page = (ROOT / "man" / "ucom.1").read_text()
    section = page[page.index(".SH TOPOLOGIES"):page.index(".SH PYTHON-CAN INTERFACE")]
    assert "defect" in section
    for name in mutants.NAMES:
        assert name.replace("-", "\\-") in section, name


def test_a_board_with_an_unknown_defect_is_refused() -> None:
    fleet = Fleet(parse(topology_text(1), "<mutants>"))
    with pytest.raises(InputError, match="unknown defect 'x'"):
        VirtualBoard(fleet.buses["CAN0"], fleet.boards["CAN0"][0].identity, defect="x")
