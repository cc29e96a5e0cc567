"""The gateway joined to the run (``ucom_tools/gateway/bridge.py``), in one process: the
in-process ARMAR-III under ``RemotePart`` (virtual time, the loop on a thread of the
test), its hand-over (``LocalRun``), the gateway's nodes on a python-can virtual bus and
canopen's own ``RemoteNode`` as the master on that bus.  What it checks: the nodes boot
and every joint is switched off until its master enables it; a PAR written by SDO reaches
the board without the loop waiting for it (``ops/remote/par_write.py``); a write out of range is
aborted and nothing reaches the board; a lost board's joints go to FAULT with EMCY 0xFF01
and a write to it is aborted 0x08000022.  The masters of other processes and the command
itself: ``tests/test_gateway_canopen.py``."""

from __future__ import annotations

import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import can
import canopen
import pytest
from canopen.sdo import SdoAbortedError

from tests.runtime_rig import programmed, robot_of
from ucom_tools.config.attrtree.robot import bind
from ucom_tools.config.scenario import FaultKind, InjectedFault
from ucom_tools.edgelists.armar3 import Command
from ucom_tools.errors import InputError
from ucom_tools.gateway import dictionary, joints
from ucom_tools.gateway.bridge import CanopenBus, Gateway, SharedCommand
from ucom_tools.gateway.cia402_objects import State402
from ucom_tools.gateway.joints import Role
from ucom_tools.ops.remote import RemotePart
from ucom_tools.ops.remote.feed import LocalRun
from ucom_tools.virtual.fleet import Fleet
from ucom_tools.wire.ids import seq

DEADLINE_S = 10.0
RIGHT_EYE = 7
LEFT_EYE = 8
EYES = ("CAN0", 3)


@dataclass
class Rig:
    fleet: Fleet
    part: RemotePart
    run: LocalRun
    gateway: Gateway
    net: canopen.Network
    emcys: list[tuple[int, int]]
    """(node ID, EMCY code) as the master heard them."""
    lock: threading.Lock

    def node(self, node_id: int) -> canopen.RemoteNode:
        joint = next(j for j in self.gateway.drives.values() if j.node_id == node_id).joint
        node = canopen.RemoteNode(node_id, dictionary.to_canopen(dictionary.build(joint)))
        self.net.add_node(node)
        return node

    def emcys_of(self, emcy: tuple[int, int]) -> int:
        """How many EMCYs (node, code) the listener has seen so far."""
        with self.lock:
            return self.emcys.count(emcy)

    def until(self, what: Callable[[], bool], why: str) -> None:
        """Wait (the loop runs on its own thread) until ``what`` holds."""
        end = time.monotonic() + DEADLINE_S
        while not what():
            assert time.monotonic() < end, why
            threading.Event().wait(0.005)  # a poll interval, not a synchronisation

    def board_par(self, name: str) -> int:
        """What the board itself has of a PAR (MCA Dump, through the loop's own client
        between its cycles: the part is paused by :meth:`paused`)."""
        ref = self.part.names.resolve(name)
        x = self.part.exchanges[ref.bus]
        return x.mca.dump(seq(ref.board), ref.kind, ref.index, 1,
                          x.configured[ref.board].edges.par)[0]


@pytest.fixture
def rig() -> Iterator[Rig]:
    fleet = programmed("armar3")
    robot = robot_of(fleet)
    assert robot.topology is not None
    part = RemotePart(robot, bind(robot.topology), on_fault="hold")
    run = LocalRun(part, 500.0)
    part.start()
    image = run.image
    assert image is not None
    channel = f"gateway-bridge-{uuid.uuid4().hex}"
    bus, master, listener = (can.Bus(interface="virtual", channel=channel) for _ in range(3))
    net = canopen.Network(master)
    net.connect()
    emcys: list[tuple[int, int]] = []
    lock = threading.Lock()

    def on_emcy(msg: can.Message) -> None:
        if 0x081 <= msg.arbitration_id <= 0x0FF:
            with lock:
                emcys.append((msg.arbitration_id - 0x80, int.from_bytes(msg.data[:2],
                                                                        "little")))
    notifier = can.Notifier(listener, [on_emcy], 0.05)
    gateway = Gateway(joints.find(robot.topology).joints, image, run,
                      [CanopenBus(bus, "virtual")]).start()
    stop = threading.Event()
    paused = threading.Lock()

    def loop() -> None:
        while not stop.is_set():
            with paused:
                part.cycle()
            stop.wait(0.0005)  # virtual time: about the wall clock's pace
    thread = threading.Thread(target=loop, daemon=True)
    thread.start()
    r = Rig(fleet, part, run, gateway, net, emcys, lock)
    r.paused = paused  # type: ignore[attr-defined]
    try:
        yield r
    finally:
        stop.set()
        thread.join(5)
        gateway.close()
        notifier.stop()
        net.disconnect()
        bus.shutdown()
        listener.shutdown()
        part.close()
        robot.close()


