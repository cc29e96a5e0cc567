"""``ucom gateway canopen`` tried with real masters (issue 35, part 4): the command runs
ARMAR-III's head (``--bus CAN0``: seven joints, nodes 2-8) over a fleet that ``ucom fleet
serve armar3 --extra-bus CO0`` serves in another process; the CANopen masters are
canopen's ``BaseNode402`` and ``RemoteNode`` as they are, each in a process of its own
(``tests/data/gateway_master.py``, driven a command at a time), on python-can's own
socketcand interface; a listener in this process (python-can's socketcand client too)
records every frame of the CANopen bus with the server's time stamps, which every bus
of the served fleet shares (the frames' end on the wall clock).

One served fleet for the module; one gateway run for the cases that can share it
(:class:`TestSharedRun`, in order), and a run of their own for the master killed and the
board lost.  What the run time itself ended with comes from the run's ``--json``.  Every
wait has a deadline; nothing sleeps to synchronise.
"""

from __future__ import annotations

import contextlib
import csv
import itertools
import json
import os
import socket
import subprocess
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import canopen
import pytest
from click.testing import CliRunner

from tests.gateway_rig import (
    CHANNEL,
    CYCLE_S,
    MASTER_FRAMES,
    MASTER_NODE,
    MAX_LAG,
    NODES,
    OFF,
    REQUESTS_S,
    ROOT,
    SLACK_S,
    START_S,
    SYNC_S,
    WAIT_S,
    Fleet,
    GatewayRun,
    Listener,
    concise,
    edge,
    emcys,
    master,
    until,
)
from tests.test_multiserve import LOCAL, served
from ucom_tools.cli.main import cli


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Fleet]:
    """ARMAR-III flashed (AutoStart), served with the extra bus CO0; the EDS files and
    bus.yml of ``ucom gateway eds``, and what Lely's dcfgen makes of them."""
    where = tmp_path_factory.mktemp("gateway")
    state, eds, dcf = where / "state", where / "eds", where / "dcf"
    runner = CliRunner()
    r = runner.invoke(cli, ["flash", str(ROOT / "firmware_images/armar3.fl.S"), "--virtual",
                            "armar3", "--state", str(state), "--autostart"])
    assert r.exit_code == 0, r.output
    r = runner.invoke(cli, ["gateway", "eds", "armar3", "-o", str(eds), "--json"])
    assert r.exit_code == 0, r.output
    table = {n["node_id"]: n["key"] for n in json.loads(r.stdout)["nodes"] if n["bus"] == "CAN0"}
    assert table == NODES
    dcf.mkdir()
    env = {**os.environ, "PYTHONWARNINGS": "ignore:pkg_resources is deprecated"}
    gen = subprocess.run([str(Path(sys.executable).parent / "dcfgen"), "-r", "-d", str(dcf),
                          "bus.yml"], cwd=eds, capture_output=True, text=True, env=env,
                         timeout=60)
    assert gen.returncode == 0, gen.stderr
    with served("--extra-bus", CHANNEL, "--state", str(state)) as server:
        yield Fleet(server, server.port, eds, dcf)


# ---------------------------------------------------------------------- the shared run
@dataclass
class Shared:
    fleet: Fleet
    run: GatewayRun
    listener: Listener
    at_end: dict[str, tuple[float, float, str]] = field(default_factory=dict)
    """Edge name -> (the value the run's --json must end with, give or take, why)."""

    def expect_at_end(self, name: str, value: float, why: str, within: float = 0) -> None:
        self.at_end[name] = (value, within, why)


@pytest.fixture(scope="class")
def shared(fleet: Fleet) -> Iterator[Shared]:
    """One gateway run for the cases of :class:`TestSharedRun`; at its end, the values
    they left on the boards as the run's --json has them."""
    listener = Listener(fleet.port)
    run = GatewayRun(fleet, "--on-fault", "hold", "--rejoin")
    try:
        run.booted(listener)
        s = Shared(fleet, run, listener)
        yield s
        result = run.stop()
        wrong = {name: (edge(result, name)["value"], value, within, why)
                 for name, (value, within, why) in s.at_end.items()
                 if abs(edge(result, name)["value"] - value) > within}
        assert not wrong, (f"the run ended with (value, expected, give or take, why): "
                           f"{wrong}; the gateway's writes the loop refused: "
                           f"{result['gateway']['writes_refused']} (the last: "
                           f"{result['gateway']['last_refused']}); its events "
                           f"{result['events']}, faults {result['faults']}")
        assert [n["node_id"] for n in result["gateway"]["nodes"]] == list(NODES)
        assert result["gateway"]["buses"][0]["thread_cpu_s"] > 0
    finally:
        run.end()
        listener.close()


