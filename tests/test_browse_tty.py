"""``ucom browse`` on a terminal (issue 18, 2): the view's rendering and its keys as pure
functions, then the real thing: ``ucom remote run armar3 --virtual armar3 --zenoh ...
--allow-writes`` and ``ucom browse`` under a pseudo-terminal, read from the screen and
driven by keys (a set, a refusal, the robot's process stopped and started again, a stop
from the view, q; Ctrl-C and SIGTERM).
Every wait has a deadline; nothing sleeps to synchronise."""

from __future__ import annotations

import fcntl
import io
import os
import re
import select
import shutil
import signal
import socket
import struct
import subprocess
import sys
import termios
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from rich.console import Console

from tests.helpers import terminate
from ucom_tools.cli.browse_tty import split_keys
from ucom_tools.cli.browse_view import (
    Action,
    Catalog,
    Keys,
    Model,
    age_text,
    render,
    tree_rows,
    value_of,
)

ROOT = Path(__file__).resolve().parent.parent
SENSOR = "Right Eye Joint Sensor"
TARGET = "Right Eye Target"


# ---------------------------------------------------------------------- a small robot
def _edge(name: str, kind: str, prefix: str, unit: str = "counts",
          robot_name: str | None = None) -> dict[str, Any]:
    return {"name": name, "generic": name, "qualified": f"{prefix}/{name}",
            "robot_name": robot_name or name, "kind": kind, "unit": unit,
            "range": f"-32768..32767 {unit}".strip(), "writable": kind != "SO",
            "key": f"ucom/head/CAN0/x/edge/{name}"}


STRUCTURE: dict[str, Any] = {
    "v": 1, "robot": "head", "name": "Head", "host": "pc", "pid": 42, "rate_hz": 1000.0,
    "publish_hz": 100.0, "allow_writes": True,
    "buses": [{"name": "CAN0", "bitrate": 1000000, "boards": [
        {"board": 1, "where": "CAN0 board 1 (neck)", "prefix": "Neck", "program": "3/4/1",
         "edges": [_edge("Neck Pitch Target", "CI", "Neck"),
                   _edge("Neck Pitch Joint Sensor", "SO", "Neck"),
                   _edge("Neck Gain", "PAR", "Neck", unit="")]},
        {"board": 3, "where": "CAN0 board 3 (eyes)", "prefix": "Eyes", "program": "2/3/0",
         "edges": [_edge(TARGET, "CI", "Eyes"), _edge("Right Eye Target Vel", "CI", "Eyes",
                                                      unit="counts/s"),
                   _edge(SENSOR, "SO", "Eyes"),
                   _edge("Send Command", "CI", "Eyes", robot_name="Eyes/Send Command")]},
    ]}]}


def _screen(model: Model, keys: Keys, now: float = 10.0, height: int = 24) -> str:
    console = Console(width=120, height=height, record=True, file=io.StringIO(),
                      color_system=None)
    console.print(render(model, keys, now, height))
    return console.export_text()


def _model() -> Model:
    m = Model("tcp/127.0.0.1:7447")
    m.connected(STRUCTURE, now=1.0)
    m.sample({"v": 1, "bus": "CAN0", "board": 3, "t": 12.5,
              "values": {TARGET: 0, SENSOR: 417, "Right Eye Target Vel": 0}}, now=9.75)
    m.board("CAN0", 3, True)
    m.board("CAN0", 1, False)
    return m


# ---------------------------------------------------------------------- the rendering
def test_the_tree_shows_buses_boards_kinds_and_edges_with_values_and_ages() -> None:
    text = _screen(_model(), Keys(Catalog(STRUCTURE)))
    lines = text.splitlines()
    assert "Head (head) on pc, pid 42: 1000 Hz loop, values at 100 Hz, writes allowed" \
        in lines[0]
    assert re.search(r"^\S+ CAN0  1000 kbit/s", text, re.M), text
    assert "CAN0 board 1 (neck) [Neck] 3/4/1  stopped" in text
    assert "CAN0 board 3 (eyes) [Eyes] 2/3/0  running  t 12.500 s" in text
    assert re.search(r"CI \(3\)", text) and re.search(r"SO \(1\)", text)
    assert re.search(rf"{SENSOR}\s+417 counts\s+250 ms", text), text
    assert re.search(r"Neck Pitch Joint Sensor\s+- counts", text), text  # no value yet
    assert "connected to head on tcp/127.0.0.1:7447" in lines[-1]
    assert "q quit" in lines[-1] and "s set" in lines[-1] and "/ filter" in lines[-1]
    assert len(lines) == 24


