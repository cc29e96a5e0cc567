"""A flash or deploy interrupted at any moment leaves every board either with its old
program intact or in its bootloader with ProgEnable cleared and no transfer open, and
says which, per board.

In process, in virtual time: the interrupt comes at an exact frame of each phase, seen
on the simulated bus, in the two ways a job meets one:

- ``cancel``: a node on the bus sets the job's cancel event when the frame ends on the
  wire (how Ctrl-C, SIGTERM and SIGHUP reach ``ucom flash`` and ``ucom deploy``, whose
  job runs in a worker thread);
- ``raise``: once the host has sent (or received) the frame, its next send or wait
  raises :class:`KeyboardInterrupt` or :class:`~ucom_tools.signals.Terminated` in the
  job's own thread (how a signal reaches a Python caller that runs the job itself).

Then every board of the fleet is looked at directly (ProgEnable, a transfer, the
program's validity and ProgID, AutoStart) and compared with what the job said of it.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from tests.helpers import ROOT, head_topology, served_in_process
from ucom_tools.config import topology as topo_mod
from ucom_tools.image.formats import load_image
from ucom_tools.ops import deploy as deploy_ops
from ucom_tools.ops import leave
from ucom_tools.ops.deploy_execute import execute
from ucom_tools.ops.flash import flash
from ucom_tools.ops.flash_types import FlashInterrupted, FlashRequest, FlashResult
from ucom_tools.ops.robot import BusHandle, ConnectSpec, Robot, open_robot
from ucom_tools.signals import Terminated, interrupt_exit_code, stop_signal
from ucom_tools.virtual.board.ucom import VirtualBoard
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import BoardState

OLD = load_image(ROOT / "firmware_images" / "armar3.fl.S")
NEW_PATH = ROOT / "firmware_images" / "armar3_fpga1.1.fl.S"
NEW = load_image(NEW_PATH)
HEAD = str(ROOT / "tests" / "data" / "armar3_can0.toml")

Match = Callable[[int, bytes], bool]


def frame(ident: int, *head: int) -> Match:
    """The frame with identifier ``ident`` whose data begin with ``head`` (at 0x2C0 a
    Program control frame: DLC < 8, not the data frame of slot 0)."""
    return lambda i, d: i == ident and d[:len(head)] == bytes(head) and (
        i != 0x2C0 or len(d) < 8)


def block(index: int) -> Match:
    """The BLOCK frame of block ``index`` (Program op 5, the index in byte 4)."""
    return lambda i, d: i == 0x2C0 and len(d) == 7 and d[0] == 5 and d[4] == index


def then(*steps: Match) -> Match:
    """The frame ``steps[-1]`` once the frames before it were seen, in that order (it
    keeps what it saw: one per job, so the phases below make one when asked)."""
    at = [0]

    def match(i: int, d: bytes) -> bool:
        if at[0] < len(steps) and steps[at[0]](i, d):
            at[0] += 1
        return at[0] == len(steps)
    return match


class Interrupter:
    """Interrupts the job on bus ``h`` at the first frame ``when`` matches (see the module
    docstring for the modes); ``stop`` is what ``raise`` raises."""

    def __init__(self, h: BusHandle, mode: str, when: Match | Callable[[], Match],
                 stop: Callable[[], KeyboardInterrupt] = KeyboardInterrupt) -> None:
        if when.__code__.co_argcount == 0:  # type: ignore[union-attr]
            when = when()  # type: ignore[call-arg]
        self.cancel = threading.Event()
        self.when, self.stop, self.fired = when, stop, False
        self.armed = False
        self.sim = h.bus.sim  # type: ignore[attr-defined]
        self.link = h.link
        if mode == "cancel":
            self.sim.attach(self)  # its on_frame, looked up per frame
        else:
            send_raw, recv_until = h.link.send_raw, h.link.recv_until

            def sending(ident: int, data: bytes) -> None:
                self._due()
                send_raw(ident, data)
                self._seen(ident, data)

            def receiving(deadline: float) -> object:
                self._due()
                got = recv_until(deadline)
                if got is not None:
                    self._seen(*m.encode(got.message, got.address))
                return got

            h.link.send_raw = sending  # type: ignore[method-assign]
            h.link.recv_until = receiving  # type: ignore[method-assign]

    def on_frame(self, arbitration_id: int, data: bytes, t_end: float, *extra: object) -> None:
        if not self.fired and self.when(arbitration_id, bytes(data)):
            self.fired = True
            self.cancel.set()

    def _seen(self, ident: int, data: bytes) -> None:
        if not self.fired and self.when(ident, data):
            self.fired = self.armed = True

    def _due(self) -> None:
        if self.armed:
            self.armed = False
            raise self.stop()

    def close(self) -> None:
        self.sim.detach(self)
        for name in ("send_raw", "recv_until"):
            self.link.__dict__.pop(name, None)


def boards(r: Robot, bus: str = "CAN0") -> dict[int, VirtualBoard]:
    """The fleet's boards on ``bus`` by seq ID (or position, where they have none)."""
    return {b.seq_id or i: b for i, b in
            enumerate(r.buses[bus].bus.fleet.boards[bus], 1)}  # type: ignore[attr-defined]