def test_every_node_boots_and_every_joint_is_off_until_enabled(rig: Rig) -> None:
    eye = rig.node(RIGHT_EYE)
    assert eye.sdo["Manufacturer device name"].raw == "Right Eye"
    rig.until(lambda: eye.sdo[0x6041].raw & 0x006F == 0x0040, "not SWITCH ON DISABLED")
    assert eye.sdo[0x6041].raw & 0x0210 == 0x0210  # voltage enabled (its board runs), remote
    command = rig.part.names.resolve("Right Eye Command")
    rig.until(lambda: rig.part.raw(command) == Command.OFF, "the joint was not switched off")
    rig.until(lambda: {d.drive.state for d in rig.gateway.drives.values()} == {
        State402.SWITCH_ON_DISABLED}, "not every joint SWITCH ON DISABLED")
    serial = eye.sdo[0x1018][4].raw
    assert serial == rig.gateway.image.serials[EYES]  # the board's own, from the init chain


def test_a_gain_written_by_sdo_reaches_the_board_without_the_loop_waiting(
        rig: Rig) -> None:
    eye = rig.node(RIGHT_EYE)
    gain = eye.sdo["RightEye P"]
    before = rig.part.stats.cycles
    gain.raw = 4321
    rig.until(lambda: rig.part.raw(rig.part.names.resolve("RightEye P")) == 4321,
              "the run does not hold the new gain")

    def on_board() -> bool:
        with rig.paused:  # type: ignore[attr-defined]
            return rig.board_par("RightEye P") == 4321
    rig.until(on_board, "the board does not have the new gain")
    assert rig.part.stats.cycles > before
    assert not [w for w in rig.part.writes if w.result != "done"]
    with pytest.raises(SdoAbortedError) as err:
        gain.raw = 1 << 40 if gain.od.max is None else gain.od.max + 1
    assert err.value.code in (0x06090030, 0x06090031, 0x06070010)
    with rig.paused:  # type: ignore[attr-defined]
        assert rig.board_par("RightEye P") == 4321  # nothing reached the board


def test_a_lost_board_puts_its_joints_in_fault_with_its_emcy(rig: Rig) -> None:
    eye, other = rig.node(RIGHT_EYE), rig.node(LEFT_EYE)
    rig.until(lambda: eye.sdo[0x6041].raw & 0x006F == 0x0040, "not SWITCH ON DISABLED")
    rig.fleet.inject(InjectedFault(FaultKind("power-off"), *EYES, for_s=30.0))
    rig.until(lambda: eye.sdo[0x6041].raw & 0x004F == 0x0008, "no FAULT")
    assert other.sdo[0x6041].raw & 0x004F == 0x0008
    assert eye.sdo[0x603F].raw == 0xFF01
    rig.until(lambda: rig.emcys_of((RIGHT_EYE, 0xFF01)) and rig.emcys_of((LEFT_EYE, 0xFF01)),
              "no EMCY 0xFF01 of both eyes")  # (the listener's thread may lag the SDO)
    with pytest.raises(SdoAbortedError) as err:
        eye.sdo["RightEye P"].raw = 1000
    assert err.value.code == 0x08000022
    eye.sdo[0x6040].raw = 0x0080  # fault reset while the cause is there: refused
    assert eye.sdo[0x6041].raw & 0x004F == 0x0008
    neck = rig.node(2)  # another board's joint is not touched
    assert neck.sdo[0x6041].raw & 0x004F == 0x0040


def test_the_python_face_serves_a_started_part_on_a_virtual_bus() -> None:
    """``Gateway.serve(part, ["virtual:NAME"])``: the gateway in the program's own process,
    its master on the same python-can virtual channel."""
    fleet = programmed("armar3")
    robot = robot_of(fleet)
    assert robot.topology is not None
    part = RemotePart(robot, bind(robot.topology), on_fault="hold")
    channel = f"gateway-serve-{uuid.uuid4().hex}"
    try:
        with pytest.raises(InputError, match="start the part first"):
            Gateway.serve(part, [f"virtual:{channel}"])
        part.start()
        with pytest.raises(InputError, match="no bus CAN9"):
            Gateway.serve(part, [f"CAN9=virtual:{channel}"])
        net = canopen.Network(can.Bus(interface="virtual", channel=channel))
        net.connect()
        with Gateway.serve(part, [f"virtual:{channel}"]) as gateway:
            assert len(gateway.drives) == 27
            eye = net.add_node(RIGHT_EYE, dictionary.to_canopen(
                dictionary.build(gateway.drives[RIGHT_EYE].joint)))
            for _ in range(20):
                part.cycle()
            assert eye.sdo["Manufacturer device name"].raw == "Right Eye"
        net.disconnect()
    finally:
        part.close()
        robot.close()


