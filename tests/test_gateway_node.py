"""The gateway's CANopen node runtime (``ucom_tools.gateway.node``) against canopen's own
master side (``canopen.Network`` + ``RemoteNode`` on the same EDS) on python-can's
virtual bus: boot-up, heartbeats, NMT, SDO, SYNC-driven and event-driven PDOs, remapping
as masters do it, EMCY, the master watch, and a concise DCF replayed as ros2_canopen's
Lely master does at boot.  Every wait is on a condition with a deadline."""

from __future__ import annotations

import itertools
import struct
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import can
import canopen
import pytest
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from ucom_tools.errors import InputError
from ucom_tools.gateway.codes import NmtCommand, NmtState, StateChange
from ucom_tools.gateway.node import NodeCallbacks, NodeRuntime

EDS = str(Path(__file__).parent / "data" / "gateway_node.eds")
WAIT = 2.0  # deadline of every wait (s)
CYCLE = 0.001
# what a loaded machine may add to a deadline the runtime keeps (scheduling of this
# process's threads on 2 cores with other work beside it)
SLACK = 0.015


class Recorder:
    """Every frame on the bus with its time stamp, and waits on them.  It reads its own end
    of the virtual bus when asked (no reader thread): python-can's virtual bus puts a
    frame into every other end's queue as it is sent, so what a peer has answered is
    here when it is asked for, and a :meth:`mark` counts everything sent before it (a
    reader thread that the machine kept waiting gave marks that were behind: a barrier
    then took an earlier SDO answer for its own)."""

    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus
        self.frames: list[can.Message] = []
        self.lock = threading.Lock()

    def _take(self, timeout: float = 0.0) -> None:
        msg = self.bus.recv(timeout)
        while msg is not None:
            self.frames.append(msg)
            msg = self.bus.recv(0.0)

    def wait_for(self, pred: Callable[[list[can.Message]], Any], timeout: float = WAIT) -> Any:
        deadline = time.monotonic() + timeout
        with self.lock:
            self._take()
            while not (result := pred(self.frames)):
                left = deadline - time.monotonic()
                assert left > 0, "deadline passed"
                self._take(min(left, 0.05))
        return result

    def mark(self) -> int:
        with self.lock:
            self._take()
            return len(self.frames)

    def since(self, mark: int, cob_id: int | None = None) -> list[can.Message]:
        with self.lock:
            self._take()
            return [m for m in self.frames[mark:]
                    if cob_id is None or m.arbitration_id == cob_id]


class Events:
    """What the runtime called back, and waits on it."""

    def __init__(self) -> None:
        self.items: list[tuple[str, Any, float]] = []
        self.cond = threading.Condition()
        self.on_sync_hook: Callable[[int | None], None] | None = None
        self.on_write_hook: Callable[[int, int, int, Any], None] | None = None

    def add(self, kind: str, value: Any) -> None:
        with self.cond:
            self.items.append((kind, value, time.time()))
            self.cond.notify_all()

    def of(self, kind: str) -> list[Any]:
        with self.cond:
            return [v for k, v, _ in self.items if k == kind]

    def wait_for(self, kind: str, count: int = 1, timeout: float = WAIT) -> list[Any]:
        with self.cond:
            ok = self.cond.wait_for(lambda: len(self.of(kind)) >= count, timeout)
        assert ok, f"no {kind} ({count}) within {timeout} s: {self.items}"
        return self.of(kind)

    def time_of(self, kind: str) -> float:
        with self.cond:
            return next(t for k, _, t in self.items if k == kind)

    def callbacks(self) -> NodeCallbacks:
        def on_sync(counter: int | None) -> None:
            if self.on_sync_hook is not None:
                self.on_sync_hook(counter)
            self.add("sync", counter)
        def on_write(node: int, index: int, sub: int, value: Any) -> None:
            if self.on_write_hook is not None:
                self.on_write_hook(node, index, sub, value)
            self.add("write", (node, index, sub, value))
        return NodeCallbacks(
            on_write=on_write,
            on_state=lambda change: self.add("state", change),
            on_sync=on_sync,
            master_lost=lambda reason: self.add("lost", reason),
            master_back=lambda reason: self.add("back", reason))


