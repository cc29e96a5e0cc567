"""``ucom conformance`` leaves the boards as found whatever ends it: Ctrl-C, SIGTERM,
SIGHUP (and a second signal during the restore), a trace that cannot be written, a lost
connection that comes back; what cannot be restored is named, with exit code 1.

One served fleet (``ucom fleet serve tests/data/armar3_can0.toml`` on 127.0.0.1, a free
port) for the module, flashed with ``--autostart --start``; each case runs ``ucom
conformance`` as a process of its own over socketcand, ends it once it is under way -
synchronised on the bus (a second client sees the suite's XReset or an SO map) or on its
stderr, never on a sleep - and checks over the bus that every board runs its program
again with AutoStart set, its parameters as they were, and the exit code.  Every wait has
a deadline.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import selectors
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import xml.etree.ElementTree as ET
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, TypeVar

import can
import pytest
from click.testing import CliRunner

from tests.runtime_rig import robot_of
from ucom_tools.cli.exitcodes import EXIT_BUS, EXIT_FAILED, EXIT_WRITE
from ucom_tools.cli.main import cli
from ucom_tools.config.topology import load
from ucom_tools.conformance.bench import Bench
from ucom_tools.conformance.restore import note_found, restore
from ucom_tools.ops.robot import ConnectSpec, open_robot
from ucom_tools.protocol.mca import McaClient
from ucom_tools.transport.socketcand import SocketcandBus
from ucom_tools.virtual.fleet import Fleet
from ucom_tools.wire import mca
from ucom_tools.wire.ids import Function, seq

ROOT = Path(__file__).resolve().parent.parent
TOPOLOGY = str(ROOT / "tests/data/armar3_can0.toml")
IMAGE = str(ROOT / "firmware_images/armar3.fl.S")
LOCAL = "127.0.0.1"
DEADLINE_S = 20.0
"""The longest any one wait may take (a suite's found-phase and restore included)."""
STOP_S = 30.0
"""How soon a signalled suite must have restored the boards and ended."""
T = TypeVar("T")


def until(condition: Callable[[], T], timeout: float = DEADLINE_S, what: str = "") -> T:
    """Poll ``condition`` until it returns something true; fail after ``timeout``."""
    deadline = time.monotonic() + timeout
    while True:
        result = condition()
        if result:
            return result
        if time.monotonic() >= deadline:
            pytest.fail(f"not within {timeout} s: {what or condition}")
        time.sleep(0.02)  # polling interval, not synchronisation


def ucom(*args: str) -> tuple[int, str, str]:
    r = CliRunner().invoke(cli, list(args))
    return r.exit_code, r.stdout, r.stderr


def over(port: int) -> list[str]:
    return ["-i", "socketcand", "--host", LOCAL, "--port", str(port), "-c", "CAN0"]


class Lines:
    """A pipe read by a thread: what came so far can be waited for."""

    def __init__(self, pipe: Any) -> None:
        self.lines: list[str] = []
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._read, args=(pipe,), daemon=True)
        self._thread.start()

    def _read(self, pipe: Any) -> None:
        for line in pipe:
            with self._lock:
                self.lines.append(line)

    def text(self) -> str:
        with self._lock:
            return "".join(self.lines)

    def join(self) -> None:
        self._thread.join(DEADLINE_S)


# ---------------------------------------------------------------------- the fleet
@dataclass
class Served:
    proc: subprocess.Popen[str]
    port: int
    stderr: Lines
    as_flashed: bool = False
    """The boards run their program with AutoStart set (checked by the last test)."""


@pytest.fixture(scope="module")
def served() -> Iterator[Served]:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(
        [sys.executable, "-m", "ucom_tools", "fleet", "serve", TOPOLOGY, "--host", LOCAL,
         "--port", "0"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
        start_new_session=True)
    err = Lines(proc.stderr)
    try:
        assert proc.stdout is not None
        with selectors.DefaultSelector() as sel:
            sel.register(proc.stdout, selectors.EVENT_READ)
            assert sel.select(timeout=DEADLINE_S), "the server did not start: " + err.text()
        line = proc.stdout.readline()
        assert line.startswith(f"listening on {LOCAL}:"), (line, err.text())
        yield Served(proc, int(line.rsplit(":", 1)[1]), err)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGINT)
        try:
            proc.wait(DEADLINE_S)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(DEADLINE_S)