def test_the_guides_are_a_tree() -> None:
    rows = tree_rows(STRUCTURE)
    assert [r.kind for r in rows[:3]] == ["bus", "board", "kind"]
    assert rows[0].guide == "\u2514\u2500\u2500 "  # the only bus
    assert rows[1].guide == "    \u251c\u2500\u2500 "  # board 1, board 3 follows
    last = rows[-1]
    assert last.kind == "edge" and last.edge is not None and last.edge["kind"] == "SO"
    assert last.guide == " " * 12 + "\u2514\u2500\u2500 "  # the last of the last board
    neck_gain = next(r for r in rows if r.edge and r.edge["name"] == "Neck Gain")
    assert neck_gain.guide == "    \u2502       \u2514\u2500\u2500 "  # board 1's last kind


def test_a_filter_keeps_the_matching_edges_and_their_boards() -> None:
    rows = tree_rows(STRUCTURE, "right eye")
    names = [r.edge["robot_name"] for r in rows if r.edge]
    assert names == [TARGET, "Right Eye Target Vel", SENSOR]
    assert [r.board["prefix"] for r in rows if r.kind == "board"] == ["Eyes"]
    by_prefix = tree_rows(STRUCTURE, "neck")  # a board's prefix: all its edges
    assert len([r for r in by_prefix if r.kind == "edge"]) == 3
    keys = Keys(Catalog(STRUCTURE))
    keys.filter = "nothing like it"
    assert "no edge is called like 'nothing like it'" in _screen(_model(), keys)


def test_connection_lost_is_said_with_its_age_and_the_values_stay() -> None:
    m = _model()
    m.lost(now=20.0)
    text = _screen(m, Keys(Catalog(STRUCTURE)), now=23.5)
    assert "connection lost 3.5 s ago: reconnecting to tcp/127.0.0.1:7447" in text
    assert re.search(rf"{SENSOR}\s+417 counts\s+13.8 s", text), text
    assert "CAN0 board 3 (eyes) [Eyes] 2/3/0  unknown" in text
    m.connected(STRUCTURE, now=30.0)
    text = _screen(m, Keys(Catalog(STRUCTURE)), now=30.0)
    assert "connected to head" in text and "417" not in text


def test_scrolling_is_clamped_to_the_tree() -> None:
    m = _model()
    m.scroll = 1000
    text = _screen(m, Keys(Catalog(STRUCTURE)), height=8)  # 4 lines of tree
    n = len(tree_rows(STRUCTURE))
    assert m.scroll == n - 4 and f"{n - 3}-{n} of {n}" in text
    assert SENSOR in text


def test_board_errors_and_events_are_shown() -> None:
    m = _model()
    m.event({"kind": "board", "bus": "CAN0", "board": 3, "where": "CAN0 board 3 (eyes)",
             "error": "WATCHDOG", "text": "", "stopped_motors": True})
    text = _screen(m, Keys(Catalog(STRUCTURE)))
    assert "[Eyes] 2/3/0  stopped: WATCHDOG" in text
    assert "CAN0 board 3 (eyes): WATCHDOG (motors stopped)" in text
    m.event({"kind": "write", "name": TARGET, "value": 5, "origin": "me@pc pid 1",
             "result": "done"})
    assert f"set {TARGET}=5 from me@pc pid 1: done" in _screen(m, Keys())


def test_a_boards_leds_and_can_errors_are_shown_from_its_status() -> None:
    m = _model()
    m.board_status({"v": 1, "bus": "CAN0", "board": 3, "t": 12.0, "state": "RUNNING_FLASH",
                    "leds": {"red": "on", "yellow": "off", "green": "blink"},
                    "tec": 0, "rec": 3, "overruns": 0})
    text = _screen(m, Keys(Catalog(STRUCTURE)))
    assert "[Eyes] 2/3/0  running  ●○◐ CAN errors tx 0 rx 3  t 12.500 s" in text, text
    neck = next(line for line in text.splitlines() if "[Neck]" in line)
    assert not set("●◐○") & set(neck)  # no status report from it yet: no LEDs shown


