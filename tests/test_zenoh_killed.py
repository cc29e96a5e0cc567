"""The robot's process killed (issue 18, 4): its loop runs over socketcand against a
fleet served by another process; after ``kill -9`` a browser's subscription sees the
robot's liveliness token go within 2 s, and every board on the loop's bus stops its
motors by its watchdog (latched until MCA Start), because nothing sends MCA Alive any
more: asked afterwards, each says so."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from ucom_tools.net.client import RobotClient
from ucom_tools.ops.robot import ConnectSpec, open_robot
from ucom_tools.protocol.mca import McaClient
from ucom_tools.wire import mca
from ucom_tools.wire.ids import seq

from .test_shared_bus import LOCAL, served, socketcand
from .test_zenoh import DEADLINE_S, _free_port, flashed  # noqa: F401

ROOT = Path(__file__).resolve().parent.parent
TOPOLOGY = Path("armar3")  # the bundled topology, served whole; the loop on CAN0
TOKEN_GONE_S = 2.0


def _latched(port: int) -> dict[int, mca.RunState]:
    """Each CAN0 board's run state, and whether its watchdog latched it."""
    robot = open_robot(ConnectSpec(interface="socketcand", host=LOCAL, port=port,
                                   channels=("CAN0",)))
    try:
        client = McaClient(robot.buses["CAN0"].link, robot.timeouts)
        try:
            out = {}
            for n in (1, 2, 3):
                ready = client.query(seq(n))
                out[n] = ready.state if ready.flags & mca.FLAG_LATCHED_BY_WATCHDOG else None
            return out
        finally:
            client.close()
    finally:
        robot.close()


def test_a_killed_robot_loses_its_token_at_once_and_its_boards_stop_by_watchdog(
        flashed: Path) -> None:  # noqa: F811
    with served(TOPOLOGY, flashed) as port:
        endpoint = f"tcp/{LOCAL}:{_free_port()}"
        robot = subprocess.Popen(
            [sys.executable, "-m", "ucom_tools", "remote", "run", str(TOPOLOGY),
             *socketcand(port, TOPOLOGY), "--bus", "CAN0", "--for", "60",
             "--zenoh", endpoint], cwd=ROOT, stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE, text=True)
        try:
            deadline = time.monotonic() + DEADLINE_S
            client = None
            while client is None:
                try:
                    client = RobotClient.connect(endpoint, timeout=2.0)
                except Exception:
                    assert robot.poll() is None and time.monotonic() < deadline, \
                        robot.stderr.read() if robot.stderr else ""
            with client:
                assert client.read(["Right Eye Joint Sensor"])  # the loop runs
                gone = threading.Event()
                sub = client.on_alive(lambda up: None if up else gone.set())
                robot.send_signal(signal.SIGKILL)
                killed = time.monotonic()
                assert gone.wait(TOKEN_GONE_S), "the robot's token is still there"
                took = time.monotonic() - killed
                sub.close()
            assert robot.wait(timeout=10) == -signal.SIGKILL  # killed, not ended
            assert took < TOKEN_GONE_S
            latched = {n: mca.RunState.LATCHED for n in (1, 2, 3)}
            deadline = killed + 1.0  # the boards' 50 ms watchdog, the bus, the asking
            while (states := _latched(port)) != latched and time.monotonic() < deadline:
                pass
            assert states == latched
        finally:
            if robot.poll() is None:
                robot.kill()
            robot.wait(timeout=10)