def boards(port: int) -> list[dict[str, Any]]:
    code, out, err = ucom("info", "all", *over(port), "--init", "--json")
    assert code == 0, err
    return list(json.loads(out)["boards"])


def assert_as_flashed(port: int) -> None:
    """Every board runs its program from flash again, with AutoStart set."""
    got = [(b["seq_id"], b["state"], b["autostart"]) for b in boards(port)]
    assert got == [(n, "running (flash)", True) for n in (1, 2, 3)], got


@pytest.fixture
def fleet(served: Served) -> Served:
    """The served fleet, its boards flashed with AutoStart and running (flashed again
    when the last test did not leave them so)."""
    if not served.as_flashed:
        code, _, err = ucom("flash", IMAGE, *over(served.port)[:-2], "--topology", TOPOLOGY,
                            "--autostart", "--start")
        assert code == 0, err
        assert_as_flashed(served.port)
    served.as_flashed = False
    return served


def restored(fleet: Served) -> None:
    assert_as_flashed(fleet.port)
    fleet.as_flashed = True


# ---------------------------------------------------------------------- the suite
class Suite:
    """``ucom conformance --json`` over socketcand, as a process of its own."""

    def __init__(self, port: int, *args: str) -> None:
        env = dict(os.environ, PYTHONUNBUFFERED="1", COLUMNS="200")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "ucom_tools", "conformance", *over(port), "--json", *args],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
            start_new_session=True)
        self.out = Lines(self.proc.stdout)
        self.err = Lines(self.proc.stderr)

    def signal(self, sig: int) -> None:
        assert self.proc.poll() is None, ("the suite ended before the signal", self.err.text())
        self.proc.send_signal(sig)

    def end(self, timeout: float = STOP_S) -> tuple[int, dict[str, Any], str]:
        """Exit code, the JSON report and stderr."""
        try:
            code = self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(DEADLINE_S)
            pytest.fail(f"the suite did not end within {timeout} s: {self.err.text()}")
        self.out.join()
        self.err.join()
        err = self.err.text()
        assert "Traceback" not in err, err
        try:
            report = json.loads(self.out.text())
        except json.JSONDecodeError:
            pytest.fail(f"no JSON report (exit {code}): {self.out.text()!r} {err}")
        return code, report, err

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(DEADLINE_S)


@contextlib.contextmanager
def suite(port: int, *args: str) -> Iterator[Suite]:
    s = Suite(port, *args)
    try:
        yield s
    finally:
        s.kill()


class Sniffer:
    """A second client on the served CAN0: every frame on the bus, and a wait for one of
    a kind."""

    def __init__(self, port: int) -> None:
        self.bus = SocketcandBus("CAN0", LOCAL, port)
        self.frames: list[can.Message] = []
        self.error: BaseException | None = None
        self._lock = threading.Lock()
        self._accepts: Callable[[can.Message], bool] | None = None
        self._seen = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                msg = self.bus.recv(0.05)
                if msg is None:
                    continue
                with self._lock:
                    self.frames.append(msg)
                    if self._accepts is not None and self._accepts(msg):
                        self._seen.set()
        except BaseException as err:  # named by wait()
            self.error = err

    def wait(self, accepts: Callable[[can.Message], bool], what: str, suite: Suite) -> None:
        """Until a frame that ``accepts`` takes has been on the bus."""
        with self._lock:
            self._accepts = accepts
            if any(accepts(f) for f in self.frames):
                self._seen.set()
        if not self._seen.wait(DEADLINE_S):
            pytest.fail(f"no {what} on the bus within {DEADLINE_S} s ({len(self.frames)} "
                        f"frames seen; sniffer: {self.error!r}; suite: {suite.err.text()})")
        self._seen.clear()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(DEADLINE_S)
        self.bus.shutdown()


