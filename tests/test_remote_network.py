"""``ucom remote run`` the way users run it: against ``ucom fleet serve`` in another
process, over socketcand on loopback; the PC side is killed or loses its connection, and
the boards stop by their watchdog."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.helpers import head_topology
from ucom_tools.protocol.link import Link
from ucom_tools.protocol.mca import McaClient
from ucom_tools.transport.socketcand import SocketcandBus
from ucom_tools.wire import mca
from ucom_tools.wire.ids import seq

ROOT = Path(__file__).resolve().parent.parent
DEADLINE_S = 20.0
WATCHDOG_MS = "1000"
"""The boards' watchdog of the runs that must keep them running: the default 50 ms is
shorter than a loaded two-core machine may leave the served fleet's process (or the PC's)
off the processor, and a board then latches although its PC is alive and well; 1 s still
tells a stop by the PC from one by the watchdog at once (the tests wait 20 s)."""


def _ucom(*args: str, **kwargs: object) -> subprocess.Popen[str]:
    env = dict(os.environ, PYTHONFAULTHANDLER="1")  # SIGABRT dumps every thread's stack
    return subprocess.Popen([sys.executable, "-m", "ucom_tools", *args], text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env,
                            **kwargs)  # type: ignore[call-overload]


def _ended(proc: subprocess.Popen[str], what: str) -> tuple[str, str]:
    """What ``proc`` wrote once it ended; where it overran :data:`DEADLINE_S`, the test
    fails with its threads' stacks (faulthandler on SIGABRT) and what it had written."""
    try:
        return proc.communicate(timeout=DEADLINE_S)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGABRT)
        out, err = proc.communicate(timeout=DEADLINE_S)
        pytest.fail(f"{what}: still running after {DEADLINE_S:g} s; its stacks and output:"
                    f"\n{err}\n{out}")


