"""Two hosts on one bus.  A host that is about to program a bus, or to start the cyclic
exchange on it, notices another host doing so (its frames, and answers to requests it
never made) and refuses, exit code 4, before it sends anything that could disturb it;
the first host's work goes on.  Its own frames, echoed back by the interface, are never
taken for another host's.

The served tests run ``ucom fleet serve`` and two ``ucom`` commands as processes on
127.0.0.1 (a third client only watches or asks the boards' state); the in-process tests
put two hosts on one bus of the virtual fleet, in virtual time.  Every wait has a
deadline; nothing sleeps to synchronise."""

from __future__ import annotations

import contextlib
import json
import os
import selectors
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

from tests.helpers import image_words, plan_of
from tests.test_loss import IMAGE, lossy_robot
from tests.test_remote_network import Observer
from ucom_tools.config.topology import load
from ucom_tools.errors import BusError
from ucom_tools.ops.exchange import ExchangeWatch
from ucom_tools.ops.flash import flash, listen_first
from ucom_tools.ops.flash_types import FlashRequest
from ucom_tools.ops.robot import BusHandle, ConnectSpec, Robot
from ucom_tools.protocol.bootloader import BootloaderClient
from ucom_tools.protocol.dispatch import share_clock
from ucom_tools.protocol.link import Link
from ucom_tools.protocol.watch import ProgrammingWatch
from ucom_tools.transport.socketcand import SocketcandBus
from ucom_tools.virtual.canbus import VirtualUcomBus
from ucom_tools.virtual.fleet import Fleet
from ucom_tools.wire import mca
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import StatusOp, Target
from ucom_tools.wire.ids import ALL, Function

ROOT = Path(__file__).resolve().parent.parent
LOCAL = "127.0.0.1"
DEADLINE_S = 60.0
"""The longest any one step may take (a flash over socketcand on a busy machine)."""
FIRMWARE = str(ROOT / "firmware_images" / "armar3.fl.S")


def head_topology(tmp_path: Path, timing: str = "") -> Path:
    """ARMAR-III's CAN0 (neck and head: 3 boards) as a robot of its own, with its trees
    and an optional ``[timing]`` table for its virtual boards."""
    text = (ROOT / "ucom_tools/config/topologies/armar3.toml").read_text()
    first = text.index("[[bus]]")
    head = text[:text.index("[[bus]]", first + 1)]
    head = head.replace('tree = "attribute_trees/', f'tree = "{ROOT}/attribute_trees/')
    head = head[:first] + timing + head[first:]
    path = tmp_path / "head.toml"
    path.write_text(head)
    return path


def ucom(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-m", "ucom_tools", *args], text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def ucom_run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "ucom_tools", *args], text=True,
                          capture_output=True, timeout=DEADLINE_S)


def socketcand(port: int, topo: Path) -> tuple[str, ...]:
    return ("-i", "socketcand", "--host", LOCAL, "--port", str(port), "--topology", str(topo))


@contextlib.contextmanager
def served(topo: Path, state: Path | None = None) -> Iterator[int]:
    """``ucom fleet serve TOPO`` in a process group of its own; its port."""
    args = [sys.executable, "-m", "ucom_tools", "fleet", "serve", str(topo), "--host", LOCAL,
            "--port", "0"] + (["--state", str(state)] if state is not None else [])
    proc = subprocess.Popen(args, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True, env=dict(os.environ, PYTHONUNBUFFERED="1"))
    try:
        assert proc.stdout is not None
        with selectors.DefaultSelector() as sel:
            sel.register(proc.stdout, selectors.EVENT_READ)
            assert sel.select(timeout=DEADLINE_S), "fleet serve did not start"
        line = proc.stdout.readline()
        assert line.startswith(f"listening on {LOCAL}:"), line
        yield int(line.rsplit(":", 1)[1])
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGINT)
        try:
            proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()