def assert_left(board: VirtualBoard, outcome: str, *, old: int, new: int) -> None:
    """What the board is left with, looked at directly, is ``outcome``; in every case no
    transfer is open and ProgEnable is cleared."""
    rec = board.nv.record
    where = f"{board.placement}: {outcome}"
    assert not board.prog_enable, where
    assert board.programming.reception is None, where
    assert board.state not in (BoardState.ERASING, BoardState.RECEIVING), where
    if outcome == leave.KEPT:
        assert rec.flash_valid and rec.progid == old, where
        assert rec.autostart, where + ": AutoStart as found"
    elif outcome == leave.ERASED:
        assert not rec.flash_valid and board.state is BoardState.BOOTLOADER, where
    else:
        assert outcome == leave.VERIFIED and rec.flash_valid and rec.progid == new, where


def erase_cut(board: VirtualBoard) -> bool:
    """The board's erase was stopped part-way: the first page of the old image is erased
    (or being written), its last page still holds the old words."""
    blocks = OLD.plan().blocks
    first, last = blocks[0], blocks[-1]
    memory = board.nv.space(first.space)
    return (list(memory.read(first.address, len(first.words))) != list(first.words)
            and list(board.nv.space(last.space).read(last.address, len(last.words)))
            == list(last.words))


def assert_told(result: FlashResult, r: Robot, expected: dict[int, str]) -> None:
    """The result says per board what the fleet shows, in its outcome, its words and
    the Info it read back."""
    rows = {b.seq_id: b for b in result.boards if b.bus == "CAN0"}
    fleet = boards(r)
    words = {leave.KEPT: "old program intact", leave.ERASED: "erased or made invalid",
             leave.VERIFIED: "new program verified"}
    for n, outcome in expected.items():
        row = rows[n]
        assert row.outcome == outcome, (n, row)
        assert words[outcome] in row.detail, (n, row.detail)
        assert "not ProgEnabled, no transfer open" in row.detail or outcome == leave.VERIFIED, \
            row.detail
        assert row.left is not None and not row.left.prog_enable, row
        assert row.left.state is fleet[n].state, row
        assert_left(fleet[n], outcome, old=OLD.progid, new=NEW.progid)


@pytest.fixture
def head() -> Iterator[Robot]:
    """ARMAR-III's head bus in process, its boards running armar3.fl.S with AutoStart."""
    r = open_robot(ConnectSpec(virtual=HEAD))
    try:
        assert flash(r, FlashRequest(OLD, autostart=True, start=True)).all_verified
        yield r
    finally:
        r.close()