def test_ages_and_values() -> None:
    assert [age_text(s) for s in (0.0123, 3.44, 125, 7300)] == ["12 ms", "3.4 s", "2 min",
                                                                 "2 h"]
    assert value_of("1000") == 1000 and value_of("0.5") == 0.5 and value_of("0x444") == "0x444"


# ---------------------------------------------------------------------- the keys
def _feed(keys: Keys, *names: str) -> list[Action]:
    out: list[Action] = []
    for n in names:
        out += keys.feed(n)
    return out


def test_terminal_bytes_become_key_names() -> None:
    assert split_keys("s\x1b[A\x1b[B\x1b[5~\x1b[6~\x1bOH\x1b[F\t\x7f\r\n\x1bq") == [
        "s", "up", "down", "pgup", "pgdn", "home", "end", "tab", "backspace", "enter",
        "esc", "q"]
    assert split_keys("\x1b[1;5A\x15\n") == ["up", "ctrl-u", "enter"]


def test_set_with_tab_completion_then_the_value() -> None:
    keys = Keys(Catalog(STRUCTURE))
    assert _feed(keys, "s", *"right eye tar", "tab") == []
    assert keys.mode == "name" and keys.text == TARGET  # the common start, as spelt
    assert keys.hint == f"2 names: {TARGET}, Right Eye Target Vel"
    assert _feed(keys, "enter") == [] and keys.mode == "value"
    assert keys.name == TARGET and keys.about == "CI, -32768..32767 counts"
    assert "set Right Eye Target (CI, -32768..32767 counts) = " in _screen(_model(), keys)
    assert _feed(keys, "enter") == [] and "a value" in keys.hint
    assert _feed(keys, *"1000", "enter") == [Action("set", TARGET, "1000")]
    assert keys.mode == "view"


def test_set_in_one_line_and_completion_of_a_unique_or_inner_name() -> None:
    keys = Keys(Catalog(STRUCTURE))
    assert _feed(keys, "s", *"neck gain=0.5", "enter") == [Action("set", "Neck Gain", "0.5")]
    _feed(keys, "s", *"Send C", "tab")
    assert keys.text == "Eyes/Send Command"  # no name starts so: the only one that holds it
    _feed(keys, "ctrl-u", *"Neck Pitch T", "tab")
    assert keys.text == "Neck Pitch Target" and keys.hint == ""


def test_set_refuses_unknown_names_and_sensors_with_the_closest_names() -> None:
    keys = Keys(Catalog(STRUCTURE))
    _feed(keys, "s", *"Right Eye Targt", "enter")
    assert keys.mode == "name" and keys.hint.startswith(
        "no CI or PAR is called 'Right Eye Targt'; closest: Right Eye Target")
    _feed(keys, "ctrl-u", *SENSOR, "enter")
    assert keys.mode == "name" and keys.hint == f"{SENSOR} is an SO: read only"
    _feed(keys, "ctrl-u", *"zzz", "tab")
    assert keys.hint == "no CI or PAR is called like 'zzz'"
    assert _feed(keys, "esc") == [] and keys.mode == "view"


def test_filter_stop_scroll_and_quit() -> None:
    keys = Keys(Catalog(STRUCTURE))
    assert _feed(keys, "/", "e", "y") == [Action("top"), Action("top")]
    assert keys.filter == "ey" and keys.mode == "filter"
    assert _feed(keys, "backspace", "enter") == [Action("top")] and keys.filter == "e"
    assert keys.mode == "view"
    assert _feed(keys, "/") == [] and keys.text == "e"  # the filter, to edit
    assert _feed(keys, "esc") == [Action("top")] and keys.filter == ""
    assert _feed(keys, "x", "n") == [] and keys.mode == "view"
    assert _feed(keys, "x") == [] and "y/N" in _screen(_model(), keys)
    assert _feed(keys, "y") == [Action("stop")]
    assert _feed(keys, "down", "k", "pgdn", "home", "G") == [
        Action("scroll", n=1), Action("scroll", n=-1), Action("page", n=1), Action("top"),
        Action("bottom")]
    assert _feed(keys, "q") == [Action("quit")]
    assert _feed(keys, "s", "q") == [] and keys.text == "q"  # typed, not quit


# ---------------------------------------------------------------------- on a real terminal
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