def ended(proc: subprocess.Popen[str]) -> tuple[str, str]:
    """What a command wrote, once it ended (killed if it overran its deadline)."""
    try:
        return proc.communicate(timeout=DEADLINE_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
        pytest.fail(f"{proc.args} did not end: {err}")


def data_frame_seen(bus: SocketcandBus, timeout: float) -> bool:
    """A Program data frame (DLC 8) went over the bus within ``timeout``."""
    deadline = time.monotonic() + timeout
    while (remaining := deadline - time.monotonic()) > 0:
        msg = bus.recv(remaining)
        if msg is not None and msg.arbitration_id >> 6 == Function.PROGRAM and msg.dlc == 8:
            return True
    return False


# ---------------------------------------------------------------------- flash, served
def test_a_second_flash_is_refused_while_the_first_sends_data_and_the_first_verifies(
        tmp_path: Path) -> None:
    """Boards that take 0.4 ms a word keep the first flash sending data for seconds; the
    second, started meanwhile, hears its frames before sending anything: exit 4, naming
    them; the first is not disturbed and verifies every board.  Their receive ring is
    small (24 frames, PAUSE at 16, RESUME at 8), so the bus is never silent for as long
    as the second listens (the quiet time, about 0.1 s): with the default ring a board
    paused the stream for 103 ms, and a second host that listened across one heard only
    the boards' Ready RESUME (refused all the same, but not by the data)."""
    topo = head_topology(tmp_path, "[timing]\nword_program_us = 400.0\nrx_capacity = 24\n"
                         "high_water = 16\nlow_water = 8\n\n")
    with served(topo) as port:
        watch = SocketcandBus("CAN0", LOCAL, port)  # only listens
        first = ucom("flash", FIRMWARE, *socketcand(port, topo), "--json")
        try:
            assert data_frame_seen(watch, DEADLINE_S), "the first flash sent no data"
            second = ucom_run("flash", FIRMWARE, *socketcand(port, topo), "--json")
            assert second.returncode == 4, second.stderr
            assert "ucom: bus error: another host is programming CAN0 (frames from another " \
                   "host: " in second.stderr, second.stderr
            assert "Program data frame" in second.stderr
            out, err = ended(first)
        finally:
            watch.shutdown()
            if first.poll() is None:
                first.kill()
                first.communicate()
        assert first.returncode == 0, err
        result = json.loads(out)
        assert result["all_verified"]
        assert [b["outcome"] for b in result["boards"]] == ["verified"] * 3


# ---------------------------------------------------------------------- remote run, served
@pytest.fixture(scope="module")
def head_flashed(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The head robot's topology and a state directory with armar3.fl.S in its flash."""
    tmp = tmp_path_factory.mktemp("head")
    topo = head_topology(tmp)
    state = tmp / "state"
    done = ucom_run("flash", FIRMWARE, "--virtual", str(topo), "--state", str(state))
    assert done.returncode == 0, done.stderr
    return topo, state


def test_a_second_remote_run_is_refused_and_the_first_keeps_its_boards_running(
        head_flashed: tuple[Path, Path]) -> None:
    topo, state = head_flashed
    with served(topo, state) as port:
        # the first runs until it is stopped (Ctrl-C), once the second was refused
        first = ucom("remote", "run", str(topo), *socketcand(port, topo), "--for", "60",
                     "--watchdog", "500", "--json")
        observer = Observer(port)
        try:
            running = observer.wait_for(mca.RunState.RUNNING, time.monotonic() + DEADLINE_S)
            if running != {mca.RunState.RUNNING}:
                first.send_signal(signal.SIGINT)
                out, err = ended(first)
                pytest.fail(f"{running} first: {first.returncode} {err}\n{out[-3000:]}")
            second = ucom_run("remote", "run", str(topo), *socketcand(port, topo), "--for",
                              "1")
            if second.returncode != 4:
                first.send_signal(signal.SIGINT)
                out, err = ended(first)
                pytest.fail(f"second: {second.returncode} {second.stderr}\nfirst: "
                            f"{first.returncode} {err}\n{out[-3000:]}")
            assert "ucom: bus error: another host runs the cyclic exchange on CAN0 (frames " \
                   "from another host: " in second.stderr, second.stderr
            assert "CI map" in second.stderr or "MCA Alive" in second.stderr
            assert "--force" in second.stderr
            assert observer.states() == {mca.RunState.RUNNING}  # untouched
            assert first.poll() is None, "the first stopped when the second was refused"
            first.send_signal(signal.SIGINT)
            out, err = ended(first)
        finally:
            observer.close()
            if first.poll() is None:
                first.kill()
                first.communicate()
        assert first.returncode == 130, err
        run = json.loads(out)
        assert run["started"] and run["interrupted"] and run["run"]["cycles"] > 0
        assert not any(e["stopped_motors"] for e in run["events"])


def test_force_starts_the_exchange_beside_another_hosts(
        head_flashed: tuple[Path, Path]) -> None:
    topo, state = head_flashed
    with served(topo, state) as port:
        first = ucom("remote", "run", str(topo), *socketcand(port, topo), "--for", "10",
                     "--watchdog", "500")
        observer = Observer(port)
        try:
            running = observer.wait_for(mca.RunState.RUNNING, time.monotonic() + DEADLINE_S)
            assert running == {mca.RunState.RUNNING}
            second = ucom_run("remote", "run", str(topo), *socketcand(port, topo), "--for",
                              "0.5", "--watchdog", "500", "--force", "--json")
            assert second.returncode == 0, second.stderr
            assert json.loads(second.stdout)["started"]
            assert "another host" not in second.stderr
        finally:
            observer.close()
            first.send_signal(signal.SIGINT)
            ended(first)


# ---------------------------------------------------------------------- in process
def _second_host(fleet: Fleet, bus: str = "CAN0") -> Link:
    """Another host on ``bus`` of ``fleet`` (its own connection to the bus)."""
    return Link(VirtualUcomBus(bus, fleet=fleet), bus)


def test_a_host_that_sees_another_hosts_program_frames_stops_before_its_data() -> None:
    """While the first host waits for its boards to erase, another host's BEGIN comes:
    the transfer stops with BusError naming it, before a single data frame is sent."""
    with lossy_robot() as (robot, fleet):
        h = robot.buses["CAN0"]
        other = _second_host(fleet)
        sent: list[can.Message] = []
        theirs: list[m.ProgramBegin] = []

        def tap(msg: can.Message) -> None:
            if msg.is_rx:
                return
            sent.append(msg)
            if msg.arbitration_id >> 6 == Function.PROGRAM and len(msg.data) == 3 and \
                    msg.data[0] == 4 and not theirs:  # our PREPARE, then their BEGIN
                theirs.append(m.ProgramBegin(Target.FLASH, 1, 4))
                other.send(theirs[0], ALL)

        h.link.dispatcher.taps.append(tap)
        try:
            with pytest.raises(BusError) as caught:
                flash(robot, FlashRequest(IMAGE))
        finally:
            other.bus.shutdown()
        text = str(caught.value)
        assert text.startswith("another host is programming CAN0 (frames from another "
                               "host: Program BEGIN")
        assert text.endswith("this host stopped before sending data")
        assert any(f.arbitration_id >> 6 == Function.PROGRAM for f in sent)  # its preamble
        assert not [f for f in sent if f.arbitration_id >> 6 == Function.PROGRAM
                    and len(f.data) == 8]


def test_answers_to_requests_never_made_show_another_host() -> None:
    """A host that cannot hear the other host's requests (its interface loses them) still
    notices its transfer: Ready answers to a ProgEnable and a PREPARE it never sent."""
    def deaf(direction: str, msg: can.Message) -> bool:
        return direction == "rx" and msg.arbitration_id >> 6 in (Function.PROGRAM,
                                                                 Function.SET_STATUS)

    with lossy_robot(drop=deaf) as (robot, fleet):
        other = _second_host(fleet)
        try:
            client = BootloaderClient(other)
            client.init_chain()
            other.send(m.SetStatus(StatusOp.PROG_ENABLE, 1), ALL)
            plan = plan_of(image_words(500))
            for frame in (plan.begin(), *plan.meta(), *plan.erases(), plan.prepare()):
                other.send(frame, ALL)
            with pytest.raises(BusError, match=r"another host is programming CAN0 \(frames "
                               r"from another host: .*\(this host sent no (SetStatus|"
                               r"PREPARE)\).*\); nothing was sent"):
                listen_first(robot)
        finally:
            other.bus.shutdown()


def test_a_quiet_bus_is_programmed_as_before() -> None:
    with lossy_robot() as (robot, _):
        listen_first(robot)
        assert flash(robot, FlashRequest(IMAGE)).all_verified


def _echoing_robot(fleet: Fleet) -> Robot:
    """CAN0 of ``fleet`` through an interface that hands every frame it sends back to its
    sender as a received frame (python-can's ``receive_own_messages``)."""
    bus = VirtualUcomBus("CAN0", fleet=fleet, receive_own_messages=True)
    link = Link(bus, "CAN0")
    topo = load("armar3")
    handle = BusHandle("CAN0", bus, link, BootloaderClient(link), topo.bus("CAN0"),
                       virtual=True)
    return Robot(ConnectSpec(virtual="armar3"), {"CAN0": handle}, topo)


def test_own_frames_echoed_back_are_not_another_hosts() -> None:
    fleet = Fleet.load("armar3")
    robot = _echoing_robot(fleet)
    echoed: list[can.Message] = []
    h = robot.buses["CAN0"]
    h.link.dispatcher.taps.append(
        lambda msg: echoed.append(msg) if msg.is_rx and msg.arbitration_id >> 6
        == Function.PROGRAM else None)
    try:
        listen_first(robot)
        h.client.reset()
        result = flash(robot, FlashRequest(IMAGE))
    finally:
        robot.close()
    assert result.all_verified, [b.detail for b in result.boards]
    assert len([f for f in echoed if len(f.data) == 8]) >= IMAGE.plan().blocks[0].frames
    assert any(len(f.data) < 8 for f in echoed)  # the preamble and END came back too


def test_the_exchange_watch_hears_another_hosts_alive_but_not_its_own_echoed() -> None:
    """Two hosts on CAN0 (one clock): the first sends MCA Alive periodically through an
    interface that echoes it; its own watch hears nothing, the second host's hears it."""
    fleet = Fleet.load("armar3")
    first_bus = VirtualUcomBus("CAN0", fleet=fleet, receive_own_messages=True)
    first = Link(first_bus, "CAN0")
    second = _second_host(fleet)
    share_clock([first.dispatcher, second.dispatcher])
    alive = can.Message(arbitration_id=mca.encode(mca.Alive(), ALL)[0], data=b"",
                        is_extended_id=False)
    first.dispatcher.every(0.01, lambda: [alive], "CAN0 MCA Alive")
    try:
        with ExchangeWatch(first) as own:
            own.listen(ExchangeWatch.listen_time(first))
            assert not own.seen
            own.check("CAN0")
        with ExchangeWatch(second) as watch:
            watch.listen(ExchangeWatch.listen_time(second))
            assert watch.seen["MCA Alive"] >= 1
            with pytest.raises(BusError, match="another host runs the cyclic exchange on "
                               r"CAN0 \(frames from another host: \d+ x MCA Alive\)"):
                watch.check("CAN0")
        with ProgrammingWatch(second) as programming:  # Alive is no programming
            programming.listen(0.05)
            assert not programming.seen
    finally:
        first_bus.shutdown()
        second.bus.shutdown()
