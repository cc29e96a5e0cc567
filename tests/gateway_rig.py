"""The harness of ``tests/test_gateway_canopen.py``: the served fleet's pieces, the
gateway's run (``ucom gateway canopen`` in a process of its own), a listener on the
CANopen bus, and the masters (``tests/data/gateway_master.py`` in processes of their own,
driven a command at a time).  Every wait has a deadline; nothing sleeps to synchronise."""

from __future__ import annotations

import contextlib
import json
import os
import queue
import signal
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import pytest

from tests.test_multiserve import LOCAL, Server

ROOT = Path(__file__).resolve().parent.parent
MASTER = (Path(__file__).parent / "data" / "gateway_master.py").read_text()
CHANNEL = "CO0"
START_S = 30.0
"""The longest a gateway run may take to boot its nodes (its boards started and checked
first) on a busy machine."""
WAIT_S = 5.0
"""The deadline of every other wait."""
NODES = {2: "neck_pitch", 3: "neck_roll", 4: "neck_yaw", 5: "upper_neck_pitch",
         6: "eyes_tilt", 7: "right_eye", 8: "left_eye"}
"""CAN0's joints as ``ucom gateway eds armar3`` numbers them (the test module's ``fleet``
checks it)."""
OFF = 3
"""The armar3 program's Command OFF."""
SYNC_S = 0.01
WATCHDOG_MS = "1000"
"""The boards' watchdog in these runs: a busy machine holds the loop up now and then (the
run's default of 50 ms is for a robot's PC, not a CI runner's two cores)."""
CYCLE_S = 0.001
"""The gateway's node runtime cycle (``ucom_tools.cli.gateway.CYCLE_S``)."""
SLACK_S = 0.030
"""What a loaded machine may add to a time the gateway keeps, as the served bus's time
stamps see it: the master's last heartbeat reaches the gateway through the serving process
and a TCP socket, and the gateway's consumers' process runs at niceness 10 beside the
loop, the served fleet and the test on two cores (measured here, with other work on them:
4-16 ms past the consumer time for the EMCY, 6-29 ms for the loop's Command OFF)."""
REQUESTS_S = 0.005
"""How often the loop takes the gateway's writes (``ops.remote.feed.REQUESTS_EVERY_S``)."""
MAX_LAG = 20
"""The most SYNC periods a joint in CSP may lag behind its ramp (its cascade's following
error, about 6 periods here, and the gateway's consumers' process, which a busy machine
holds up now and then for tens of milliseconds)."""
MASTER_NODE = 1
HEARTBEAT_S = 0.1
"""The masters' heartbeat (node 1), as ros2_canopen's bus.yml has it."""
CONSUMER_MS = 1000
"""The heartbeat consumer time the masters of the shared run give the nodes (0x1016):
with one, the nodes watch the master's heartbeat instead of its SYNC, whose timeout (50 ms
with a SYNC every 10 ms) a busy machine's bursts reach now and then."""
MASTER_FRAMES = frozenset({0x000, 0x080, *range(0x200, 0x580), *range(0x600, 0x680), 0x701})
"""The identifiers a master sends: NMT, SYNC, RPDOs, SDO requests, its heartbeat."""


# ---------------------------------------------------------------------- the fleet
@dataclass
class Fleet:
    server: Server
    port: int
    eds: Path
    dcf: Path

    def eds_of(self, node: int) -> str:
        return str(self.eds / f"{NODES[node]}.eds")

    @property
    def canopen(self) -> str:
        return f"socketcand:{CHANNEL}@{LOCAL}:{self.port}"