# ---------------------------------------------------------------------- helpers of the cases
def steady(read: Callable[[], tuple[int, int, int]], what: str) -> int:
    """Read (0x6064, the other value, 0x6064) until all three agree: the joint stood
    still over the reads (its sensor may move by a count), and the other way gives what
    0x6064 does (a value that differs every time: the deadline, with every read)."""
    got: list[tuple[int, int, int]] = []

    def agree() -> bool:
        got.append(read())
        return len(set(got[-1])) == 1

    until(agree, what=f"{what}: 0x6064 and the other way alike ({got})")
    return got[-1][0]


def lag_periods(samples: list[list[int | None]]) -> list[int]:
    """For each [target of SYNC k, position reported for it]: how many SYNCs back the
    target was that the position has reached (the lag, in SYNC periods)."""
    targets = [t for t, _ in samples]
    out = []
    for k, (_, position) in enumerate(samples):
        if position is None:
            continue
        back = 0
        while back < k and position < targets[k - back]:
            back += 1
        out.append(back)
    return out


def object_limits(eds: str, name: str) -> tuple[int, int, int]:
    """An object's (default, LowLimit, HighLimit) as canopen reads them from the EDS."""
    var = canopen.import_od(eds)[name]
    assert var.min is not None and var.max is not None, name
    return int(var.default), int(var.min), int(var.max)


