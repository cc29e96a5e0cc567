"""SIGTERM and SIGHUP stop a job as Ctrl-C does: real signals to real ``ucom`` processes,
sent once the job is under way (seen on its output or on its bus traffic, never after a
sleep), then the exit code (128 + the signal), the message, and the boards' state."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
IMAGE = ROOT / "firmware_images" / "armar3.fl.S"
DEADLINE = 120.0


def start(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-m", "ucom_tools", *args], stdin=subprocess.DEVNULL,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "COLUMNS": "200"})


def wait_for_line(stream, needle: str, seen: list[str]) -> bool:  # type: ignore[no-untyped-def]
    """Read ``stream`` until a line holds ``needle`` (True) or it ends (False)."""
    for line in stream:
        seen.append(line)
        if needle in line:
            return True
    return False


def signal_when(proc: subprocess.Popen[str], stream, needle: str,  # type: ignore[no-untyped-def]
                signum: int) -> list[str]:
    """Send ``signum`` once ``needle`` showed on ``stream``; the lines read up to then."""
    seen: list[str] = []
    box: dict[str, bool] = {}
    reader = threading.Thread(target=lambda: box.setdefault(
        "found", wait_for_line(stream, needle, seen)), daemon=True)
    reader.start()
    reader.join(DEADLINE)
    assert box.get("found"), f"{needle!r} never came: {''.join(seen)}"
    proc.send_signal(signum)
    return seen


@pytest.fixture(scope="module")
def state(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("a3")
    r = subprocess.run([sys.executable, "-m", "ucom_tools", "flash", str(IMAGE), "--virtual",
                        "armar3", "--state", str(d)], capture_output=True, text=True,
                       timeout=DEADLINE)
    assert r.returncode == 0, r.stderr
    return d


@pytest.mark.parametrize(("signum", "code"), [(signal.SIGTERM, 143), (signal.SIGHUP, 129),
                                              (signal.SIGINT, 130)])
def test_remote_run_stops_every_board_on_a_signal(state: Path, signum: int, code: int) -> None:
    proc = start("remote", "run", "armar3", "--virtual", "armar3", "--state", str(state),
                 "--json")
    try:
        seen = signal_when(proc, proc.stderr, "cycles,", signum)  # the first status line
        out, err = proc.communicate(timeout=DEADLINE)
    finally:
        proc.kill()
    assert proc.returncode == code, "".join(seen) + err
    report = json.loads(out)
    assert report["interrupted"] is True and report["not_stopped"] == []
    assert report["run"]["cycles"] > 0
    name = signal.Signals(signum).name
    assert (f"terminated ({name})" if signum != signal.SIGINT else "interrupted") in err
    assert "Traceback" not in err


def test_flash_aborts_the_transfer_on_sigterm(tmp_path: Path) -> None:
    """Paced (the fleet in real time), so the job is under way when the signal comes;
    the boards are put back (no ProgEnable, no transfer) and the message says per board
    what they were left with (every phase: ``tests/test_flash_interrupt.py``)."""
    proc = start("-v", "flash", str(IMAGE), "--virtual", "armar3", "--pace", "--state",
                 str(tmp_path))
    try:
        seen = signal_when(proc, proc.stderr, "programming armar3.fl.S", signal.SIGTERM)
        _out, err = proc.communicate(timeout=DEADLINE)
    finally:
        proc.kill()
    assert proc.returncode == 143, "".join(seen) + err
    assert "flash terminated (SIGTERM) (" in err and "kept their program as found" in err, err
    assert "Traceback" not in err
    check = subprocess.run([sys.executable, "-m", "ucom_tools", "info", "all", "--virtual",
                            "armar3", "--state", str(tmp_path), "--init", "--json"],
                           capture_output=True, text=True, timeout=DEADLINE)
    boards = json.loads(check.stdout)["boards"]
    assert boards and not any(b.get("flash_valid") for b in boards), check.stdout
    assert not any(b.get("prog_enable") or b.get("state") in ("erasing", "receiving")
                   for b in boards), check.stdout


def test_params_load_stops_on_sigterm_seen_on_its_bus_traffic(state: Path,
                                                              tmp_path: Path) -> None:
    """The job's own --log, a FIFO read here, shows when the parameter writes begin."""
    fifo = tmp_path / "traffic.asc"
    os.mkfifo(fifo)
    tree = ROOT / "attribute_trees" / "armar3" / "head_right.tree"
    proc = start("params", "load", "armar3", str(tree), "--virtual", "armar3", "--pace",
                 "--state", str(state), "--log", str(fifo))
    try:
        with open(fifo, encoding="ascii", errors="replace") as traffic:
            seen = signal_when(proc, traffic, " Tx ", signal.SIGTERM)
            traffic.read()  # until the job closes it
        _out, err = proc.communicate(timeout=DEADLINE)
    finally:
        proc.kill()
    assert proc.returncode == 143, "".join(seen[-5:]) + err
    assert "terminated (SIGTERM)" in err and "Traceback" not in err


def test_a_signal_waits_for_the_fleet_step_it_comes_in() -> None:
    """A signal that comes while the in-process fleet runs an event (a board in the middle
    of a frame) is raised after the step, never inside it: an event taken off the clock
    and not finished would leave the board half-way (it then ignored the stop)."""
    from ucom_tools.signals import Terminated, stop_signals
    from ucom_tools.virtual.canbus import VirtualUcomBus
    from ucom_tools.virtual.fleet import Fleet

    fleet = Fleet.load("tests/data/armar3_can0.toml")
    bus = VirtualUcomBus("CAN0", fleet=fleet)
    finished: list[bool] = []

    def event(t: float) -> None:  # a board's work, interrupted by a signal in its middle
        os.kill(os.getpid(), signal.SIGTERM)
        finished.append(True)

    try:
        with stop_signals(), pytest.raises(Terminated):
            fleet.clock.at(fleet.clock.now + 100.0, event)
            bus.recv(timeout=0.001)
        assert finished == [True]  # the event ran to its end, then the signal was raised
    finally:
        bus.shutdown()
        fleet.close()