K, E, V = leave.KEPT, leave.ERASED, leave.VERIFIED
PHASES = [  # (phase, where the interrupt comes, per board: cancel, raise)
    ("init chain", frame(0x280, 2, 2), [K, K, K], [K, K, K]),
    ("XReset", frame(0x042), [K, K, K], [K, K, K]),
    ("ProgEnable", frame(0x1C0, 1, 1), [K, K, K], [K, K, K]),
    # raise: META never goes out after BEGIN: nothing erased, but BEGIN cleared the
    # program-valid flag; cancel: the job sees it at its first look in the erase wait
    ("preamble", frame(0x2C0, 1), [E, E, E], [E, E, E]),
    ("erase", frame(0x2C0, 4), [E, E, E], [E, E, E]),
    ("erased", frame(0x183, 1), [E, E, E], [E, E, E]),
    ("transfer", block(10), [E, E, E], [E, E, E]),
    # cancel: the boards' Program Finished came within the job's first look; raise: its
    # ABORT overtakes their verification (ucom-protocol(7), Abort: receiving)
    ("verification", frame(0x2C0, 6), [E, E, E], [E, E, E]),
    ("read-back", lambda: then(frame(0x2C0, 6), frame(0x202)), [V, V, V], [V, V, V]),
    ("AutoStart", frame(0x1C2, 2, 1), [V, V, V], [V, V, V]),
    ("start", frame(0x302), [V, V, V], [V, V, V]),
]


@pytest.mark.parametrize("mode", ["cancel", "raise"])
@pytest.mark.parametrize(("phase", "when", "by_cancel", "by_raise"), PHASES,
                         ids=[p[0] for p in PHASES])
def test_a_flash_interrupted_in_any_phase_leaves_each_board_as_it_says(
        head: Robot, mode: str, phase: str, when: Match, by_cancel: list[str],
        by_raise: list[str]) -> None:
    stop = (lambda: Terminated(signal.SIGTERM)) if phase in ("erase", "start") \
        else KeyboardInterrupt
    trap = Interrupter(head.buses["CAN0"], mode, when, stop)
    try:
        with pytest.raises(FlashInterrupted) as caught:
            flash(head, FlashRequest(NEW, autostart=True, start=True), cancel=trap.cancel)
    finally:
        trap.close()
    assert trap.fired, f"the {phase} never came"
    result = caught.value.result
    expected = dict(enumerate(by_cancel if mode == "cancel" else by_raise, 1))
    bus = result.buses[0]
    assert bus.interrupted, bus
    if phase == "init chain" and mode == "raise":  # the chain was cut: numbered by place
        assert bus.interrupted == "init chain"
        assert [b.placement for b in result.boards] == ["neck", "head left", "head right"]
        assert all(b.outcome == K and "nothing that changes its program" in b.detail
                   for b in result.boards)
        for b in boards(head).values():
            assert_left(b, K, old=OLD.progid, new=NEW.progid)
            assert b.application is not None  # still running its program
    else:
        assert_told(result, head, expected)
    if phase == "erase":  # the job stopped the erase at once, it did not wait it out
        assert all(erase_cut(b) for b in boards(head).values())
    if mode == "raise" and stop is not KeyboardInterrupt:
        assert stop_signal(caught.value) is not None
        assert interrupt_exit_code(caught.value) == 143
    else:
        assert interrupt_exit_code(caught.value) == 130
    if phase in ("erase", "transfer"):  # the bus is usable at once: a flash verifies
        assert flash(head, FlashRequest(NEW)).all_verified