# ---------------------------------------------------------------------- the gateway
class GatewayRun:
    """``ucom gateway canopen armar3 --bus CAN0`` over the served fleet until
    :meth:`stop` (SIGINT, as Ctrl-C): its ``--json`` then."""

    def __init__(self, fleet: Fleet, *args: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "ucom_tools", "gateway", "canopen", "armar3", "-i",
             "socketcand", "--host", LOCAL, "--port", str(fleet.port), "--bus", "CAN0",
             "--canopen", fleet.canopen, "--watchdog", WATCHDOG_MS, "--json", *args],
            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            start_new_session=True)
        self._err: list[str] = []
        self._reader = threading.Thread(target=self._read_stderr, daemon=True)
        self._reader.start()
        self.result: dict[str, Any] | None = None

    def _read_stderr(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self._err.append(line)

    @property
    def stderr(self) -> str:
        return "".join(self._err)

    def stop(self) -> dict[str, Any]:
        """Ctrl-C: every board stopped, the run's --json (exit code 130)."""
        if self.result is None:
            self.proc.send_signal(signal.SIGINT)
            out, _ = self.proc.communicate(timeout=START_S)
            self._reader.join(WAIT_S)
            assert self.proc.returncode == 130, (self.proc.returncode, out, self.stderr)
            self.result = json.loads(out)
        return self.result

    def end(self) -> None:
        """However the case went: Ctrl-C (every board stopped, the consumers' process
        ends with it), else SIGKILL."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.communicate(timeout=START_S)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(WAIT_S)

    def booted(self, listener: Listener) -> None:
        """Wait for the boot-up of every node (once the boards run)."""
        try:
            listener.booted(0, list(NODES), START_S)
        except AssertionError as err:
            raise AssertionError(f"{err}; the run: exit code {self.proc.poll()}, "
                                 f"{self.stderr}") from None


def edge(result: dict[str, Any], name: str) -> dict[str, Any]:
    """A board's edge as the run's --json has it at the end: {name, kind, value, text}."""
    for board in result["boards"]:
        for e in board["edges"]:
            if e["name"] == name:
                return dict(e)
    raise AssertionError(f"no edge {name!r} in the run's --json")


# ---------------------------------------------------------------------- the listener
class Listener:
    """Every frame of the CANopen bus, time-stamped by the server, and waits on them."""

    def __init__(self, port: int) -> None:
        self.bus = can.Bus(interface="socketcand", host=LOCAL, port=port, channel=CHANNEL)
        self.frames: list[can.Message] = []
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name="co-listener")
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self.bus.recv(0.05)
            if msg is None or msg.is_error_frame:
                continue
            with self._cond:
                self.frames.append(msg)
                self._cond.notify_all()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(WAIT_S)
        self.bus.shutdown()

    def mark(self) -> int:
        with self._cond:
            return len(self.frames)

    def since(self, mark: int, pred: Callable[[can.Message], bool] = lambda m: True
              ) -> list[can.Message]:
        with self._cond:
            return [m for m in self.frames[mark:] if pred(m)]

    def wait(self, mark: int, pred: Callable[[list[can.Message]], Any],
             timeout: float = WAIT_S, what: str = "") -> Any:
        with self._cond:
            got = self._cond.wait_for(lambda: pred(self.frames[mark:]), timeout)
        assert got, f"not within {timeout} s: {what or pred}"
        return got

    def booted(self, mark: int, nodes: Iterator[int] | list[int], timeout: float) -> None:
        """Wait for the boot-up of every node of ``nodes`` after ``mark``."""
        ids = {0x700 + n for n in nodes}
        self.wait(mark, lambda fs: ids <= {m.arbitration_id for m in fs
                                           if bytes(m.data) == b"\x00"},
                  timeout, f"the boot-ups of {sorted(i - 0x700 for i in ids)}")


def emcys(frames: list[can.Message], code: int) -> dict[int, can.Message]:
    """The first EMCY with ``code`` of each node among ``frames``."""
    out: dict[int, can.Message] = {}
    for m in frames:
        if 0x081 <= m.arbitration_id <= 0x0FF and len(m.data) == 8 \
                and int.from_bytes(m.data[:2], "little") == code:
            out.setdefault(m.arbitration_id - 0x80, m)
    return out


# ---------------------------------------------------------------------- the masters
class MasterError(AssertionError):
    pass


class Master:
    """``tests/data/gateway_master.py`` in a process of its own: :meth:`call` runs one of
    its commands there and returns its result."""

    def __init__(self, port: int) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-c", MASTER, LOCAL, str(port), CHANNEL], cwd=ROOT,
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self._lines: queue.Queue[str] = queue.Queue()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        assert self._answer(START_S) == {"ok": "ready"}
        self.syncing = False
        self.call("produce_heartbeat", period=HEARTBEAT_S)

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self._lines.put(line)

    def _answer(self, timeout: float) -> dict[str, Any]:
        try:
            line = self._lines.get(timeout=timeout)
        except queue.Empty:
            self.kill()
            raise MasterError(f"the master did not answer within {timeout} s: "
                              f"{self.proc.stderr.read() if self.proc.stderr else ''}") from None
        answer: dict[str, Any] = json.loads(line)
        return answer

    def answer(self, op: str, **args: Any) -> dict[str, Any]:
        """The master's whole answer to ``op``: {"ok": ...}, {"abort": code} or
        {"error": traceback}; within its own deadline (``within``) and :data:`WAIT_S`."""
        assert self.proc.stdin is not None
        self.proc.stdin.write(json.dumps({"op": op, "args": args}) + "\n")
        self.proc.stdin.flush()
        return self._answer(WAIT_S + args.get("within", 0.0))

    def call(self, op: str, **args: Any) -> Any:
        got = self.answer(op, **args)
        if "ok" not in got:
            raise MasterError(f"{op}({args}): {got}")
        return got["ok"]

    def drive(self, node: int, eds: str, mode: str | None = None, *,
              consumer_ms: int = CONSUMER_MS) -> None:
        """As a master takes a drive into service: its heartbeat heard, the master's
        heartbeat consumed (0x1016, ``consumer_ms``), the PDOs read
        (BaseNode402.setup_402_state_machine), NMT start, the SYNC running (from the
        first drive on: its TPDOs carry the statusword BaseNode402 waits for), then
        OPERATION ENABLED (a FAULT that a master before left is reset on the way), in
        ``mode``."""
        self.call("add", node_id=node, eds=eds)
        self.call("heartbeat", node_id=node, within=WAIT_S)
        self.call("write", node_id=node, k=[0x1016, 1], value=MASTER_NODE << 16 | consumer_ms)
        self.call("setup", node_id=node)
        self.call("nmt", node_id=node, state="OPERATIONAL")
        if not self.syncing:
            self.call("sync", period=SYNC_S)
            self.syncing = True
        try:
            self.call("state", node_id=node, target="OPERATION ENABLED", within=WAIT_S)
        except MasterError as err:
            raise MasterError(f"{err}; node {node}: statusword "
                              f"0x{self.call('read', node_id=node, k=0x6041):04X}, error "
                              f"0x{self.call('read', node_id=node, k=0x603F):04X}") from err
        if mode is not None:
            assert self.call("op_mode", node_id=node, mode=mode) == mode

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(WAIT_S)

    def close(self) -> None:
        if self.proc.poll() is None and self.proc.stdin is not None:
            with contextlib.suppress(BrokenPipeError):
                self.proc.stdin.close()
            try:
                self.proc.wait(WAIT_S)
            except subprocess.TimeoutExpired:
                self.kill()


@contextlib.contextmanager
def master(fleet: Fleet) -> Iterator[Master]:
    m = Master(fleet.port)
    try:
        yield m
    finally:
        m.close()


def until(condition: Callable[[], Any], timeout: float = WAIT_S, what: str = "") -> Any:
    deadline = time.monotonic() + timeout
    while True:
        got = condition()
        if got:
            return got
        if time.monotonic() > deadline:
            pytest.fail(f"not within {timeout} s: {what or condition}")
        time.sleep(0.02)  # polling interval


def concise(data: bytes) -> list[tuple[int, int, bytes]]:
    """A concise DCF's entries (CiA 302-3): (index, sub-index, data)."""
    (count,), at = struct.unpack_from("<I", data), 4
    out = []
    for _ in range(count):
        index, sub, size = struct.unpack_from("<HBI", data, at)
        out.append((index, sub, data[at + 7:at + 7 + size]))
        at += 7 + size
    return out
