"""What an interrupted flash or deploy leaves: its boards put back, and said per board.

A job ended by Ctrl-C, SIGTERM or SIGHUP (or its cancel event) at any step must leave
every board either with its old program intact (not erased) or in its bootloader with
ProgEnable cleared and no transfer open, and say which (``man/ucom.1``, flash).
:func:`put_back` undoes what a job began on one bus: ABORT broadcast when a transfer may
have begun, SetStatus PROG_ENABLE 0 to every board it ProgEnabled (that too ends a
transfer under way: ``man/ucom-protocol.7``, PROGRAMMING, Abort), then every board's Info
to confirm it, asking again a board that still shows a transfer or ProgEnable.
:func:`judge` turns a board's Info after that into what it was left with.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from ucom_tools.errors import UcomError
from ucom_tools.ops.robot import BusHandle
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import BoardState, StatusOp, Target
from ucom_tools.wire.ids import ALL, seq
from ucom_tools.wire.info import BoardInfo

KEPT = "kept"
"""Its old program is intact (nothing of it was erased), or it had none and has none."""
ERASED = "erased"
"""In its bootloader, no transfer open, ProgEnable cleared; its program erased, or made
invalid by BEGIN before the erase began: no startable program."""
VERIFIED = "verified"
"""The new program verified before the interrupt."""
UNREACHABLE = "unreachable"
"""It did not answer after the interrupt: what it was left with is unknown."""
NOT_UNDONE = "not undone"
"""It answered, but still shows a transfer or ProgEnable."""
OUTCOMES = (KEPT, ERASED, VERIFIED, UNREACHABLE, NOT_UNDONE)

BUSY = (BoardState.ERASING, BoardState.RECEIVING)
RUNNING = (BoardState.RUNNING_FLASH, BoardState.RUNNING_EXTRAM)
ROUNDS = 2
"""A board that still shows a transfer or ProgEnable after the undo (its ABORT or
PROG_ENABLE 0 lost, or an erase page still under way) is sent PROG_ENABLE 0 again and
read again, up to this many times."""


@dataclass(frozen=True)
class Left:
    """What one board was left with: one of :data:`OUTCOMES`, in words, and its Info."""

    outcome: str
    detail: str
    info: BoardInfo | None


def read_infos(h: BusHandle, numbers: Iterable[int]) -> dict[int, BoardInfo]:
    """The Info of the boards ``numbers`` on bus ``h`` (a board that does not answer,
    asked again as Info is, is missing; a bus that fails gives none)."""
    wanted = sorted(set(numbers))
    if not wanted:
        return {}
    try:
        infos = h.client.info_many(ALL, expect=[seq(n) for n in wanted])
    except UcomError:
        return {}
    return {n: infos[seq(n)] for n in wanted if seq(n) in infos}


def _clear(h: BusHandle, n: int, notes: list[str]) -> None:
    try:
        h.client.set_status(seq(n), StatusOp.PROG_ENABLE, 0)
    except UcomError as err:
        notes.append(f"{h.name}: ProgEnable of board {n} could not be cleared: {err}")


def put_back(h: BusHandle, *, abort: bool, enabled: Iterable[int],
             ask: Iterable[int]) -> tuple[dict[int, BoardInfo], list[str]]:
    """Undo on bus ``h``: ABORT broadcast (``abort``: a transfer may have begun), ProgEnable
    cleared on the boards ``enabled``, then the Info of those and of ``ask``.  A board
    that still shows a transfer or ProgEnable is cleared and read again
    (:data:`ROUNDS`).  Returns the Info by seq ID and what could not be sent."""
    notes: list[str] = []
    enabled = sorted(set(enabled))
    if abort:
        try:
            h.link.send(m.ProgramAbort(), ALL)
        except UcomError as err:
            notes.append(f"{h.name}: ABORT could not be sent: {err}")
    for n in enabled:
        _clear(h, n, notes)
    infos = read_infos(h, [*enabled, *ask])
    for _ in range(ROUNDS):
        again = [n for n, info in infos.items() if info.prog_enable or info.state in BUSY]
        if not again:
            break
        for n in again:
            _clear(h, n, notes)
        infos.update(read_infos(h, again))
    return infos, notes


def judge(info: BoardInfo | None, *, old_progid: int | None, new_progid: int,
          verified: bool, target: Target = Target.FLASH) -> Left:
    """What a board was left with, from its Info after :func:`put_back`.  ``old_progid``:
    its flash program's ProgID as found (None: it had none); ``verified``: the job saw it
    verify the new program (``new_progid``) before the interrupt."""
    if info is None:
        return Left(UNREACHABLE, "did not answer after the interrupt (Info asked again): "
                    "what it was left with is unknown, it may still be ProgEnabled or in "
                    "the transfer", None)
    busy = info.state in BUSY
    if busy or info.prog_enable:
        what = " and ".join([info.state.text] * busy + ["ProgEnabled"] * info.prog_enable)
        return Left(NOT_UNDONE, f"still {what} after ABORT and ProgEnable 0", info)
    where = "running it" if info.state in RUNNING else "in its bootloader"
    valid = info.extram_valid if target is Target.EXTRAM else info.flash_valid
    if valid and info.progid == new_progid and (verified or old_progid != new_progid):
        return Left(VERIFIED, f"new program verified (ProgID 0x{new_progid:08X}), {where}",
                    info)
    cleared = "not ProgEnabled, no transfer open"
    if target is Target.EXTRAM:
        return Left(KEPT, f"{where}, {cleared}; its flash untouched (an ExtRAM load erases "
                    "nothing)", info)
    if info.flash_valid:
        if old_progid is not None and info.progid != old_progid:
            return Left(KEPT, f"program ProgID 0x{info.progid:08X} intact (found "
                        f"0x{old_progid:08X}), {where}, {cleared}", info)
        return Left(KEPT, f"old program intact (ProgID 0x{info.progid:08X}, not erased), "
                    f"{where}, {cleared}", info)
    if old_progid is None:
        return Left(KEPT, f"{where}, {cleared}; no program, as found", info)
    return Left(ERASED, f"{where}, {cleared}; its program (ProgID 0x{old_progid:08X}) was "
                "erased or made invalid by the transfer (BEGIN clears its valid flag, then "
                "the erase begins): no startable program until it is flashed again", info)