@contextlib.contextmanager
def sniffing(port: int) -> Iterator[Sniffer]:
    s = Sniffer(port)
    try:
        yield s
    finally:
        s.close()


def xreset(f: can.Message) -> bool:
    """The suite brings every board to its bootloader (and clears AutoStart)."""
    return f.arbitration_id >> 6 == Function.XRESET


def so_map(f: can.Message) -> bool:
    """A board runs the suite's run-time program and exchanges process data."""
    return f.arbitration_id >> 6 == Function.MCA_SENSOR_OUTPUT and bool(f.arbitration_id & 0x20)


def parameter(port: int, board: int, name: str, value: int | None = None) -> int:
    """PAR ``name`` of ``board``'s running program (written first when ``value``)."""
    robot = open_robot(ConnectSpec(interface="socketcand", host=LOCAL, port=port,
                                   channels=("CAN0",)))
    try:
        client = McaClient(robot.buses["CAN0"].link, robot.timeouts)
        try:
            ready = client.query(seq(board))
            par = client.describe(seq(board), (ready.ci, ready.so, ready.par)).par
            index = next(i for i, r in enumerate(par) if r.name == name)
            if value is not None:
                client.write(seq(board), mca.Kind.PAR, index, [value], par)
            (got,) = client.dump(seq(board), mca.Kind.PAR, index, 1, par)
            return got
        finally:
            client.close()
    finally:
        robot.close()


# ---------------------------------------------------------------------- signals
def test_ctrl_c_restores_programs_autostart_and_parameters(fleet: Served) -> None:
    assert parameter(fleet.port, 2, "Max PWM", 12345) == 12345
    assert parameter(fleet.port, 3, "Max PWM", 9876) == 9876
    with sniffing(fleet.port) as bus, suite(fleet.port) as s:
        bus.wait(xreset, "XReset of the suite", s)
        s.signal(signal.SIGINT)
        code, report, err = s.end()
    assert code == 130, err
    assert report["stopped"] == "interrupted (SIGINT)" and not report["ok"]
    assert report["left_as_found"] and report["not_restored"] == [], report["not_restored"]
    assert "interrupted (SIGINT): restoring the boards of CAN0" in err
    restored(fleet)
    assert parameter(fleet.port, 2, "Max PWM") == 12345
    assert parameter(fleet.port, 3, "Max PWM") == 9876
    assert parameter(fleet.port, 1, "Max PWM") == 16000  # untouched: the program's own


def test_sigterm_while_a_board_runs_the_suites_program(fleet: Served) -> None:
    with sniffing(fleet.port) as bus, suite(fleet.port, "--only", "mca.so-period") as s:
        bus.wait(so_map, "SO map of the run-time program", s)
        s.signal(signal.SIGTERM)
        code, report, err = s.end()
    assert code == 143, err
    assert report["stopped"] == "terminated (SIGTERM)" and report["not_restored"] == []
    assert "terminated (SIGTERM)" in err
    restored(fleet)


def test_a_second_signal_waits_for_the_restore(fleet: Served) -> None:
    with sniffing(fleet.port) as bus, suite(fleet.port) as s:
        bus.wait(xreset, "XReset of the suite", s)
        s.signal(signal.SIGHUP)
        until(lambda: "restoring the boards of CAN0" in s.err.text(), what="the restore")
        s.signal(signal.SIGINT)
        code, report, err = s.end()
    assert code == 129, err
    assert report["stopped"] == "terminated (SIGHUP)" and report["not_restored"] == []
    assert "SIGINT: restoring the boards first" in err
    restored(fleet)