# ---------------------------------------------------------------------- the shared run
class TestSharedRun:
    """The cases that share one gateway run, in this order.  A master that leaves takes
    the bus's nodes to FAULT once its heartbeat is missed (0x1016, 1 s) where no other
    master's comes first: the next one resets the FAULT on its way to OPERATION ENABLED,
    as BaseNode402 does."""

    def test_profile_position_reaches_its_target_and_0x6064_is_the_joint_sensor(
            self, shared: Shared) -> None:
        """0x6064 is compared with an SDO read of the joint sensor's own manufacturer
        object, named by the tree ("Right Eye Joint Sensor", looked up by canopen in the
        EDS): a way apart from the drive's (the gateway's read callback of that SO edge,
        found by its index, against the drive's joint report, found by its role), both
        the loop's latest values as its snapshots bring them; and the run's --json, the
        loop's own values in its own process, must end with that reading give or take the
        position window (0x6067: its motor is off once its master left)."""
        node = 7  # Right Eye
        with master(shared.fleet) as m:
            m.drive(node, shared.fleet.eds_of(node), "PROFILED POSITION")
            start = m.call("read", node_id=node, k=0x6064)
            window = m.call("read", node_id=node, k=0x6067)
            target = start + 300
            m.call("write", node_id=node, k=0x607A, value=target)
            m.call("controlword", node_id=node, value=0x0F)
            m.call("controlword", node_id=node, value=0x1F)  # new set-point
            m.call("wait_status", node_id=node, mask=0x1000, value=0x1000, within=WAIT_S)
            m.call("controlword", node_id=node, value=0x0F)  # acknowledge seen
            m.call("wait_status", node_id=node, mask=0x1400, value=0x0400, within=WAIT_S)
            position = steady(lambda: (m.call("read", node_id=node, k=0x6064),
                                       m.call("read", node_id=node, k="Right Eye Joint Sensor"),
                                       m.call("read", node_id=node, k=0x6064)), "Right Eye")
            assert abs(position - target) <= window
            assert m.call("statusword", node_id=node) & 0x6F == 0x27  # still enabled
        shared.expect_at_end("Right Eye Joint Sensor", position, "case 1: where PP left it, "
                             "its motor off since its master left", window)

    def test_cyclic_synchronous_position_follows_a_ramp_by_rpdo(self, shared: Shared) -> None:
        node, step, count = 8, 4, 100  # Left Eye: 400 counts/s for 1 s
        with master(shared.fleet) as m:
            m.drive(node, shared.fleet.eds_of(node), "CYCLIC SYNCHRONOUS POSITION")
            start = m.call("read", node_id=node, k=0x6064)
            samples = m.call("csp_ramp", node_id=node, start=start, step=step, count=count,
                             period=SYNC_S, within=count * SYNC_S + WAIT_S)
            sw = m.call("statusword", node_id=node)
            assert sw & 0x6F == 0x27 and sw & 0x1000, f"0x{sw:04X}"  # follows the command
            end = samples[-1][0]
            window = m.call("read", node_id=node, k=0x6067)
            until(lambda: abs(m.call("read", node_id=node, k=0x6064) - end) <= window,
                  what="the joint at the ramp's end")
        lags = lag_periods(samples)
        positions = [p for _, p in samples if p is not None]
        assert len(positions) >= count * 0.9, samples
        assert all(b >= a - 1 for a, b in itertools.pairwise(positions)), \
            samples  # it follows, never back (but by the sensor's last count)
        assert positions[-1] - start >= (count - MAX_LAG) * step, samples
        assert max(lags) <= MAX_LAG, (lags, samples)

    def test_a_pid_gain_by_its_tree_name_reaches_the_board(self, shared: Shared) -> None:
        """The Right Eye's position controller gain ("MotorA P ==> RightEye P" in
        head_right.tree), by canopen's look-up of its ParameterName in the EDS."""
        node, name = 7, "RightEye P"
        default, low, high = object_limits(shared.fleet.eds_of(node), name)
        wanted = 62_500_000  # 62.5: the edge's fixed point (its EDS value x 1e6)
        assert low <= wanted <= high and wanted != default
        with master(shared.fleet) as m:
            m.call("add", node_id=node, eds=shared.fleet.eds_of(node))
            m.call("heartbeat", node_id=node, within=WAIT_S)
            assert m.call("read", node_id=node, k=name) == default
            m.call("write", node_id=node, k=name, value=wanted)
            assert m.call("read", node_id=node, k=name) == wanted
        shared.expect_at_end(name, 62.5, "case 3: the gain written by SDO")

    def test_a_write_out_of_range_is_aborted_and_nothing_reaches_the_board(
            self, shared: Shared) -> None:
        node, name = 2, "Neck Pitch P"  # neck.tree: "MotorA P ==> Neck Pitch P", 40
        default, low, high = object_limits(shared.fleet.eds_of(node), name)
        with master(shared.fleet) as m:
            m.call("add", node_id=node, eds=shared.fleet.eds_of(node))
            m.call("heartbeat", node_id=node, within=WAIT_S)
            assert m.answer("write", node_id=node, k=name, value=high + 1) == \
                {"abort": 0x06090031}  # value of parameter written too high
            assert m.answer("write", node_id=node, k=name, value=low - 1) == \
                {"abort": 0x06090032}  # too low
            assert m.call("read", node_id=node, k=name) == default
        shared.expect_at_end(name, default / 1_000_000, "case 4: refused writes, none sent")

    def test_nmt_stop_switches_an_enabled_joint_off(self, shared: Shared) -> None:
        """Neck Pitch moving in profile velocity, then NMT stop: its motor is off (the
        joint coasts to a stop and stays), watched through another node of its board
        (Neck Roll's SDO: the stopped node answers none)."""
        node, other, sensor = 2, 3, "Neck Pitch Joint Sensor"
        with master(shared.fleet) as m:
            m.drive(node, shared.fleet.eds_of(node), "PROFILED VELOCITY")
            m.call("add", node_id=other, eds=shared.fleet.eds_of(other))
            m.call("write", node_id=node, k=0x60FF, value=2000)

            def position() -> int:
                return int(m.call("read", node_id=other, k=sensor))

            start = position()
            until(lambda: position() - start > 50, what="Neck Pitch moving")
            mark = shared.listener.mark()
            m.call("nmt", node_id=node, state="STOPPED")
            shared.listener.wait(mark, lambda fs: any(
                f.arbitration_id == 0x700 + node and bytes(f.data) == b"\x04" for f in fs),
                what="the heartbeat of a stopped node")
            still: list[int] = []

            def stopped() -> bool:
                still.append(position())
                return len(still) >= 10 and len(set(still[-10:])) == 1  # 0.2 s and more

            until(stopped, what="Neck Pitch standing still")
            m.call("nmt", node_id=node, state="OPERATIONAL")
            assert m.call("read", node_id=node, k=0x6041) & 0x4F == 0x40  # switch on disabled
            assert position() == still[-1]

    def test_a_concise_dcf_from_dcfgen_replayed_into_the_running_gateway(
            self, shared: Shared) -> None:
        """Eyes Tilt's .bin from Lely's dcfgen (bus.yml of ``ucom gateway eds``), written
        as ros2_canopen's master writes it at boot, over a PDO layout another master
        left: its remapped TPDOs arrive, its RPDO1 carries BaseNode402's controlwords to
        OPERATION ENABLED, its heartbeat consumer (0x1016) watches the master.  Reset
        node at the end: the defaults again."""
        node = 6
        binary = shared.fleet.dcf / f"{NODES[node]}.bin"
        entries = concise(binary.read_bytes())
        assert entries[0][:2] == (0x1016, 1)
        with master(shared.fleet) as m:
            m.call("add", node_id=node, eds=shared.fleet.eds_of(node))
            m.call("heartbeat", node_id=node, within=WAIT_S)
            for index, sub, value in ((0x1800, 1, 0x80000186), (0x1A00, 0, 0),
                                      (0x1A00, 1, 0x60640020), (0x1A00, 0, 1),
                                      (0x1800, 1, 0x186), (0x1801, 1, 0x80000286)):
                m.call("write", node_id=node, k=[index, sub], value=value)
            assert m.call("read_pdos", node_id=node)[:2] == [
                [0x186, True, ["Position actual value"]],
                [0x286, False, ["Position actual value", "Velocity actual value"]]]
            assert m.call("replay", node_id=node, path=str(binary)) == len(entries)
            assert m.call("read_pdos", node_id=node)[:2] == [
                [0x186, True, ["Statusword", "Modes of operation display"]],
                [0x286, True, ["Position actual value", "Velocity actual value"]]]
            mark = shared.listener.mark()
            m.call("nmt", node_id=node, state="OPERATIONAL")
            m.call("sync", period=SYNC_S)
            pdos = shared.listener.wait(mark, lambda fs: (
                (a := [f for f in fs if f.arbitration_id == 0x186])
                and (b := [f for f in fs if f.arbitration_id == 0x286]) and (a[-1], b[-1])),
                what="TPDO1 and TPDO2 as remapped")
            assert [len(f.data) for f in pdos] == [3, 8]
            position = int.from_bytes(pdos[1].data[:4], "little", signed=True)
            assert position == m.call("read", node_id=node, k=0x6064)
            m.call("setup", node_id=node)
            assert m.call("state", node_id=node, target="OPERATION ENABLED",
                          within=WAIT_S)[0] == "OPERATION ENABLED"  # by RPDO1
            consumer = m.call("read", node_id=node, k=[0x1016, 1])
            assert consumer == int.from_bytes(entries[0][2], "little")
            mark = shared.listener.mark()
            m.call("produce_heartbeat", period=0)
            lost = shared.listener.wait(mark, lambda fs: emcys(fs, 0x8130).get(node),
                                        what="the EMCY of a master's heartbeat lost")
            beats = shared.listener.since(0, lambda f: f.arbitration_id == 0x700 + MASTER_NODE)
            late = lost.timestamp - beats[-1].timestamp
            timeout = (consumer & 0xFFFF) / 1000
            assert timeout - 0.001 <= late <= timeout + CYCLE_S + SLACK_S, late
            m.call("nmt", node_id=node, state="RESET")


