"""A robot's live parameters kept across a reflash (``ucom flash --keep-params``): read
from every board that runs a program and dumped into a temporary directory before
(:func:`keep_before`), loaded back and read back after (:func:`keep_after`); what
became of each board's values is a :class:`KeepResult`.
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from ucom_tools.config import attrtree
from ucom_tools.config.attrtree import RobotTrees
from ucom_tools.errors import MissingInput
from ucom_tools.ops.params import BoardRead, Readout, load_values, read_values, select_prefixes
from ucom_tools.ops.params_dump import DumpTarget, write_dump
from ucom_tools.ops.robot import Robot

if TYPE_CHECKING:
    from ucom_tools.config.topology import BoardKey


@dataclass(frozen=True)
class Kept:
    """The values of the running boards, read before a reflash and dumped into
    ``directory`` (a temporary directory) to be loaded back after it."""

    trees: RobotTrees
    readout: Readout
    directory: Path | None
    """None when no board ran a program matching its tree (nothing to keep)."""
    files: tuple[Path, ...] = ()


def keep_before(robot: Robot, *, bus: str | None = None) -> Kept:
    """Read the values of every board of the robot (on ``bus``) that runs a program,
    matched against its tree (the robot's topology binds them), and dump them into a new
    temporary directory.  InputError when the robot has no topology or no trees."""
    if robot.topology is None:
        raise MissingInput("keeping the parameters needs the robot's topology (which tree "
                           "each board has)", key="topology")
    trees = attrtree.bind_present(robot.topology)
    readout = read_values(robot, trees, bus=bus, running_only=True)
    if not readout.read:
        return Kept(trees, readout, None)
    sources = list(dict.fromkeys(str(b.tree) for b in readout.read))
    by_source = {t.source: t for t in trees.trees}
    directory = Path(tempfile.mkdtemp(prefix="ucom-keep-params-"))
    try:
        targets = [DumpTarget(by_source[s], directory / f"{i:02d}-{Path(s).name}")
                   for i, s in enumerate(sources, 1)]
        files = write_dump(readout, targets)
    except BaseException:
        shutil.rmtree(directory, ignore_errors=True)
        raise
    return Kept(trees, readout, directory, tuple(files))


@dataclass(frozen=True)
class KeptBoard:
    """What became of one board's values across the reflash."""

    bus: str
    board: int
    where: str
    prefix: str
    outcome: str
    """kept (loaded back and read back), skipped (nothing to keep: no program ran),
    failed (read before but not loaded back, or not read although it ran a program),
    untouched (the job stopped before programming)."""
    detail: str = ""
    values: int = 0
    changed: int = 0
    """Values that differ from the tree's defaults (what a plain flash would have lost
    to a 'ucom remote' start)."""


@dataclass(frozen=True)
class KeepResult:
    boards: tuple[KeptBoard, ...]
    directory: Path | None
    """The dumped values, left in place when some board did not get them back."""

    @property
    def ok(self) -> bool:
        return all(b.outcome != "failed" for b in self.boards)

    @property
    def failed(self) -> list[KeptBoard]:
        return [b for b in self.boards if b.outcome == "failed"]


def _kept_board(r: BoardRead, outcome: str, detail: str) -> KeptBoard:
    return KeptBoard(r.bus, r.board, r.where, r.prefix, outcome, detail, len(r.values),
                     sum(v.changed for v in r.values))


def keep_refused(kept: Kept) -> KeepResult:
    """The result when the job stops before programming (the values stay on the boards):
    the temporary directory is removed."""
    if kept.directory is not None:
        shutil.rmtree(kept.directory, ignore_errors=True)
    return KeepResult(tuple(
        _kept_board(r, "failed" if r.error else "skipped" if r.skipped else "untouched",
                    r.error or r.skipped or "read; nothing was programmed")
        for r in kept.readout.boards), None)


def keep_after(robot: Robot, kept: Kept, programmed: Mapping[BoardKey, str]) -> KeepResult:
    """Load the kept values back into their boards (each program started if needed).
    ``programmed`` gives the flash outcome of every board of the job by (bus, seq ID);
    a board whose flash failed is not loaded (its values stay in the directory).  The
    temporary directory is removed when every board that was read got its values back;
    otherwise the result names it."""
    out: dict[BoardKey, KeptBoard] = {}
    load: list[BoardRead] = []
    for r in kept.readout.boards:
        key = (r.bus, r.board)
        if r.skipped:
            out[key] = _kept_board(r, "skipped", f"nothing to keep: {r.skipped}")
        elif r.error:
            out[key] = _kept_board(r, "failed", f"not read before programming: {r.error}")
        elif programmed.get(key, "verified") not in ("verified", "refused"):
            out[key] = _kept_board(r, "failed", "not loaded back: programming "
                                   f"{programmed[key]}")
        else:
            load.append(r)
    if load:
        assert kept.directory is not None
        given = attrtree.with_files(kept.trees, kept.files, only=True)
        chosen = select_prefixes(given, (r.prefix for r in load))
        result = load_values(robot, chosen, strict=False)
        by_key = {(b.bus, b.board): b for b in result.boards}
        for r in load:
            b = by_key.get((r.bus, r.board))
            if b is None:
                out[(r.bus, r.board)] = _kept_board(r, "failed", "not loaded back")
            elif b.ok:
                out[(r.bus, r.board)] = _kept_board(r, "kept", f"{b.written} values loaded "
                                                    "back and read back")
            else:
                why = b.error or ", ".join(f"{x.unique} reads {x.read}, not {x.sent}"
                                           for x in b.not_taken)
                out[(r.bus, r.board)] = _kept_board(r, "failed", f"not loaded back: {why}")
    boards = tuple(out[(r.bus, r.board)] for r in kept.readout.boards)
    directory = kept.directory
    lost = [r for r in kept.readout.read if out[(r.bus, r.board)].outcome == "failed"]
    if directory is not None and not lost:  # every value read is back on its board
        shutil.rmtree(directory, ignore_errors=True)
        directory = None
    return KeepResult(boards, directory)