def test_a_shared_command_is_off_only_while_every_joint_asks_off() -> None:
    """LAURON-IV's Leg Mode (0 off, 1 position, 2 velocity) is one edge for three joints."""
    leg = SharedCommand(off=0)
    assert [leg.want(n, 0) for n in (2, 3, 4)] == [0, 0, 0]
    assert leg.want(3, 1) == 1  # one joint enabled: the leg runs
    assert leg.want(2, 0) == 1 and leg.want(4, 0) == 1  # its neighbours' off does not stop it
    assert leg.want(4, 2) == 2  # the latest mode asked for wins
    assert leg.want(4, 0) == 1  # back to the one still enabled
    assert leg.want(3, 0) == 0


def test_lauron4s_legs_are_joints_by_their_boards_own_names() -> None:
    """Each leg has an "Alpha": the gateway finds a joint's edges on its own board."""
    fleet = programmed("lauron4")
    robot = robot_of(fleet)
    assert robot.topology is not None
    part = RemotePart(robot, bind(robot.topology), on_fault="hold")
    channel = f"gateway-lauron-{uuid.uuid4().hex}"
    try:
        part.start()
        with Gateway.serve(part, [f"virtual:{channel}"]) as gateway:
            by_leg: dict[int, list[int]] = {}
            for jd in gateway.drives.values():
                if jd.shared is not None:
                    by_leg.setdefault(id(jd.shared), []).append(jd.board[1])
            assert all(len(set(b)) == 1 for b in by_leg.values())  # one Leg Mode a board
            assert sum(len(b) == 3 for b in by_leg.values()) == 6  # each leg's three joints
            names = {jd._out_names[Role.TARGET] for jd in gateway.drives.values()}
            assert len(names) == len(gateway.drives)  # every joint its own target edge
    finally:
        part.close()
        robot.close()


def test_a_mode_the_joint_lacks_is_refused_and_a_lost_board_sends_one_emcy(rig: Rig) -> None:
    eye = rig.node(RIGHT_EYE)
    with pytest.raises(SdoAbortedError) as err:
        eye.sdo[0x6060].raw = 7  # interpolated position: not a mode of the gateway's
    assert err.value.code == 0x06090030
    eye.sdo[0x6060].raw = 8
    rig.until(lambda: eye.sdo[0x6061].raw == 8, "CSP not taken")
    rig.fleet.inject(InjectedFault(FaultKind("power-off"), *EYES, for_s=30.0))
    rig.until(lambda: eye.sdo[0x6041].raw & 0x004F == 0x0008, "no FAULT")
    syncs = rig.gateway.runtimes[0].stats().syncs
    def cycles_on(n: int) -> Callable[[], bool]:
        start = rig.part.stats.cycles
        return lambda: rig.part.stats.cycles > start + n
    for _ in range(5):  # each SYNC runs every drive of the bus
        rig.until(cycles_on(20), "the loop stopped")
        rig.net.sync.transmit()
    rig.until(lambda: rig.gateway.runtimes[0].stats().syncs == syncs + 5, "SYNCs not seen")
    rig.until(lambda: rig.emcys_of((RIGHT_EYE, 0xFF01)) > 0, "no EMCY")  # (the listener)
    # the drives ran many times while it stayed lost: one EMCY each
    assert rig.emcys_of((RIGHT_EYE, 0xFF01)) == 1, rig.emcys


def test_a_sync_rate_the_pdos_cannot_fit_is_warned_of_once(
        rig: Rig, caplog: pytest.LogCaptureFixture) -> None:
    """Every node OPERATIONAL (27 joints' TPDOs on one bus) and SYNC far faster than
    1 Mbit/s carries: the gateway says so once, naming the rate and the share."""
    rig.node(RIGHT_EYE).nmt.wait_for_heartbeat(DEADLINE_S)
    rig.net.send_message(0x000, bytes((0x01, 0)))  # NMT start, every node
    with caplog.at_level("WARNING", logger="ucom.gateway"):
        for _ in range(120):  # back to back: a rate of thousands of Hz
            rig.net.sync.transmit()
        rig.until(lambda: any("needs" in r.getMessage() for r in caplog.records),
                  "no warning")
        warned = [r.getMessage() for r in caplog.records if "needs" in r.getMessage()]
    assert len(warned) == 1 and "% of a 1 Mbit/s bus" in warned[0], warned