@pytest.fixture(scope="module")
def flashed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The state of the head robot, flashed once for the module (the state directory is
    all a virtual fleet keeps; each test serves a copy of its own)."""
    where = tmp_path_factory.mktemp("flashed-head")
    flash = subprocess.run([sys.executable, "-m", "ucom_tools", "flash",
                            str(ROOT / "firmware_images/armar3.fl.S"), "--virtual",
                            str(head_topology(where)), "--state", str(where / "state")],
                           capture_output=True, text=True, timeout=120)
    assert flash.returncode == 0, flash.stderr
    return where / "state"


@pytest.fixture
def served(flashed: Path, tmp_path: Path) -> Iterator[tuple[Path, int]]:
    """The head robot flashed, then served in another process; (topology, port)."""
    topo = head_topology(tmp_path)
    state = Path(shutil.copytree(flashed, tmp_path / "state"))
    server = _ucom("fleet", "serve", str(topo), "--state", str(state), "--port", "0")
    try:
        assert server.stdout is not None
        line = server.stdout.readline()
        assert line.startswith("listening on 127.0.0.1:"), line + server.stderr.read()
        yield topo, int(line.rsplit(":", 1)[1])
    finally:
        server.send_signal(signal.SIGINT)
        try:
            server.wait(timeout=10)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()


class Observer:
    """A second PC on the bus that only asks the boards for their run state."""

    def __init__(self, port: int) -> None:
        self.bus = SocketcandBus("CAN0", "127.0.0.1", port)
        self.mca = McaClient(Link(self.bus, "CAN0", margin=0.25))

    def states(self) -> set[mca.RunState]:
        out = set()
        for n in (1, 2, 3):
            try:
                out.add(self.mca.query(seq(n)).state)
            except Exception:  # a board that has no seq ID yet (before the PC's init)
                out.add(None)  # type: ignore[arg-type]
        return out

    def wait_for(self, state: mca.RunState, deadline: float) -> set[mca.RunState]:
        seen: set[mca.RunState] = set()
        while time.monotonic() < deadline:
            seen = self.states()
            if seen == {state}:
                return seen
        return seen

    def close(self) -> None:
        self.bus.shutdown()


class Proxy:
    """A TCP forwarder on loopback that can drop its connections (a lost network)."""

    def __init__(self, port: int) -> None:
        self.target = port
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.sockets: list[socket.socket] = []
        self._lock = threading.Lock()
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        with contextlib.suppress(OSError):
            while True:
                client, _ = self.listener.accept()
                upstream = socket.create_connection(("127.0.0.1", self.target))
                with self._lock:
                    self.sockets += [client, upstream]
                for a, b in ((client, upstream), (upstream, client)):
                    threading.Thread(target=self._pipe, args=(a, b), daemon=True).start()

    @staticmethod
    def _pipe(a: socket.socket, b: socket.socket) -> None:
        with contextlib.suppress(OSError):
            while data := a.recv(65536):
                b.sendall(data)

    def cut(self) -> None:
        self.listener.close()
        with self._lock:
            for s in self.sockets:
                with contextlib.suppress(OSError):
                    s.shutdown(socket.SHUT_RDWR)
                s.close()


def _remote(topo: Path, port: int) -> subprocess.Popen[str]:
    return _ucom("remote", "run", str(topo), "-i", "socketcand", "--host", "127.0.0.1",
                 "--port", str(port), "--for", "60", "--watchdog", WATCHDOG_MS)


def test_a_killed_remote_part_leaves_the_boards_to_their_watchdog(served) -> None:
    topo, port = served
    remote = _remote(topo, port)
    observer = Observer(port)
    try:
        deadline = time.monotonic() + DEADLINE_S
        assert observer.wait_for(mca.RunState.RUNNING, deadline) == {mca.RunState.RUNNING}
        os.kill(remote.pid, signal.SIGKILL)  # no goodbye: the PC just dies
        remote.wait(timeout=10)
        started = time.monotonic()
        assert observer.wait_for(mca.RunState.LATCHED, started + DEADLINE_S) == {
            mca.RunState.LATCHED}
    finally:
        observer.close()
        if remote.poll() is None:
            remote.kill()
            remote.wait()


def test_a_lost_connection_is_exit_4_and_the_boards_stop_by_their_watchdog(served) -> None:
    topo, port = served
    proxy = Proxy(port)
    remote = _remote(topo, proxy.port)
    observer = Observer(port)
    try:
        deadline = time.monotonic() + DEADLINE_S
        assert observer.wait_for(mca.RunState.RUNNING, deadline) == {mca.RunState.RUNNING}
        proxy.cut()
        _, err = remote.communicate(timeout=DEADLINE_S)
        assert remote.returncode == 4, err
        assert "bus error" in err and "Traceback" not in err
        assert observer.wait_for(mca.RunState.LATCHED, time.monotonic() + DEADLINE_S) == {
            mca.RunState.LATCHED}
    finally:
        observer.close()
        if remote.poll() is None:
            remote.kill()
            remote.wait()


def test_ctrl_c_stops_the_boards_and_exits_130(served) -> None:
    topo, port = served
    remote = _remote(topo, port)
    observer = Observer(port)
    try:
        assert observer.wait_for(mca.RunState.RUNNING, time.monotonic() + DEADLINE_S) == {
            mca.RunState.RUNNING}
        remote.send_signal(signal.SIGINT)
        _, err = _ended(remote, "ucom remote run after Ctrl-C")
        assert remote.returncode == 130, err
        # stopped by the PC (MCA Start STOP), not latched by the watchdog (a latch stays:
        # waited for, the STOPPED the served fleet may take a moment to apply, as the
        # observer's questions come on a connection of their own, not after the STOP)
        assert observer.wait_for(mca.RunState.STOPPED, time.monotonic() + DEADLINE_S) == {
            mca.RunState.STOPPED}
    finally:
        observer.close()
        if remote.poll() is None:
            remote.kill()
            remote.wait()


def test_realtime_runs_the_loop_under_sched_fifo_or_says_why_not(served) -> None:
    topo, port = served
    remote = _ucom("remote", "run", str(topo), "-i", "socketcand", "--host", "127.0.0.1",
                   "--port", str(port), "--for", "1", "--realtime", "--json",
                   "--watchdog", WATCHDOG_MS)
    observer = Observer(port)
    try:
        out, err = remote.communicate(timeout=DEADLINE_S)
        assert remote.returncode == 0, err + out
        run = json.loads(out)["run"]
        assert run["cycles"] > 0 and not run["virtual_time"]
        if run["realtime"].startswith("normal"):  # not permitted here: said, and why
            assert "SCHED_FIFO" in run["realtime"] and "--realtime" in err
        else:
            assert run["realtime"] == "SCHED_FIFO 40"
        assert observer.wait_for(mca.RunState.STOPPED, time.monotonic() + DEADLINE_S) == {
            mca.RunState.STOPPED}
    finally:
        observer.close()
        if remote.poll() is None:
            remote.kill()
            remote.wait()