# ---------------------------------------------------------------------- writing fails
@contextlib.contextmanager
def full_tmpfs(where: Path) -> Iterator[Path]:
    """A tiny tmpfs at ``where``, filled up (skip where the machine does not mount one)."""
    if shutil.which("mount") is None or shutil.which("umount") is None:
        pytest.skip("no mount(8) here")
    where.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(where)],
                       capture_output=True, text=True, timeout=DEADLINE_S)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.strip() or r.returncode}")
    try:
        with contextlib.suppress(OSError), open(where / "filler", "wb") as f:
            while True:
                f.write(b"\0" * 4096)
                f.flush()
        with pytest.raises(OSError) as full:
            (where / "probe").write_bytes(b"\0" * 4096)
        assert full.value.errno == errno.ENOSPC
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], capture_output=True, timeout=DEADLINE_S)


@pytest.mark.parametrize("how", ["full disk", "a file where the bus directory goes"])
def test_a_trace_that_cannot_be_written(fleet: Served, tmp_path: Path, how: str) -> None:
    with contextlib.ExitStack() as stack:
        if how == "full disk":
            traces = stack.enter_context(full_tmpfs(tmp_path / "full")) / "traces"
            reason = "No space left on device"
        else:
            traces = tmp_path / "traces"
            traces.mkdir()
            (traces / "CAN0").write_text("not a directory\n")
            reason = "not a directory"
        with suite(fleet.port, "--trace-dir", str(traces)) as s:
            code, report, err = s.end()
    ran = report["counts"]
    assert sum(ran.values()) == 1  # the first case, then its trace failed
    assert code == (EXIT_FAILED if ran["failed"] else EXIT_WRITE), err  # a failure wins
    assert report["not_restored"] == []
    assert report["stopped"].startswith("cannot write: --trace-dir: ")
    assert reason in report["stopped"]
    lines = [line for line in err.splitlines() if "cannot write" in line]
    assert len(lines) == 1 and reason in lines[0], err
    assert "a trace could not be written: restoring the boards of CAN0" in err
    restored(fleet)


# ---------------------------------------------------------------------- the connection
class Relay:
    """A TCP relay on loopback in front of the server: :meth:`cut` drops every connection
    it carries (the next is relayed again), :meth:`close` stops taking new ones too."""

    def __init__(self, port: int) -> None:
        self.target = (LOCAL, port)
        self.listener = socket.create_server((LOCAL, 0))
        self.listener.settimeout(0.05)
        self.port = self.listener.getsockname()[1]
        self.accepted = 0
        self._socks: list[socket.socket] = []
        self._lock = threading.Lock()
        self._closed = threading.Event()
        self._threads = [threading.Thread(target=self._accept, daemon=True)]
        self._threads[0].start()

    def _accept(self) -> None:
        while not self._closed.is_set():
            try:
                client, _ = self.listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            upstream = socket.create_connection(self.target, timeout=DEADLINE_S)
            client.settimeout(None)
            upstream.settimeout(None)
            with self._lock:
                self._socks += [client, upstream]
                self.accepted += 1
            for a, b in ((client, upstream), (upstream, client)):
                t = threading.Thread(target=self._pump, args=(a, b), daemon=True)
                self._threads.append(t)
                t.start()

    @staticmethod
    def _pump(src: socket.socket, dst: socket.socket) -> None:
        with contextlib.suppress(OSError):
            while data := src.recv(65536):
                dst.sendall(data)
        for s in (src, dst):
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)

    def cut(self) -> None:
        with self._lock:
            socks, self._socks = self._socks, []
        for s in socks:
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)
            s.close()

    def close(self) -> None:
        self._closed.set()
        self._threads[0].join(DEADLINE_S)
        self.listener.close()
        self.cut()


@contextlib.contextmanager
def relay(port: int) -> Iterator[Relay]:
    r = Relay(port)
    try:
        yield r
    finally:
        r.close()


def test_a_lost_connection_that_comes_back(fleet: Served) -> None:
    with relay(fleet.port) as r, sniffing(fleet.port) as bus, suite(r.port) as s:
        bus.wait(xreset, "XReset of the suite", s)
        r.cut()
        code, report, err = s.end()
        assert r.accepted == 2  # the suite's connection, then the restore's
    assert code == EXIT_BUS, err
    assert report["bus_failure"] and report["not_restored"] == [], report
    assert "the bus failed: restoring the boards of CAN0" in err
    restored(fleet)


