"""Leaving the boards as found (``man/ucom.1``, conformance): what every board of a bus
was before the suite touched it, and bringing it back, whatever ended the suite.

As found (:func:`note_found`): each board's Info (program in flash, ProgID, AutoStart),
whether it ran a program, and the raw values of its running program's parameters (MCA
DumpIO Descr and Dump CI, ``man/ucom-protocol.7``, RUN TIME; a program that does not
answer MCA Query has none).  Restored (:func:`restore`): every board reset to its
bootloader (XReset: that ends whatever a case left running), numbered, a flash program
the suite left where there was none made invalid again, AutoStart set again, the programs
that ran started again and their parameters written back where they differ; then each
board is read again and what it lacks is named (``CAN0:2: not running (was running),
AutoStart not set``).  A bus whose connection was lost is opened again (:func:`reopen`)
when it comes back within a deadline.
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass
from typing import Any

import can

from ucom_tools.conformance.bench import Bench
from ucom_tools.conformance.outcome import CaseFailed, Skipped
from ucom_tools.errors import BoardError, BusError, UcomError, UcomTimeoutError
from ucom_tools.ops.exchange import write_runs
from ucom_tools.ops.robot import BusHandle, Robot
from ucom_tools.protocol.bootloader import BootloaderClient
from ucom_tools.protocol.link import Link
from ucom_tools.transport.socketcand import SocketcandBus
from ucom_tools.wire import mca
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import BoardState, StatusOp, Target
from ucom_tools.wire.ids import seq
from ucom_tools.wire.info import BoardInfo

RUNNING = (BoardState.RUNNING_FLASH, BoardState.RUNNING_EXTRAM)
RECONNECT_S = 10.0
"""How long a lost bus is given to come back before its boards are named unrestored."""
RETRY_S = 0.5
"""Between two attempts to open a lost bus again."""


@dataclass
class Found:
    """A board as the suite found it."""

    bus: str
    board: int
    serial: int
    flash_valid: bool
    progid: int | None
    autostart: bool
    running: bool
    extram: bool = False
    """Its program ran from external RAM (a reset ends it: it cannot be started again)."""
    params: tuple[int, ...] | None = None
    """The raw values of its running program's parameters (None: none were read)."""
    param_names: tuple[str, ...] = ()
    params_error: str = ""
    """Why its running program's parameters could not be read."""

    @property
    def where(self) -> str:
        return f"{self.bus}:{self.board}"

    @property
    def was(self) -> str:
        """What it was, in words (for a board that could not be restored)."""
        return ", ".join(["running" if self.running else "in its bootloader",
                          "AutoStart set" if self.autostart else "AutoStart clear"])


def note_found(bench: Bench) -> list[Found]:
    """Every board of the bench's bus as it is now (nothing is changed)."""
    out = []
    for n in bench.boards():
        if not 1 <= n <= 31:
            raise UcomError(f"a board answered the init chain as number {n}")
        info = bench.boot.info(seq(n))
        found = Found(bench.name, n, info.serial, info.flash_valid, info.progid,
                      info.autostart, info.state in RUNNING,
                      extram=info.state is BoardState.RUNNING_EXTRAM)
        if info.state is BoardState.RUNNING_FLASH:
            _note_params(bench, found)
        out.append(found)
    return out


def _note_params(bench: Bench, found: Found) -> None:
    """The parameters of ``found``'s running program, raw, into ``found``."""
    address = seq(found.board)
    try:
        ready = bench.mca.query(address)
    except (BoardError, UcomTimeoutError):
        return  # a program without the run-time protocol: no parameters to keep
    try:
        edges = bench.mca.describe(address, (ready.ci, ready.so, ready.par))
        values = bench.mca.dump(address, mca.Kind.PAR, 0, len(edges.par), edges.par) \
            if edges.par else []
    except (BoardError, UcomTimeoutError) as err:
        found.params_error = str(err)
        return
    found.params = tuple(values)
    found.param_names = tuple(r.name for r in edges.par)


def restore(bench: Bench, found: list[Found]) -> list[str]:
    """Bring every board of ``found`` back (module docstring); what each lacks, one line
    per board.  BusError when the bus fails (see :func:`reopen`)."""
    bench.reset_all()
    bench.init()
    problems = []
    for f in found:
        try:
            lacks = _restore_board(bench, f)
        except BusError:
            raise
        except (UcomError, CaseFailed, Skipped) as err:
            lacks = [f"not restored ({err}; it was {f.was})"]
        if lacks:
            problems.append(f"{f.where}: {', '.join(lacks)}")
    return problems


def _restore_board(bench: Bench, f: Found) -> list[str]:
    if f.board not in bench.numbers:
        return [f"did not answer the init chain at the end (it was {f.was})"]
    address = seq(f.board)
    notes: list[str] = []
    if not f.flash_valid and bench.boot.info(address).flash_valid:
        _invalidate_flash(bench, f.board)  # the suite's image, left by a case cut short
    if f.autostart and f.flash_valid:
        bench.boot.set_status(address, StatusOp.AUTOSTART, 1)
    if f.running and f.flash_valid and not f.extram:
        started = bench.boot.start(address)
        if started and started[0].started and f.params:
            notes += _restore_params(bench, f)
    if f.params_error:
        notes.append(f"parameters unknown (not read as found: {f.params_error})")
    return lacking(f, bench.boot.info(address)) + notes