class Rig:
    """The runtime with nodes ``ids`` on its own virtual channel, canopen's master on
    another end of it and a recorder on a third."""

    def __init__(self, ids: tuple[int, ...] = (5,)) -> None:
        channel = f"gw-node-{uuid.uuid4().hex}"
        self.buses = [can.Bus(interface="virtual", channel=channel) for _ in range(3)]
        self.recorder = Recorder(self.buses[0])
        self.net = canopen.Network(self.buses[1])
        self.net.NOTIFIER_CYCLE = 0.05  # (this network's: a prompt disconnect)
        self.net.connect()
        self.remotes = {i: self.net.add_node(i, canopen.import_od(EDS, i)) for i in ids}
        self.events = Events()
        self.runtime = NodeRuntime(self.buses[2], {i: canopen.import_od(EDS, i) for i in ids},
                                   self.events.callbacks(), cycle=CYCLE)

    def start(self) -> Rig:
        self.runtime.start()
        for i in self.remotes:  # each boot-up is on the bus when start() returns
            self.recorder.wait_for(lambda f, i=i: any(
                m.arbitration_id == 0x700 + i and bytes(m.data) == b"\0" for m in f))
        return self

    def close(self) -> None:
        self.runtime.close()
        self.net.disconnect()
        for bus in self.buses:
            bus.shutdown()

    def barrier(self, node: int = 5) -> None:
        """Everything the runtime sent before it answers one SDO is recorded."""
        mark = self.recorder.mark()
        self.remotes[node].sdo.upload(0x1000, 0)
        self.recorder.wait_for(lambda f: any(
            m.arbitration_id == 0x580 + node for m in f[mark:]))

    def sync(self, count: int = 1, node: int = 5) -> None:
        """``count`` SYNCs, each handled (its TPDOs recorded) before the next."""
        for _ in range(count):
            self.net.sync.transmit()
            self.barrier(node)

    def start_nodes(self, node: int = 0) -> None:
        self.net.nmt.send_command(NmtCommand.START) if node == 0 else \
            self.remotes[node].nmt.send_command(NmtCommand.START)
        self.events.wait_for("state", len(self.events.of("state")) + 1)


@pytest.fixture
def rig() -> Iterator[Rig]:
    r = Rig()
    try:
        yield r.start()
    finally:
        r.close()


@pytest.fixture
def rig2() -> Iterator[Rig]:
    r = Rig((5, 6))
    try:
        yield r.start()
    finally:
        r.close()


def intervals(frames: list[can.Message]) -> list[float]:
    return [b.timestamp - a.timestamp for a, b in itertools.pairwise(frames)]


# ---------------------------------------------------------------- boot-up, NMT, heartbeat
def test_every_node_boots_up_then_beats_pre_operational(rig2: Rig) -> None:
    boots = [m for m in rig2.recorder.since(0) if m.arbitration_id in (0x705, 0x706)]
    assert [(m.arbitration_id, bytes(m.data)) for m in boots[:2]] == \
        [(0x705, b"\0"), (0x706, b"\0")]
    changes = rig2.events.wait_for("state", 2)
    assert changes == [StateChange(5, NmtState.INITIALISING, NmtState.PRE_OPERATIONAL, None),
                       StateChange(6, NmtState.INITIALISING, NmtState.PRE_OPERATIONAL, None)]
    # the heartbeat from 0x1017 (100 ms by default), PRE-OPERATIONAL
    beats = rig2.recorder.wait_for(
        lambda f: (b := [m for m in f if m.arbitration_id == 0x705][1:]) and len(b) >= 2
        and b)
    assert {bytes(m.data) for m in beats} == {b"\x7f"}
    assert 0.08 <= intervals(beats)[0] <= 0.12 + SLACK