def test_a_connection_that_does_not_come_back_names_every_board(fleet: Served) -> None:
    with relay(fleet.port) as r, sniffing(fleet.port) as bus, \
            suite(r.port, "--reconnect", "1") as s:
        bus.wait(xreset, "XReset of the suite", s)
        r.close()
        code, report, err = s.end()
    assert code == EXIT_FAILED, err
    lines = report["not_restored"]
    assert [line.split(":", 2)[:2] for line in lines] == [["CAN0", "1"], ["CAN0", "2"],
                                                           ["CAN0", "3"]], lines
    assert all("did not come back within 1 s" in line and
               "it was running, AutoStart set" in line for line in lines), lines
    assert err.count("not left as found: CAN0:") == 3, err
    # and so they are: in their bootloader, AutoStart cleared by the suite's XReset
    assert {(b["state"], b["autostart"]) for b in boards(fleet.port)} == {("bootloader", False)}



# ---------------------------------------------------------------------- naming
def test_a_board_that_cannot_be_restored_is_named_with_what_it_lacks() -> None:
    """In-process, on the virtual CAN0: a board noted as running its program with
    AutoStart set, which it cannot be again (its flash holds no program)."""
    armar3 = load("armar3")
    robot = robot_of(Fleet(replace(armar3, buses=armar3.buses[:1])))
    bench = Bench(robot.buses["CAN0"], robot.timeouts)
    try:
        bench.init()
        found = note_found(bench)
        assert [(f.running, f.autostart, f.flash_valid) for f in found] == [
            (False, False, False)] * 3
        found[1] = replace(found[1], running=True, autostart=True, flash_valid=True,
                           progid=0x1234)
        assert restore(bench, found) == [
            "CAN0:2: not running (was running), AutoStart not set, no valid program in "
            "flash (had ProgID 0x00001234)"]
    finally:
        bench.close()
        robot.close()


def test_a_report_that_cannot_be_written_is_one_line(tmp_path: Path) -> None:
    """The JUnit report on a full disk (in-process, the virtual fleet): the result is
    reported, the write error is one line with exit code 5, no traceback."""
    with full_tmpfs(tmp_path / "full") as full:
        report = full / "report.xml"
        r = CliRunner().invoke(cli, ["conformance", "--virtual", "armar3", "--bus", "CAN0",
                                     "--only", "ids.*", "--junit", str(report), "--json"])
        assert not report.exists() and not list(full.glob(".report.xml.*"))
    assert r.exit_code == EXIT_WRITE, (r.stderr, r.exception)
    assert json.loads(r.stdout)["ok"]
    assert r.stderr.strip().splitlines() == [
        f"ucom: cannot write: --junit: {report}: No space left on device"]


def test_the_report_of_a_stopped_suite_keeps_the_junit_schema() -> None:
    """The rules Jenkins' xunit validates with, on a report with every kind of outcome
    and a stopped suite (system-err at the testsuite)."""
    from tests import junit_rules
    from ucom_tools.conformance import junit
    from ucom_tools.conformance.catalogue import all_cases
    from ucom_tools.conformance.runner import Outcome, SuiteResult

    cases = all_cases()[:4]
    outcomes = [Outcome(case=c, bus="CAN0", status=status, message=f"{status} here",
                        seconds=0.01, frames="280#0100", trace="")
                for c, status in zip(cases, ("passed", "failed", "error", "skipped"),
                                     strict=True)]
    result = SuiteResult(outcomes=outcomes, not_restored=["CAN0:2: not running"],
                         bus_failure=None)
    assert junit_rules.breaches(junit.to_xml(result).getroot()) == []
    wrong = junit.to_xml(result).getroot()
    ET.SubElement(wrong.find("testcase"), "properties")  # what the report once held
    assert junit_rules.breaches(wrong) == [
        "/testsuite/testcase: 'properties' may not be inside 'testcase'"]