ENV = {**{k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES", "NO_COLOR")},
       "PYTHONPATH": str(ROOT), "TERM": "xterm-256color"}
_ANSI = re.compile(r"\x1b\[[0-9;?]*[ -/]*[@-~]|\x1b\][^\x07\x1b]*(\x07|\x1b\\)|\x1b[()][0-9A-B]"
                   r"|\x1b[=>78]")


def _controlling_terminal() -> None:
    """In the child: a session of its own whose controlling terminal is its standard
    input (the pty), so that Ctrl-C typed there is its SIGINT."""
    os.setsid()
    fcntl.ioctl(0, termios.TIOCSCTTY, 0)


def _restored(term: Terminal, mark: int) -> None:
    """The terminal as it was before the browser: its mode, the main screen, the cursor."""
    after = termios.tcgetattr(term.slave)
    assert after[3] & (termios.ECHO | termios.ICANON) == termios.ECHO | termios.ICANON
    assert after == term.before  # cbreak undone, exactly
    out = bytes(term.raw[mark:])
    assert b"\x1b[?1049l" in out and b"\x1b[?25h" in out


class Terminal:
    """``argv`` on a pseudo-terminal of ``rows`` x ``cols``; what it shows, read as it
    comes (escape sequences taken out)."""

    def __init__(self, argv: list[str], rows: int = 40, cols: int = 150) -> None:
        self.master, self.slave = os.openpty()
        fcntl.ioctl(self.slave, termios.TIOCSWINSZ, struct.pack("HHHH", rows, cols, 0, 0))
        self.before = termios.tcgetattr(self.slave)
        self.proc = subprocess.Popen(argv, stdin=self.slave, stdout=self.slave,
                                     stderr=self.slave, cwd=ROOT, env=ENV,
                                     preexec_fn=_controlling_terminal)
        self.raw = bytearray()
        self.changed = threading.Condition()
        self.done = threading.Event()
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self) -> None:
        while not self.done.is_set():
            ready, _, _ = select.select([self.master], [], [], 0.1)
            if not ready:
                continue
            try:
                data = os.read(self.master, 65536)
            except OSError:
                return
            with self.changed:
                self.raw += data
                self.changed.notify_all()

    def mark(self) -> int:
        with self.changed:
            return len(self.raw)

    def text(self, since: int = 0) -> str:
        with self.changed:
            return _ANSI.sub("", self.raw[since:].decode("utf-8", "replace"))

    def wait_for(self, pattern: str, since: int = 0, timeout: float = 15.0) -> re.Match[str]:
        deadline = time.monotonic() + timeout
        with self.changed:
            while True:
                m = re.search(pattern, _ANSI.sub("", self.raw[since:].decode("utf-8",
                                                                              "replace")))
                if m:
                    return m
                left = deadline - time.monotonic()
                if left <= 0:
                    tail = _ANSI.sub("", self.raw[since:].decode("utf-8", "replace"))
                    raise AssertionError(f"{pattern!r} not on the screen within {timeout:g} "
                                         f"s; it shows:\n{tail[-3000:]}")
                self.changed.wait(min(left, 0.5))

    def keys(self, data: str) -> None:
        os.write(self.master, data.encode())

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        self.done.set()
        self.reader.join(5)
        os.close(self.master)
        os.close(self.slave)


class Robot:
    """``ucom remote run armar3 --virtual armar3 --zenoh ENDPOINT --allow-writes``."""

    def __init__(self, state: Path, endpoint: str, log: Path) -> None:
        self.log = log
        with open(log, "a") as out:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "ucom_tools", "remote", "run", "armar3", "--virtual",
                 "armar3", "--state", str(state), "--zenoh", endpoint, "--allow-writes",
                 "--for", "60"], stdout=out, stderr=out, cwd=ROOT, env=ENV)

    def stop(self) -> None:
        terminate(self.proc)


@pytest.fixture(scope="module")
def flashed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    state = tmp_path_factory.mktemp("flashed") / "armar3"
    r = subprocess.run([sys.executable, "-m", "ucom_tools", "flash",
                        str(ROOT / "firmware_images/armar3.fl.S"), "--virtual", "armar3",
                        "--state", str(state)], capture_output=True, text=True, cwd=ROOT,
                       env=ENV, timeout=120)
    assert r.returncode == 0, r.stderr
    return state