def test_heartbeat_follows_0x1017_and_the_state(rig: Rig) -> None:
    remote = rig.remotes[5]
    states: list[int] = []
    remote.nmt.add_heartbeat_callback(states.append)
    remote.sdo[0x1017].raw = 20
    mark = rig.recorder.mark()
    beats = rig.recorder.wait_for(
        lambda f: len(b := [m for m in f[mark:] if m.arbitration_id == 0x705]) >= 6 and b)
    gaps = intervals(beats[1:])
    assert sorted(gaps)[len(gaps) // 2] == pytest.approx(0.020, abs=0.005)
    rig.start_nodes(5)
    mark = rig.recorder.mark()
    rig.recorder.wait_for(lambda f: any(m.arbitration_id == 0x705 and m.data[0] == 5
                                        for m in f[mark:]))
    remote.nmt.send_command(NmtCommand.STOP)
    rig.recorder.wait_for(lambda f: any(m.arbitration_id == 0x705 and m.data[0] == 4
                                        for m in f[mark:]))
    assert rig.runtime.state(5) is NmtState.STOPPED
    remote.nmt.send_command(NmtCommand.ENTER_PRE_OPERATIONAL)
    rig.events.wait_for("state", 4)
    assert remote.sdo[0x1017].raw == 20  # SDO answered again
    remote.sdo[0x1017].raw = 0  # off
    mark = rig.recorder.mark()
    rig.barrier()
    got = threading.Event().wait(0.1)  # a deadline that must pass with no heartbeat
    assert not got and not rig.recorder.since(mark, 0x705)
    assert 0x7F in states and 0x05 in states and 0x04 in states


def test_nmt_broadcast_reaches_every_node(rig2: Rig) -> None:
    rig2.net.nmt.send_command(NmtCommand.START)
    rig2.events.wait_for("state", 4)
    assert rig2.runtime.state(5) is rig2.runtime.state(6) is NmtState.OPERATIONAL
    rig2.remotes[6].nmt.send_command(NmtCommand.STOP)
    rig2.events.wait_for("state", 5)
    assert rig2.runtime.state(5) is NmtState.OPERATIONAL
    assert rig2.runtime.state(6) is NmtState.STOPPED


def test_stop_sends_no_pdos_and_answers_no_sdo(rig: Rig) -> None:
    remote = rig.remotes[5]
    remote.sdo[0x1017].raw = 10
    rig.start_nodes(5)
    mark = rig.recorder.mark()
    rig.sync(1)
    assert len(rig.recorder.since(mark, 0x185)) == 1
    remote.nmt.send_command(NmtCommand.STOP)
    change = rig.events.wait_for("state", 3)[-1]
    assert change == StateChange(5, NmtState.OPERATIONAL, NmtState.STOPPED, NmtCommand.STOP)
    mark = rig.recorder.mark()
    rig.net.sync.transmit()
    remote.rpdo.read(from_od=True)
    remote.rpdo[1]["Controlword"].raw = 0x0F
    remote.rpdo[1].transmit()
    # the next heartbeats come after the SYNC and the RPDO were handled
    rig.recorder.wait_for(lambda f: len([m for m in f[mark:] if m.arbitration_id == 0x705])
                          >= 2)
    assert not rig.recorder.since(mark, 0x185) and not rig.recorder.since(mark, 0x285)
    assert not rig.events.of("write")
    remote.sdo.RESPONSE_TIMEOUT = 0.1
    with pytest.raises(SdoCommunicationError):
        remote.sdo.upload(0x1000, 0)


def test_reset_communication_boots_up_again_with_the_defaults(rig: Rig) -> None:
    remote = rig.remotes[5]
    remote.sdo[0x1017].raw = 30
    remote.sdo[0x60FF].raw = 1234  # an application object: kept
    remote.tpdo.read()
    remote.tpdo[1].trans_type = 2
    remote.tpdo.save()
    rig.start_nodes(5)
    mark = rig.recorder.mark()
    remote.nmt.send_command(NmtCommand.RESET_COMMUNICATION)
    boot = rig.recorder.wait_for(lambda f: [m for m in f[mark:] if m.arbitration_id == 0x705
                                            and bytes(m.data) == b"\0"])
    assert boot
    changes = rig.events.wait_for("state", 4)[-2:]
    assert changes == [
        StateChange(5, NmtState.OPERATIONAL, NmtState.INITIALISING,
                    NmtCommand.RESET_COMMUNICATION),
        StateChange(5, NmtState.INITIALISING, NmtState.PRE_OPERATIONAL,
                    NmtCommand.RESET_COMMUNICATION)]
    assert remote.sdo[0x1017].raw == 100
    assert remote.sdo[0x1800][2].raw == 1
    assert remote.sdo[0x60FF].raw == 1234
    beats = rig.recorder.wait_for(lambda f: (b := [m for m in f[mark:]
                                                   if m.arbitration_id == 0x705][1:]) and b)
    assert bytes(beats[0].data) == b"\x7f"
    assert beats[0].timestamp - boot[0].timestamp == pytest.approx(0.1, abs=0.02 + SLACK)
    remote.nmt.send_command(NmtCommand.RESET_NODE)
    rig.events.wait_for("state", 6)
    assert remote.sdo[0x60FF].raw == 0  # reset node: the application's too


# ---------------------------------------------------------------- SDO
def test_sdo_reads_and_writes_reach_the_application(rig: Rig) -> None:
    remote = rig.remotes[5]
    assert remote.sdo[0x1008].raw == "test joint"
    assert remote.sdo[0x1018][2].raw == 1
    assert remote.sdo[0x1014].raw == 0x85
    rig.runtime.set(5, 0x6064, 0, -4321)
    assert remote.sdo[0x6064].raw == -4321
    remote.sdo[0x60FF].raw = 777
    assert rig.events.of("write") == [(5, 0x60FF, 0, 777)]
    assert rig.runtime.get(5, 0x60FF) == 777
    with pytest.raises(SdoAbortedError) as high:
        remote.sdo[0x607A].raw = 100001
    with pytest.raises(SdoAbortedError) as low:
        remote.sdo[0x607A].raw = -100001
    assert (high.value.code, low.value.code) == (0x06090031, 0x06090032)
    assert rig.runtime.get(5, 0x607A) == 0 and len(rig.events.of("write")) == 1
    with pytest.raises(SdoAbortedError) as ro:
        remote.sdo.download(0x6041, 0, b"\1\0")
    assert ro.value.code == 0x06010002


def test_the_application_may_refuse_a_write(rig: Rig) -> None:
    def refuse(node: int, index: int, sub: int, value: Any) -> None:
        raise SdoAbortedError(0x08000022)
    rig.events.on_write_hook = refuse
    with pytest.raises(SdoAbortedError) as err:
        rig.remotes[5].sdo[0x60FF].raw = 5
    assert err.value.code == 0x08000022
    assert rig.runtime.get(5, 0x60FF) == 0


# ---------------------------------------------------------------- SYNC and TPDOs
def test_sync_sends_type_1_every_sync_and_type_2_every_second(rig: Rig) -> None:
    remote = rig.remotes[5]
    remote.tpdo.read()
    remote.tpdo[2].trans_type = 2
    remote.tpdo.save()
    count = [0]

    def refresh(counter: int | None) -> None:  # on_sync: values of this SYNC
        count[0] += 1
        rig.runtime.set(5, 0x6041, 0, 0x1000 + count[0])
        rig.runtime.set(5, 0x6064, 0, -count[0])
    rig.events.on_sync_hook = refresh
    rig.start_nodes(5)
    mark = rig.recorder.mark()
    rig.sync(6)
    t1 = rig.recorder.since(mark, 0x185)
    t2 = rig.recorder.since(mark, 0x285)
    assert [struct.unpack("<Hb", m.data) for m in t1] == [(0x1000 + k, 0) for k in range(1, 7)]
    assert [struct.unpack("<ii", m.data) for m in t2] == [(-2, 0), (-4, 0), (-6, 0)]


def test_sync_counter_and_start_value(rig: Rig) -> None:
    remote = rig.remotes[5]
    remote.tpdo.read()
    remote.tpdo[1].sync_start_value = 3
    remote.tpdo.save()
    rig.start_nodes(5)
    mark = rig.recorder.mark()
    for counter in (1, 2, 3, 4):
        rig.net.sync.transmit(counter)
        rig.barrier()
    assert rig.events.of("sync") == [1, 2, 3, 4]
    assert len(rig.recorder.since(mark, 0x185)) == 2  # from the SYNC counting 3 on


def test_acyclic_synchronous_tpdo_goes_on_sync_when_changed(rig: Rig) -> None:
    remote = rig.remotes[5]
    remote.tpdo.read()
    remote.tpdo[2].trans_type = 0
    remote.tpdo.save()
    rig.start_nodes(5)
    mark = rig.recorder.mark()
    rig.sync(2)
    rig.runtime.set(5, 0x606C, 0, 99)
    rig.sync(2)
    frames = rig.recorder.since(mark, 0x285)
    assert [struct.unpack("<ii", m.data) for m in frames] == [(0, 0), (0, 99)]


def test_event_driven_tpdo_keeps_its_inhibit_time(rig: Rig) -> None:
    remote = rig.remotes[5]
    remote.tpdo.read()
    tpdo = remote.tpdo[3]
    tpdo.clear()
    tpdo.add_variable(0x6064)
    tpdo.trans_type = 255
    tpdo.inhibit_time = 300  # 30 ms
    tpdo.event_timer = 0
    tpdo.cob_id = 0x385
    tpdo.enabled = True
    tpdo.save()
    rig.start_nodes(5)
    first = rig.recorder.wait_for(lambda f: [m for m in f if m.arbitration_id == 0x385])[0]
    assert struct.unpack("<i", first.data) == (0,)  # sent on entering OPERATIONAL
    for value in (1, 2, 3):
        rig.runtime.set(5, 0x6064, 0, value)
    frames = rig.recorder.wait_for(lambda f: len(x := [m for m in f if m.arbitration_id
                                                       == 0x385]) >= 2 and x)
    assert struct.unpack("<i", frames[1].data) == (3,)  # the latest, once
    assert frames[1].timestamp - frames[0].timestamp >= 0.030 - 0.0005
    rig.runtime.set(5, 0x6064, 0, 3)  # unchanged: nothing
    rig.runtime.set(5, 0x6064, 0, 4)
    frames = rig.recorder.wait_for(lambda f: len(x := [m for m in f if m.arbitration_id
                                                       == 0x385]) >= 3 and x)
    assert struct.unpack("<i", frames[2].data) == (4,)
    assert frames[2].timestamp - frames[1].timestamp >= 0.030 - 0.0005


def test_event_timer_repeats_an_unchanged_tpdo(rig: Rig) -> None:
    remote = rig.remotes[5]
    remote.tpdo.read()
    remote.tpdo[1].trans_type = 254
    remote.tpdo[1].event_timer = 25
    remote.tpdo.save()
    rig.start_nodes(5)
    frames = rig.recorder.wait_for(lambda f: len(x := [m for m in f if m.arbitration_id
                                                       == 0x185]) >= 5 and x)
    gaps = intervals(frames[1:])
    assert min(gaps) >= 0.025 - 0.0005
    assert sorted(gaps)[len(gaps) // 2] <= 0.025 + SLACK


# ---------------------------------------------------------------- RPDOs
def test_synchronous_rpdo_is_applied_at_the_next_sync(rig: Rig) -> None:
    remote = rig.remotes[5]
    remote.rpdo.read()
    seen_in_sync: list[Any] = []
    rig.events.on_sync_hook = lambda c: seen_in_sync.append(rig.runtime.get(5, 0x607A))
    rig.start_nodes(5)
    remote.rpdo[2]["Target position"].raw = 4242
    remote.rpdo[2].transmit()
    rig.barrier()
    assert rig.runtime.get(5, 0x607A) == 0 and not rig.events.of("write")
    rig.sync(1)
    assert rig.events.of("write") == [(5, 0x607A, 0, 4242)]
    assert seen_in_sync == [4242]
    assert remote.sdo[0x607A].raw == 4242  # SDO reads it


def test_event_driven_rpdo_is_applied_at_once_in_map_order(rig: Rig) -> None:
    remote = rig.remotes[5]
    remote.rpdo.read()
    rig.start_nodes(5)
    remote.rpdo[1]["Controlword"].raw = 0x0F
    remote.rpdo[1]["Modes of operation"].raw = -3
    remote.rpdo[1].transmit()
    writes = rig.events.wait_for("write", 2)
    assert writes == [(5, 0x6040, 0, 0x0F), (5, 0x6060, 0, -3)]
    assert remote.sdo[0x6060].raw == -3


def test_rpdo_out_of_limits_or_short_is_not_applied(rig: Rig) -> None:
    remote = rig.remotes[5]
    rig.start_nodes(5)
    remote.network.send_message(0x305, struct.pack("<i", 200000))
    remote.network.send_message(0x205, b"\x0f")  # 1 of 3 bytes
    rig.sync(1)
    assert not rig.events.of("write")
    assert rig.runtime.stats().rpdo_errors == 2


# ---------------------------------------------------------------- remapping
def test_master_remaps_a_tpdo_and_an_rpdo(rig: Rig) -> None:
    remote = rig.remotes[5]
    remote.tpdo.read()
    remote.rpdo.read()
    tpdo, rpdo = remote.tpdo[3], remote.rpdo[3]
    tpdo.clear()
    tpdo.add_variable(0x6064)
    tpdo.add_variable(0x6041)
    tpdo.trans_type = 1
    tpdo.cob_id = 0x385
    tpdo.enabled = True
    rpdo.clear()
    rpdo.add_variable(0x60FF)
    rpdo.add_variable(0x6040)
    rpdo.trans_type = 255
    rpdo.cob_id = 0x405
    rpdo.enabled = True
    remote.pdo.save()
    assert remote.sdo[0x1A02][0].raw == 2
    assert remote.sdo[0x1A02][1].raw == 0x60640020
    rig.runtime.set(5, 0x6064, 0, 31337)
    rig.runtime.set(5, 0x6041, 0, 0x0237)
    rig.start_nodes(5)
    rig.net.sync.start(0.01)
    try:
        assert tpdo.wait_for_reception(WAIT) is not None
    finally:
        rig.net.sync.stop()
    assert tpdo["Position actual value"].raw == 31337
    assert tpdo["Statusword"].raw == 0x0237
    rpdo["Target velocity"].raw = -500
    rpdo["Controlword"].raw = 6
    rpdo.transmit()
    assert rig.events.wait_for("write", 2) == [(5, 0x60FF, 0, -500), (5, 0x6040, 0, 6)]
    # read back as a master reads a configuration
    fresh = canopen.RemoteNode(5, canopen.import_od(EDS, 5))
    rig.net.add_node(fresh)
    fresh.tpdo.read()
    assert [v.index for v in fresh.tpdo[3].map] == [0x6064, 0x6041]
    assert fresh.tpdo[3].enabled and fresh.tpdo[3].cob_id == 0x385


@pytest.mark.parametrize(("index", "sub", "value", "code"), [
    (0x1A02, 1, 0x20000008, 0x06040041),  # a string: not mappable
    (0x1A02, 1, 0x20010010, 0x06040041),  # PDOMapping=0
    (0x1A02, 1, 0x60410008, 0x06040041),  # length is not the object's
    (0x1A02, 1, 0x50000020, 0x06020000),  # no such object
    (0x1602, 1, 0x60410010, 0x06040041),  # read-only into an RPDO
    (0x1802, 2, 252, 0x06090030),  # RTR-only transmission type
    (0x1802, 2, 245, 0x06090030),  # reserved
    (0x1802, 1, 0x00000705, 0x06090030),  # a COB-ID CiA 301 reserves (heartbeats)
])
def test_an_invalid_mapping_is_refused_and_not_stored(rig: Rig, index: int, sub: int,
                                                      value: int, code: int) -> None:
    sdo = rig.remotes[5].sdo
    before = sdo.upload(index, sub)
    with pytest.raises(SdoAbortedError) as err:
        sdo[index][sub].raw = value
    assert err.value.code == code
    assert sdo.upload(index, sub) == before


def test_remapping_needs_the_pdo_invalid_and_its_count_zero(rig: Rig) -> None:
    sdo = rig.remotes[5].sdo
    with pytest.raises(SdoAbortedError) as err:  # TPDO1 is valid
        sdo[0x1A00][1].raw = 0x60640020
    assert err.value.code == 0x06090030
    with pytest.raises(SdoAbortedError) as err:  # a valid PDO keeps its COB-ID
        sdo[0x1800][1].raw = 0x195
    assert err.value.code == 0x06090030
    with pytest.raises(SdoAbortedError) as err:  # inhibit time: only while invalid
        sdo[0x1800][3].raw = 10
    assert err.value.code == 0x06090030
    sdo[0x1800][1].raw = 0x80000185
    with pytest.raises(SdoAbortedError) as err:  # count still 2
        sdo[0x1A00][1].raw = 0x60640020
    assert err.value.code == 0x06090030
    sdo[0x1A00][0].raw = 0
    for s in (1, 2, 3):
        sdo[0x1A00][s].raw = 0x60640020
    with pytest.raises(SdoAbortedError) as err:  # 96 bits
        sdo[0x1A00][0].raw = 3
    assert err.value.code == 0x06040042
    assert sdo[0x1A00][0].raw == 0
    with pytest.raises(SdoAbortedError) as err:
        sdo[0x1A00][0].raw = 9
    assert err.value.code == 0x06040042
    sdo[0x1A00][0].raw = 2
    sdo[0x1800][1].raw = 0x185
    assert rig.runtime.node(5).tpdos[0].entries[0].index == 0x6064


# ---------------------------------------------------------------- EMCY
def test_emcy_keeps_0x1001_0x1003_and_its_inhibit_time(rig: Rig) -> None:
    remote = rig.remotes[5]
    remote.sdo[0x1015].raw = 200  # 20 ms
    got = threading.Condition()

    def received(_: Any) -> None:
        with got:
            got.notify_all()
    remote.emcy.add_callback(received)
    rig.runtime.emcy(5, 0x8611, 0x20, b"\x01")
    rig.runtime.emcy(5, 0x5000, 0x00)
    frames = rig.recorder.wait_for(lambda f: len(x := [m for m in f if m.arbitration_id
                                                       == 0x85]) >= 2 and x)
    assert [struct.unpack("<HB5s", m.data)[:2] for m in frames] == [(0x8611, 0x21),
                                                                     (0x5000, 0x01)]
    assert frames[1].timestamp - frames[0].timestamp >= 0.020 - 0.0005
    assert remote.sdo[0x1001].raw == 0x01
    field = remote.sdo[0x1003]
    assert field[0].raw == 2 and field[1].raw == 0x5000 and field[2].raw == 0x8611
    with got:
        got.wait_for(lambda: len(remote.emcy.log) >= 2, WAIT)
    assert [e.code for e in remote.emcy.active] == [0x8611, 0x5000]
    rig.runtime.emcy(5, 0)  # error reset
    with got:
        assert got.wait_for(lambda: len(remote.emcy.log) >= 3, WAIT)
    assert remote.emcy.active == [] and remote.sdo[0x1001].raw == 0
    assert field[0].raw == 2  # the history stays until a master clears it
    with pytest.raises(SdoAbortedError) as err:
        field[0].raw = 1
    assert err.value.code == 0x06090030
    field[0].raw = 0
    assert field[0].raw == 0 and field[1].raw == 0


def test_emcy_disabled_by_0x1014_is_recorded_not_sent(rig: Rig) -> None:
    remote = rig.remotes[5]
    remote.sdo[0x1014].raw = 0x80000085
    mark = rig.recorder.mark()
    rig.runtime.emcy(5, 0x1000, 0x01)
    rig.barrier()
    rig.recorder.wait_for(lambda f: any(m.arbitration_id == 0x705 for m in f[mark:]))
    assert not rig.recorder.since(mark, 0x85)
    assert remote.sdo[0x1003][1].raw == 0x1000


# ---------------------------------------------------------------- the master watch
def test_master_heartbeat_lost_within_its_time_plus_a_cycle(rig: Rig) -> None:
    remote = rig.remotes[5]
    remote.sdo[0x1016][1].raw = 0x7F << 16 | 60  # master 127, 60 ms
    beat = rig.net.send_periodic(0x77F, [0x05], 0.02)
    mark = rig.recorder.mark()
    try:
        rig.recorder.wait_for(lambda f: len([m for m in f[mark:]
                                             if m.arbitration_id == 0x77F]) >= 5)
    finally:
        beat.stop()
    reason = rig.events.wait_for("lost")[0]
    last = rig.recorder.since(mark, 0x77F)[-1].timestamp
    late = rig.events.time_of("lost") - last
    assert 0.060 <= late <= 0.060 + CYCLE + SLACK, late
    assert "node 127" in reason
    assert rig.runtime.master_lost
    assert not rig.events.of("back")
    rig.net.send_message(0x77F, [0x05])
    assert "node 127" in rig.events.wait_for("back")[0]
    assert len(rig.events.of("lost")) == 1


@pytest.mark.parametrize(("period", "timeout"), [
    pytest.param(0.02, 0.060, id="3 periods"),
    pytest.param(0.01, 0.050, id="at least 50 ms")])
def test_sync_lost_within_three_periods_or_the_floor(rig: Rig, period: float,
                                                     timeout: float) -> None:
    got = threading.Event().wait(0.15)  # no SYNC yet: no timeout
    assert not got and not rig.events.of("lost")
    mark = rig.recorder.mark()
    rig.net.sync.start(period)
    try:
        rig.recorder.wait_for(lambda f: len([m for m in f[mark:]
                                             if m.arbitration_id == 0x80]) >= 12)
    finally:
        rig.net.sync.stop()
    rig.events.wait_for("lost")
    last = rig.recorder.since(mark, 0x80)[-1].timestamp
    late = rig.events.time_of("lost") - last
    assert timeout - 0.005 <= late <= timeout + 0.003 + CYCLE + SLACK, late
    rig.net.sync.transmit()
    assert rig.events.wait_for("back")[0] == "SYNC again"


def test_sync_timeout_from_0x1006(rig: Rig) -> None:
    rig.remotes[5].sdo[0x1006].raw = 15000  # 15 ms: timeout 45 ms
    rig.net.sync.transmit()
    rig.net.sync.transmit()
    rig.events.wait_for("lost")
    assert "45.0 ms" in rig.events.of("lost")[0]


# ---------------------------------------------------------------- a DCF as Lely replays it
def concise_dcf(entries: list[tuple[int, int, bytes]]) -> bytes:
    """A concise DCF (CiA 302-3: count, then index, sub-index, size, data each)."""
    out = [struct.pack("<I", len(entries))]
    for index, sub, data in entries:
        out.append(struct.pack("<HBI", index, sub, len(data)) + data)
    return b"".join(out)


def replay(sdo: Any, dcf: bytes) -> int:
    (count,), at = struct.unpack_from("<I", dcf), 4
    for _ in range(count):
        index, sub, size = struct.unpack_from("<HBI", dcf, at)
        at += 7
        sdo.download(index, sub, dcf[at:at + size])
        at += size
    return count


def u8(v: int) -> bytes:
    return struct.pack("<B", v)


def u16(v: int) -> bytes:
    return struct.pack("<H", v)


def u32(v: int) -> bytes:
    return struct.pack("<I", v)


def test_a_concise_dcf_replayed_at_boot_then_start(rig: Rig) -> None:
    # as dcfgen writes a slave's joint_N.bin: heartbeat, each PDO disabled, its map
    # emptied, written, counted, its communication set, enabled again
    entries = [(0x1017, 0, u16(50))]
    for comm, mapping, cob, trans, objects in (
            (0x1800, 0x1A00, 0x185, 1, [0x60410010, 0x60610008]),
            (0x1801, 0x1A01, 0x285, 1, [0x60640020, 0x606C0020]),
            (0x1400, 0x1600, 0x205, 255, [0x60400010, 0x60600008]),
            (0x1401, 0x1601, 0x305, 255, [0x607A0020, 0x60FF0020])):
        entries += [(comm, 1, u32(cob | 1 << 31)), (comm, 2, u8(trans)), (mapping, 0, u8(0))]
        entries += [(mapping, s + 1, u32(o)) for s, o in enumerate(objects)]
        entries += [(mapping, 0, u8(len(objects))), (comm, 1, u32(cob))]
    dcf = concise_dcf(entries)
    remote = rig.remotes[5]
    assert replay(remote.sdo, dcf) == len(entries) == 29
    remote.tpdo.read()
    remote.rpdo.read()
    rig.runtime.set(5, 0x606C, 0, -77)
    rig.start_nodes(5)
    rig.net.sync.start(0.01)
    try:
        assert remote.tpdo[2].wait_for_reception(WAIT) is not None
    finally:
        rig.net.sync.stop()
    assert remote.tpdo[2]["Velocity actual value"].raw == -77
    remote.rpdo[2]["Target position"].raw = 1000
    remote.rpdo[2]["Target velocity"].raw = 20
    remote.rpdo[2].transmit()  # event-driven now: applied at once
    assert rig.events.wait_for("write", 2) == [(5, 0x607A, 0, 1000), (5, 0x60FF, 0, 20)]
    mark = rig.recorder.mark()
    beats = rig.recorder.wait_for(lambda f: len(b := [m for m in f[mark:]
                                                      if m.arbitration_id == 0x705]) >= 3
                                  and b)
    assert intervals(beats)[-1] == pytest.approx(0.05, abs=0.005 + SLACK)


# ---------------------------------------------------------------- the application's errors
def test_bad_input_is_refused_clearly(rig: Rig) -> None:
    with pytest.raises(InputError, match="no object 0x5000:00"):
        rig.runtime.set(5, 0x5000, 0, 1)
    with pytest.raises(InputError, match="does not fit"):
        rig.runtime.set(5, 0x6041, 0, 70000)
    with pytest.raises(InputError, match="at most 5"):
        rig.runtime.emcy(5, 0x1000, 1, b"123456")
    with pytest.raises(InputError, match="no CANopen node 9"):
        rig.runtime.get(9, 0x1000)
    with pytest.raises(InputError, match="node ID 128"):
        NodeRuntime(rig.buses[2], {128: canopen.import_od(EDS, 127)})


# ---------------------------------------------------------------- canopen's BaseNode402
def test_base_node_402_drives_a_node_to_operation_enabled(rig: Rig) -> None:
    """canopen's own CiA 402 client works through the runtime: its controlword by RPDO,
    its statusword by TPDO on SYNC (an application with the smallest state machine)."""
    statusword = {0x06: 0x0021, 0x07: 0x0023, 0x0F: 0x0027}

    def on_write(node: int, index: int, sub: int, value: Any) -> None:
        if index == 0x6040:
            rig.runtime.set(5, 0x6041, 0, statusword.get(value & 0x0F, 0x0040)
                            if value & 0x02 else 0x0040)
    rig.events.on_write_hook = on_write
    rig.runtime.set(5, 0x6041, 0, 0x0040)
    drive = canopen.BaseNode402(5, canopen.import_od(EDS, 5))
    rig.net.add_node(drive)  # (replaces the plain RemoteNode)
    drive.nmt.wait_for_heartbeat(WAIT)
    drive.setup_402_state_machine()
    drive.nmt.state = "OPERATIONAL"
    rig.events.wait_for("state", 2)
    rig.net.sync.start(0.01)
    try:
        drive.state = "OPERATION ENABLED"
        assert drive.state == "OPERATION ENABLED"
    finally:
        rig.net.sync.stop()
    assert [v for n, i, s, v in rig.events.of("write") if i == 0x6040][-3:] == \
        [0x06, 0x07, 0x0F]