def lacking(f: Found, info: BoardInfo) -> list[str]:
    """What ``info`` (the board now) lacks of ``f`` (the board as found)."""
    out = []
    running = info.state in RUNNING
    if f.running and not running:
        out.append("not running (was running its program from external RAM, which a reset "
                   "ends)" if f.extram else "not running (was running)")
    elif running and not f.running:
        out.append("running (was not)")
    if f.autostart and not info.autostart:
        out.append("AutoStart not set")
    elif info.autostart and not f.autostart:
        out.append("AutoStart set (was not)")
    if f.flash_valid and not info.flash_valid:
        out.append(f"no valid program in flash (had ProgID {_hex(f.progid)})")
    elif info.flash_valid and not f.flash_valid:
        out.append(f"a program in flash (ProgID {_hex(info.progid)}; had none)")
    elif f.flash_valid and info.progid != f.progid:
        out.append(f"ProgID {_hex(info.progid)} (was {_hex(f.progid)})")
    return out


def _hex(progid: int | None) -> str:
    return "?" if progid is None else f"0x{progid:08X}"


def _invalidate_flash(bench: Bench, n: int) -> None:
    """Make the program in board ``n``'s flash invalid (a transfer begun and aborted leaves
    none: ``man/ucom-protocol.7``, PROGRAMMING, Sequence)."""
    bench.boot.set_status(seq(n), StatusOp.PROG_ENABLE, 1)
    bench.link.send(m.ProgramBegin(Target.FLASH, 1, 4), seq(n))
    bench.link.send(m.ProgramAbort(), seq(n))
    bench.wait(bench.timeouts.reply)
    bench.boot.set_status(seq(n), StatusOp.PROG_ENABLE, 0)


def _restore_params(bench: Bench, f: Found) -> list[str]:
    """Write back the parameters of ``f``'s program that differ from what it had; what
    could not be restored."""
    assert f.params is not None
    address = seq(f.board)
    ready = bench.mca.wait_ready(address, bench.timeouts.reply)
    if ready is None:
        return ["parameters not restored (its program did not answer MCA Query)"]
    try:
        edges = bench.mca.describe(address, (ready.ci, ready.so, ready.par))
        if tuple(r.name for r in edges.par) != f.param_names:
            return ["parameters not restored (its program now has other parameters)"]
        now = bench.mca.dump(address, mca.Kind.PAR, 0, len(edges.par), edges.par)
        differ = [(i, raw) for i, (raw, cur) in enumerate(zip(f.params, now, strict=True))
                  if raw != cur]
        if not differ:
            return []
        write_runs(bench.mca, address, mca.Kind.PAR, differ, edges.par)
        back = bench.mca.dump(address, mca.Kind.PAR, 0, len(edges.par), edges.par)
    except (BoardError, UcomTimeoutError) as err:
        return [f"parameters not restored ({err})"]
    wrong = [f"{f.param_names[i]} = {back[i]} (was {raw})"
             for i, raw in enumerate(f.params) if back[i] != raw]
    return [f"parameters {', '.join(wrong)}"] if wrong else []


def unrestored(found: list[Found], why: str) -> list[str]:
    """One line per board of ``found`` that could not be restored at all, and why."""
    return [f"{f.where}: not restored ({why}; it was {f.was})" for f in found]


def reopen(robot: Robot, name: str, within: float = RECONNECT_S) -> BusHandle | None:
    """Open bus ``name`` of ``robot`` again after its connection was lost, trying until
    ``within`` seconds have passed; the new handle replaces the old one in ``robot`` (and
    in its ``--log``).  None when it did not come back, or cannot be opened again (the
    in-process fleet)."""
    old = robot.buses[name]
    spec = robot.spec
    channel = getattr(old.bus, "channel", None)
    if old.virtual or not spec.interface or not isinstance(channel, str):
        return None
    deadline = time.monotonic() + within
    while True:
        left = deadline - time.monotonic()
        try:
            bus = _open(robot, channel, max(0.1, min(3.0, left)))
            break
        except (can.CanError, OSError, ValueError):
            if left <= 0:
                return None
            time.sleep(min(RETRY_S, max(0.0, deadline - time.monotonic())))  # retry pace
    link = Link(bus, name, bitrate=old.link.bitrate, margin=old.link.margin)
    new = BusHandle(name, bus, link, BootloaderClient(link, robot.timeouts), old.expected,
                    virtual=False)
    with contextlib.suppress(Exception):
        old.bus.shutdown()
    if robot.log is not None:
        robot.log.detach(name, old.link.dispatcher)
        robot.log.attach(name, new.link.dispatcher)
    robot.buses[name] = new
    return new


def _open(robot: Robot, channel: str, timeout: float) -> can.BusABC:
    spec = robot.spec
    if spec.interface == "socketcand":
        if not spec.host or not spec.port:
            raise ValueError("the socketcand interface needs a host and a port")
        return SocketcandBus(channel, spec.host, spec.port, connect_timeout=timeout)
    kwargs: dict[str, Any] = {"bitrate": spec.bitrate} if spec.bitrate else {}
    return can.Bus(interface=spec.interface, channel=channel, **kwargs)