# ---------------------------------------------------------------------- runs of their own
@contextlib.contextmanager
def own_run(fleet: Fleet, *args: str) -> Iterator[tuple[GatewayRun, Listener]]:
    """A gateway run of a case's own (the shared one has ended), its nodes booted."""
    listener = Listener(fleet.port)
    run = GatewayRun(fleet, *args)
    try:
        run.booted(listener)
        yield run, listener
    finally:
        run.end()
        listener.close()


def test_a_master_killed_switches_every_joint_off_by_the_heartbeat_consumer(
        fleet: Fleet, tmp_path: Path) -> None:
    """Every joint OPERATION ENABLED (one moved first: the loop takes the drives'
    commands), each node consuming the master's heartbeat (0x1016: 300 ms, as
    ros2_canopen's bus.yml gives it), then the master SIGKILLed.  Measured from the
    master's last heartbeat on the bus (the listener's time stamps, the served bus's
    clock): each node's EMCY 0x8130, and each joint's Command OFF as the loop set it
    (its --record values file, stamped on the same clock), within that time plus a
    cycle plus :data:`SLACK_S` (the loop: plus the 5 ms it takes the gateway's writes
    at most, ``REQUESTS_EVERY_S``, and the longest its own cycles were apart, which it
    reports: a loop that a busy machine holds up applies nothing meanwhile); the run ends
    with every joint OFF and in FAULT."""
    consumer, record = 0.300, tmp_path / "run.blf"
    with own_run(fleet, "--on-fault", "hold", "--record", str(record)) as (run, listener), \
            master(fleet) as m:
        for node in NODES:
            m.drive(node, fleet.eds_of(node), "PROFILED POSITION",
                    consumer_ms=round(consumer * 1000))
        moved = 7
        start = m.call("read", node_id=moved, k=0x6064)
        m.call("write", node_id=moved, k=0x607A, value=start - 200)
        m.call("controlword", node_id=moved, value=0x1F)
        m.call("wait_status", node_id=moved, mask=0x1400, value=0x1400, within=WAIT_S)
        mark = listener.mark()
        listener.wait(mark, lambda fs: all(
            any(f.arbitration_id == 0x180 + n and f.data[0] & 0x6F == 0x27 for f in fs)
            for n in NODES), what="every node's TPDO1: OPERATION ENABLED")
        m.kill()
        lost = listener.wait(mark, lambda fs: len(e := emcys(fs, 0x8130)) == len(NODES) and e,
                             what="every node's EMCY 0x8130")
        beat = listener.since(0, lambda f: f.arbitration_id == 0x700 + MASTER_NODE)[-1]
        last = max(f.timestamp for f in listener.since(mark)
                   if f.arbitration_id in MASTER_FRAMES)
        deadline = beat.timestamp + consumer + CYCLE_S + SLACK_S
        listener.wait(mark, lambda fs: fs[-1].timestamp > deadline + 1.0,
                      what="the bus's frames (the nodes' heartbeats) a second past the "
                           "deadline: time for a loop that was held up to catch up")
        result = run.stop()
    late = {n: round(e.timestamp - beat.timestamp, 4) for n, e in lost.items()}
    assert all(consumer - 0.001 <= t <= consumer + CYCLE_S + SLACK_S for t in late.values()), \
        (late, f"the master's last frame {last - beat.timestamp:+.4f} s after its heartbeat")
    names = {n["node_id"]: n["name"] for n in result["gateway"]["nodes"]}
    assert {n: edge(result, f"{names[n]} Command")["value"] for n in NODES} == \
        dict.fromkeys(NODES, OFF)
    assert {(n["node_id"], n["state"], n["error_code"]) for n in result["gateway"]["nodes"]} \
        == {(n, "FAULT", 0x8130) for n in NODES}
    off: dict[str, list[float]] = {}
    with open(f"{record}.values.csv", newline="") as f:
        for row in csv.DictReader(f):
            if row["name"].endswith(" Command") and int(row["value"]) == OFF:
                off.setdefault(row["name"][:-len(" Command")], []).append(
                    round(float(row["timestamp"]) - beat.timestamp, 4))
    gap = result["run"]["longest_gap_ms"] / 1000  # the loop's own longest wait
    why = (off, result["run"], {k: v for k, v in result["gateway"].items() if k != "nodes"})
    assert all(off[names[n]][-1] > consumer for n in NODES), why  # off after the master went
    assert max(off[names[n]][-1] for n in NODES) <= \
        consumer + CYCLE_S + SLACK_S + REQUESTS_S + gap, why