def test_a_resend_round_interrupted_leaves_the_verified_boards_verified(head: Robot) -> None:
    """Board 3 misses a data frame; interrupted when it reports it, before the resend:
    boards 1 and 2 verified, board 3 erased, and each says so."""
    h = head.buses["CAN0"]
    third = boards(head)[3]
    lost = [False]

    def drop(node: object, ident: int, data: bytes) -> bool:
        if node is third and ident == 0x2C5 and not lost[0]:
            lost[0] = True
            return True
        return False

    h.bus.sim.drop = drop  # type: ignore[attr-defined]
    trap = Interrupter(h, "raise", frame(0x103, 0, 1))  # its RESULT: MISSING
    try:
        with pytest.raises(FlashInterrupted) as caught:
            flash(head, FlashRequest(NEW), cancel=trap.cancel)
    finally:
        trap.close()
        h.bus.sim.drop = None  # type: ignore[attr-defined]
    assert lost[0] and trap.fired
    result = caught.value.result
    assert result.buses[0].interrupted == "verification"
    assert_told(result, head, {1: V, 2: V, 3: E})


def test_a_board_that_does_not_answer_the_undo_is_named_unreachable(head: Robot) -> None:
    """Board 2 loses its power while the boards erase (a node on the bus does both: the
    power and the interrupt): the others are put back, board 2 is named, its state
    unknown, in its row and in the line that counts them."""
    from ucom_tools.cli.render import interrupted_line

    second = boards(head)[2]
    trap = Interrupter(head.buses["CAN0"], "cancel", frame(0x2C0, 4))
    interrupt = trap.on_frame

    def power_off_then_interrupt(arbitration_id: int, data: bytes, t_end: float,
                                 *extra: object) -> None:
        if not trap.fired and trap.when(arbitration_id, bytes(data)):
            second.power_off()
        interrupt(arbitration_id, data, t_end)

    trap.on_frame = power_off_then_interrupt  # type: ignore[method-assign]
    try:
        with pytest.raises(FlashInterrupted) as caught:
            flash(head, FlashRequest(NEW), cancel=trap.cancel)
    finally:
        trap.close()
    result = caught.value.result
    rows = {b.seq_id: b for b in result.boards}
    assert rows[2].outcome == leave.UNREACHABLE and rows[2].left is None
    assert "did not answer" in rows[2].detail
    assert rows[1].outcome == rows[3].outcome == E
    assert "1 did not answer (state unknown) (CAN0:2)" in interrupted_line(result, "cancelled")
    for n in (1, 3):
        assert_left(boards(head)[n], E, old=OLD.progid, new=NEW.progid)


def test_an_interrupted_bus_is_put_back_the_one_done_says_so_the_others_not_begun() -> None:
    """The whole robot, interrupted on its second bus while its boards erase (in virtual
    time the buses are worked one after the other): the first bus's boards verified
    ("finished"), the second's put back (erased, ProgEnable cleared), the job on the two
    others never begun, their boards keeping their program."""
    r = open_robot(ConnectSpec(virtual="armar3"))
    try:
        assert flash(r, FlashRequest(OLD)).all_verified
        first, second, *others = r.buses
        trap = Interrupter(r.buses[second], "raise", frame(0x2C0, 4))
        with pytest.raises(FlashInterrupted) as caught:
            flash(r, FlashRequest(NEW), cancel=trap.cancel)
        trap.close()
        result = caught.value.result
        assert {b.bus: b.interrupted for b in result.buses} == {
            first: "finished", second: "erase", **{o: "not begun" for o in others}}
        left = {first: V, second: E, **{o: K for o in others}}
        for b in result.boards:
            assert b.outcome == left[b.bus], b
        for name, outcome in left.items():
            for board in boards(r, name).values():
                assert not board.prog_enable and board.programming.reception is None
                assert board.nv.record.flash_valid is (outcome != E)
                assert board.nv.record.progid == (NEW if outcome == V else OLD).progid \
                    or outcome == E
    finally:
        r.close()