class Rig:
    """A robot on a free loopback port (started again by :meth:`restart`, on the same
    port and state) and browsers on terminals of their own."""

    def __init__(self, flashed: Path, tmp: Path) -> None:
        self.state = tmp / "armar3"
        shutil.copytree(flashed, self.state)
        self.endpoint = f"tcp/127.0.0.1:{_free_port()}"
        self.log = tmp / "robot.log"
        self.robots = [Robot(self.state, self.endpoint, self.log)]
        self.terminals: list[Terminal] = []

    def restart(self) -> None:
        self.robots.append(Robot(self.state, self.endpoint, self.log))

    def browse(self) -> Terminal:
        t = Terminal([sys.executable, "-m", "ucom_tools", "browse", "--zenoh", self.endpoint,
                      "--timeout", "15"])
        self.terminals.append(t)
        return t

    def close(self) -> None:
        for t in self.terminals:
            t.close()
        for r in self.robots:
            r.stop()


@pytest.fixture()
def rig(flashed: Path, tmp_path: Path) -> Iterator[Rig]:
    r = Rig(flashed, tmp_path)
    try:
        yield r
    finally:
        r.close()


def test_browse_on_a_terminal_sets_loses_the_robot_finds_it_again_and_quits(
        rig: Rig) -> None:
    term = rig.browse()
    term.wait_for(r"connected to armar3 on tcp/127\.0\.0\.1:\d+")
    term.wait_for(r"ARMAR-III \(armar3\) on .*writes allowed")
    mark = term.mark()
    term.keys("/Right Eye\r")
    term.wait_for(rf"{SENSOR}\s+-?\d+ counts\s+\d+ ms", mark)
    assert "Neck Pitch Target" not in term.text(term.wait_for(SENSOR, mark).start() + mark)

    mark = term.mark()  # set, the name completed with Tab, then the value
    term.keys("sRight Eye Tar\t")
    term.wait_for(r"\d+ names: Right Eye Target, Right Eye Target Vel", mark)
    term.keys("\r")
    term.wait_for(r"set Right Eye Target \(CI, -32768\.\.32767 counts\) = ", mark)
    term.keys("1000\r")
    term.wait_for(rf"{TARGET} = 1000 counts: done", mark)
    term.wait_for(rf"{TARGET}\s+1000 counts", mark)
    mark = term.mark()  # a value out of range: the robot's refusal, with the range
    term.keys(f"s{TARGET}=100000\r")
    term.wait_for(r"refused: .*100000 is outside -32768\.\.32767 counts", mark)

    mark = term.mark()  # the robot's process ends: said, and found again when it is back
    rig.robots[-1].stop()
    term.wait_for(r"connection lost [\d.]+ m?s ago: reconnecting to tcp/", mark)
    assert term.proc.poll() is None
    mark = term.mark()
    rig.restart()
    term.wait_for(r"connected to armar3 on tcp/", mark, timeout=20)
    mark = term.mark()  # the values from before the loss were drawn since the last mark
    term.wait_for(rf"{SENSOR}\s+-?\d+ counts\s+\d+ ms", mark)

    mark = term.mark()  # x stops the boards and the loop, once confirmed
    term.keys("x")
    term.wait_for(r"stop every board \(motors off\) and the robot's loop\? y/N", mark)
    term.keys("y")
    term.wait_for(r"stopping every board: the robot's loop ends", mark)
    assert rig.robots[-1].proc.wait(timeout=15) == 0
    term.wait_for(r"connection lost", mark)

    mark = term.mark()
    term.keys("q")
    assert term.proc.wait(timeout=10) == 0, term.text()[-2000:] + rig.log.read_text()[-2000:]
    _restored(term, mark)


def test_the_terminal_is_restored_after_ctrl_c_and_sigterm(rig: Rig) -> None:
    interrupted, terminated = rig.browse(), rig.browse()
    marks = []
    for term in (interrupted, terminated):
        term.wait_for(r"connected to armar3 on tcp/")
        marks.append(term.mark())
        term.keys("s")  # in the set prompt: the way out must restore everything still
        term.wait_for(r"set \(name, Tab completes\)", marks[-1])
    interrupted.keys("\x03")  # Ctrl-C, typed: SIGINT from the terminal
    terminated.proc.send_signal(signal.SIGTERM)
    # (what the terminal showed, in the message: an abort by the Zenoh runtime says why)
    assert interrupted.proc.wait(timeout=10) == 130, interrupted.text()[-2000:]
    assert terminated.proc.wait(timeout=10) == 143, terminated.text()[-2000:]
    _restored(interrupted, marks[0])
    _restored(terminated, marks[1])