def test_a_board_lost_faults_its_joints_until_it_rejoins_and_a_fault_reset(
        fleet: Fleet) -> None:
    """Head right (CAN0/3: Right Eye, Left Eye) powered off for 1 s while both are
    enabled, the run holding the others and bringing it back (--on-fault hold
    --rejoin): FAULT with EMCY 0xFF01; a fault reset while it is lost is refused; once
    it runs again (statusword bit 4, "voltage enabled", back) a fault reset brings SWITCH
    ON DISABLED, and enabled again the joint holds where it stands."""
    eyes = (7, 8)
    with own_run(fleet, "--on-fault", "hold", "--rejoin") as (run, listener), \
            master(fleet) as m:
        for node in eyes:
            m.drive(node, fleet.eds_of(node), "PROFILED POSITION")
        mark = listener.mark()
        fault = CliRunner().invoke(cli, ["fleet", "fault", "--host", LOCAL, "--port",
                                         str(fleet.port), "CAN0/3", "power-off", "--for", "1"])
        assert fault.exit_code == 0, fault.output
        listener.wait(mark, lambda fs: set(eyes) <= set(emcys(fs, 0xFF01)),
                      what="the EMCYs 0xFF01 of both eyes")
        for node in eyes:
            sw = m.call("wait_status", node_id=node, mask=0x4F, value=0x08, within=WAIT_S)[1]
            assert not sw & 0x10, f"0x{sw:04X}: voltage enabled while its board is lost"
            assert m.call("read", node_id=node, k=0x603F) == 0xFF01
        mark = listener.mark()
        m.call("controlword", node_id=7, value=0x00)
        m.call("controlword", node_id=7, value=0x80)  # fault reset, refused while lost
        listener.wait(mark, lambda fs: len([f for f in fs if f.arbitration_id == 0x187]) >= 5,
                      what="five TPDO1 after the fault reset")
        after = [f.data[0] | f.data[1] << 8 for f in listener.since(
            mark, lambda f: f.arbitration_id == 0x187)]
        assert all(sw & 0x4F == 0x08 and not sw & 0x10 for sw in after), \
            [hex(sw) for sw in after]  # FAULT, and still lost: the reset came while lost
        assert 7 not in emcys(listener.since(mark), 0x0000)
        for node in eyes:
            m.call("wait_status", node_id=node, mask=0x5F, value=0x18, within=START_S)
            mark = listener.mark()
            m.call("controlword", node_id=node, value=0x00)
            m.call("controlword", node_id=node, value=0x80)
            m.call("wait_status", node_id=node, mask=0x4F, value=0x40, within=WAIT_S)
            listener.wait(mark, lambda fs, n=node: n in emcys(fs, 0x0000),
                          what="the EMCY error reset")
        stands = {n: m.call("read", node_id=n, k=0x6064) for n in eyes}
        window = m.call("read", node_id=7, k=0x6067)
        for node in eyes:
            assert m.call("state", node_id=node, target="OPERATION ENABLED",
                          within=WAIT_S)[0] == "OPERATION ENABLED"
        mark = listener.mark()
        listener.wait(mark, lambda fs: len([f for f in fs if f.arbitration_id == 0x288]) >= 30,
                      what="0.3 s of Left Eye's TPDO2")
        for node in eyes:
            held = [int.from_bytes(f.data[:4], "little", signed=True)
                    for f in listener.since(mark, lambda f, n=node: f.arbitration_id == 0x280 + n)]
            assert held and all(abs(p - stands[node]) <= window for p in held), (node, held)
        result = run.stop()  # the master still there: the eyes enabled to the end
    faults = [(f["bus"], f["board"], f["event"]) for f in result["faults"]]
    assert faults == [("CAN0", 3, "lost"), ("CAN0", 3, "rejoined")], result["faults"]
    for node, name in ((7, "Right Eye"), (8, "Left Eye")):
        assert edge(result, f"{name} Command")["value"] == 0  # POSITION: the loop has it
        assert abs(edge(result, f"{name} Target")["value"] - stands[node]) <= window