# ----------------------------------------------------------------------------- deploy
@pytest.fixture(scope="module")
def deployed_head(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """ARMAR-III's head deployed (armar3.fl.S, AutoStart, running): its state directory
    and topology; a second topology wants armar3_fpga1.1.fl.S on every board."""
    where = tmp_path_factory.mktemp("head")
    topo = head_topology(where)
    text = topo.read_text()
    (where / "head_v2.toml").write_text(text.replace("firmware_images/armar3.fl.S",
                                                     "firmware_images/armar3_fpga1.1.fl.S"))
    r = open_robot(ConnectSpec(virtual=str(topo), state_dir=where / "state"))
    try:
        t = topo_mod.load(str(topo))
        journal = deploy_ops.Journal.open(where / "journal", t.name)
        request = deploy_ops.DeployRequest(deploy_ops.load_manifest(t), journal)
        assert execute(r, request, deploy_ops.plan(r, request)).ok
    finally:
        r.close()
    return where


@contextmanager
def head_copy(deployed: Path, tmp_path: Path) -> Iterator[tuple[Robot, topo_mod.Topology]]:
    shutil.copytree(deployed / "state", tmp_path / "state")
    r = open_robot(ConnectSpec(virtual=str(deployed / "head.toml"),
                               state_dir=tmp_path / "state"))
    try:
        yield r, topo_mod.load(str(deployed / "head_v2.toml"))
    finally:
        r.close()


STEPS = [  # (step, where the interrupt comes, per board)
    ("reading the parameters", frame(0x601), K),
    ("programming", frame(0x2C0, 4), E),
    ("programming", block(10), E),
    ("loading the parameters back", frame(0x3C1), V),
    ("AutoStart and start", frame(0x1C1, 2, 1), V),
]


@pytest.mark.parametrize(("mode", "step", "when", "outcome"),
                         [("cancel", *s) for s in STEPS]  # the ucom deploy way, every step
                         + [("raise", *s) for s in STEPS if s[0] != "programming"],
                         ids=[f"{m}-{i}" for m, i in [
                             *(("cancel", i) for i in ("dump", "erase", "transfer", "restore",
                                                       "autostart")),
                             *(("raise", i) for i in ("dump", "restore", "autostart"))]])
def test_a_deploy_interrupted_in_any_step_leaves_no_board_prog_enabled_and_says_so(
        deployed_head: Path, tmp_path: Path, mode: str, step: str, when: Match,
        outcome: str) -> None:
    """ARMAR-III's head, deployed, deploys a new image to its three boards, interrupted
    in each step (a KeyboardInterrupt inside the flash is the flash's own, tested above):
    no board ProgEnabled or in a transfer, each as the result says, the journal kept
    for the next deploy, which finishes the work."""
    with head_copy(deployed_head, tmp_path) as (r, topo):
        journal = deploy_ops.Journal.open(tmp_path / "journal", topo.name)
        request = deploy_ops.DeployRequest(deploy_ops.load_manifest(topo), journal)
        the_plan = deploy_ops.plan(r, request)
        assert [x.action for x in the_plan.rows] == ["program"] * 3
        trap = Interrupter(r.buses["CAN0"], mode, when)
        try:
            with pytest.raises(deploy_ops.DeployInterrupted) as caught:
                execute(r, request, the_plan, cancel=trap.cancel)
        finally:
            trap.close()
        assert trap.fired
        result = caught.value.result
        assert result.interrupted == step
        assert result.journal == (journal.directory if journal.boards else None)
        for row in result.boards:
            assert row.outcome == outcome, row
            board = boards(r)[row.row.seq_id]
            assert not board.prog_enable and board.programming.reception is None
            assert row.after is not None
            if outcome == V:
                assert board.nv.record.progid == NEW.progid and board.nv.record.flash_valid
            elif outcome == K:
                assert board.nv.record.progid == OLD.progid and board.nv.record.flash_valid
                assert board.application is not None  # never stopped
            else:
                assert not board.nv.record.flash_valid
            entry = journal.boards.get(row.row.key, {})
            saved = bool(entry.get("params")) and entry.get("stage") != "restored"
            assert ("saved parameters are in the journal" in row.detail) == saved, row.detail
            if step == "programming":
                assert saved
        if step == "programming" and mode == "cancel":  # the next deploy finishes it
            journal = deploy_ops.Journal.open(tmp_path / "journal", topo.name)
            request = deploy_ops.DeployRequest(deploy_ops.load_manifest(topo), journal)
            again = execute(r, request, deploy_ops.plan(r, request))
            assert again.ok, again.failed
            assert all(b.params.outcome == "kept" for b in again.boards)


# ----------------------------------------------------------------------------- served
class Signaller:
    """A node on a served bus that sends ``signum`` to ``proc`` when ``when`` first
    matches a frame there (the served fleet runs in this process: the bus is seen as it
    happens, never guessed by a sleep), and ``signum`` again at the frame ``again``
    matches after it (a second Ctrl-C while the job puts its boards back)."""

    def __init__(self, when: Match, signum: int, again: Match | None = None) -> None:
        self.steps = [when] + ([again] if again is not None else [])
        self.signum = signum
        self.proc: subprocess.Popen[str] | None = None
        self.sent = 0

    @property
    def fired(self) -> bool:
        return self.sent == len(self.steps)

    def on_frame(self, arbitration_id: int, data: bytes, t_end: float, *extra: object) -> None:
        if self.proc is not None and not self.fired and \
                self.steps[self.sent](arbitration_id, bytes(data)):
            self.sent += 1
            self.proc.send_signal(self.signum)


SERVED = [  # (phase on CAN0, where, signal, exit code, CAN0's boards)
    # the finding this file answers; the erase takes 1.25 s
    ("erase", frame(0x2C0, 4), signal.SIGINT, 130, E),
    # the first XReset: the job waits the board's reset time (100 ms) before the next
    # step, far longer than the signal takes to reach it
    ("XReset", frame(0x041), signal.SIGHUP, 129, K),
]


@pytest.mark.parametrize(("phase", "when", "signum", "code", "outcome"), SERVED,
                         ids=[s[0] for s in SERVED])
def test_a_whole_robot_flash_over_fleet_serve_signalled_in_a_phase_puts_every_board_back(
        phase: str, when: Match, signum: int, code: int, outcome: str) -> None:
    """``ucom flash`` of ARMAR-III over ``fleet serve`` (its four buses at once, boards
    running armar3.fl.S with AutoStart), signalled when CAN0 reaches the phase (during
    the erase twice, as a hurried user presses Ctrl-C): the exit code is the signal's,
    and every one of the 11 boards is as the JSON says (CAN0's in the phase's outcome;
    the other buses', at whatever step they were, kept, erased or verified), none
    ProgEnabled, none in a transfer."""
    with served_in_process("armar3") as (fleet, port):
        with fleet.bus("CAN0").lock:
            for name, spec in fleet.boards.items():
                for board in spec:
                    board.nv.install(OLD.plan())
                    board.nv.record.autostart = True
                    board.power_off()
                    board.power_on(fleet.bus(name).now)
        # during the erase, Ctrl-C twice: the second when the undo's ABORT is on the bus
        tap = Signaller(when, signum, frame(0x2C0, 7) if phase == "erase" else None)
        fleet.bus("CAN0").attach(tap)
        conn = ["-i", "socketcand", "--host", "127.0.0.1", "--port", str(port)]
        for name in fleet.buses:
            conn += ["-c", name]
        tap.proc = subprocess.Popen(
            [sys.executable, "-m", "ucom_tools", "flash", str(NEW_PATH), *conn,
             "--topology", "armar3", "--autostart", "--start", "--json"],
            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            text=True, env={**os.environ, "COLUMNS": "200"})
        try:
            out, err = tap.proc.communicate(timeout=120)
        finally:
            tap.proc.kill()
        assert tap.fired, err
        assert tap.proc.returncode == code, err
        doc = json.loads(out)
        assert doc["interrupted"]["signal"] == signal.Signals(signum).name
        assert doc["interrupted"]["buses"]["CAN0"] == phase, doc["interrupted"]
        assert "Traceback" not in err and ("flash cancelled" if signum == signal.SIGINT
                                           else "flash terminated") in err, err
        assert ("still putting the boards back" in err) is (phase == "erase"), err
        rows = {(b["bus"], b["seq_id"]): b for b in doc["boards"]}
        assert len(rows) == 11
        with fleet.bus("CAN0").lock:
            for name, spec in fleet.boards.items():
                for board in spec:
                    row = rows[(name, board.seq_id)]
                    if name == "CAN0":
                        assert row["outcome"] == outcome, row
                    if doc["interrupted"]["buses"][name] == "finished":  # done before
                        assert row["outcome"] == V and row["started"], row
                        assert_left(board, V, old=OLD.progid, new=NEW.progid)
                        continue
                    assert row["left"]["prog_enable"] is False, row
                    assert row["left"]["state"] == board.state.text, row
                    if row["outcome"] == K:
                        assert row["left"]["autostart"] is True, row  # as found
                    assert_left(board, row["outcome"], old=OLD.progid, new=NEW.progid)


@contextmanager
def served_running(topology: str) -> Iterator[tuple[object, int]]:
    """``topology`` served from this process, every board running armar3.fl.S with
    AutoStart (stored as a verified transfer would, then powered on again)."""
    with served_in_process(topology) as (fleet, port):
        with fleet.bus("CAN0").lock:
            for name, spec in fleet.boards.items():
                for board in spec:
                    board.nv.install(OLD.plan())
                    board.nv.record.autostart = True
                    board.power_off()
                    board.power_on(fleet.bus(name).now)
        yield fleet, port


def test_a_deploy_over_fleet_serve_signalled_while_its_boards_erase_puts_them_back(
        tmp_path: Path) -> None:
    """``ucom deploy`` of the head's new image over ``fleet serve`` (without its trees:
    the parameters, in process above, would take the most time here), SIGINT when its
    boards begin to erase: exit 130, the JSON and the line on stderr say per board that
    it was erased; no board is left ProgEnabled or in the transfer; the journal stays."""
    head = tmp_path / "head.toml"
    head.write_text("\n".join(line for line in head_topology(tmp_path).read_text().splitlines()
                              if not line.startswith("tree = ")))
    v2 = tmp_path / "head_v2.toml"
    v2.write_text(head.read_text().replace("firmware_images/armar3.fl.S",
                                           "firmware_images/armar3_fpga1.1.fl.S"))
    with served_running(str(head)) as (fleet, port):
        tap = Signaller(frame(0x2C0, 4), signal.SIGINT)
        fleet.bus("CAN0").attach(tap)  # type: ignore[attr-defined]
        tap.proc = subprocess.Popen(
            [sys.executable, "-m", "ucom_tools", "deploy", str(v2), "-i", "socketcand",
             "--host", "127.0.0.1", "--port", str(port), "-c", "CAN0", "--journal",
             str(tmp_path / "journal"), "--json"],
            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            text=True, env={**os.environ, "COLUMNS": "200"})
        try:
            out, err = tap.proc.communicate(timeout=120)
        finally:
            tap.proc.kill()
        assert tap.fired and tap.proc.returncode == 130, err
        doc = json.loads(out)
        assert doc["interrupted"] == {"how": "cancelled", "signal": "SIGINT",
                                      "step": "programming"}
        assert doc["journal"] == str(tmp_path / "journal")
        assert "deploy cancelled while programming: 3 in their bootloader" in err, err
        with fleet.bus("CAN0").lock:  # type: ignore[attr-defined]
            for row, board in zip(doc["boards"], fleet.boards["CAN0"],  # type: ignore[attr-defined]
                                  strict=True):
                assert row["outcome"] == E and row["after"]["state"] == "bootloader", row
                assert_left(board, E, old=OLD.progid, new=NEW.progid)