# ---------------------------------------------------------------------- the command's errors
def _free_port() -> int:
    with socket.socket() as s:
        s.bind((LOCAL, 0))
        return int(s.getsockname()[1])


@pytest.mark.parametrize(("spec", "message"), [
    ("virtual:co", "'virtual:co': python-can's virtual buses live in one process"),
    ("socketcan", "'socketcan': expected [UCOM_BUS=]INTERFACE:CHANNEL"),
    ("socketcand:CO0@127.0.0.1", "a socketcand bus is socketcand:CHANNEL@HOST:PORT"),
    ("CAN7=socketcan:vcan0", "'CAN7=socketcan:vcan0': the robot has no bus CAN7 (its "
                             "buses: CAN0, CAN1, CAN2, CAN3)"),
])
def test_a_canopen_bus_that_does_not_fit_is_refused_before_anything_runs(
        spec: str, message: str) -> None:
    result = CliRunner().invoke(cli, ["gateway", "canopen", "armar3", "-i", "socketcand",
                                      "--host", LOCAL, "--port", str(_free_port()),
                                      "--canopen", spec], terminal_width=400)
    assert result.exit_code == 3, result.output  # InputError: bad input
    assert message in " ".join(result.output.split())
    assert "Traceback" not in result.output


def test_an_unreachable_canopen_bus_ends_the_run_before_the_boards_start(
        fleet: Fleet) -> None:
    dead = f"socketcand:{CHANNEL}@{LOCAL}:{_free_port()}"
    result = CliRunner().invoke(cli, ["gateway", "canopen", "armar3", "-i", "socketcand",
                                      "--host", LOCAL, "--port", str(fleet.port), "--bus",
                                      "CAN0", "--canopen", dead, "--json"],
                                terminal_width=400)
    assert result.exit_code == 4, result.output  # bus error
    doc = json.loads(result.stdout)
    assert doc["error"]["exit_code"] == 4 and "started" not in doc
    assert f"CANopen bus {dead}: cannot open the bus" in doc["error"]["message"]
