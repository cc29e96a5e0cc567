"""A robot's live parameters: every PAR and CI value its boards hold, read back into
attribute trees (``ucom params dump``), written from trees (``ucom params load``), and
kept across a reflash (``ucom flash --keep-params``).

Every board is brought up by :meth:`RemotePart.check <ucom_tools.ops.remote.RemotePart>`
(program started if needed, edges described and compared with the board's tree block):
a board whose edges differ from its tree is read or written not at all.  Values travel
raw (MCA Dump CI / acknowledged MCA writes, ``man/ucom-protocol.7``, RUN TIME) and are
converted exactly with the edge's exponent (:mod:`ucom_tools.ops.edges`).

A dumped tree is the robot's tree in canonical form (:func:`attrtree.dumps
<ucom_tools.config.attrtree.dumps>`) with a default for every PAR and CI edge: the live
value, written as the tree wrote it when that text denotes the same number (``0x444``,
``0.0005``), else as the exact decimal, or as hex for an edge whose name ends in
``(BitMask)``.  Loading such a tree gives every board exactly the values it had.
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from decimal import Decimal, InvalidOperation
from pathlib import Path

from ucom_tools import fileio
from ucom_tools.config import attrtree
from ucom_tools.config.attrtree import BoundBoard, Kind, RobotTrees, Tree, Value
from ucom_tools.config.topology import Topology
from ucom_tools.edgelists.model import EdgeSpec
from ucom_tools.errors import BoardError, InputError, UcomError, UcomTimeoutError
from ucom_tools.ops.edges import spec_of
from ucom_tools.ops.exchange import defaults_raw, write_runs
from ucom_tools.ops.remote import BoardCheck, RemotePart
from ucom_tools.ops.robot import Robot
from ucom_tools.protocol.mca import BoardEdges, McaClient
from ucom_tools.wire import mca
from ucom_tools.wire.codes import BoardState
from ucom_tools.wire.ids import ALL, seq

KINDS = (Kind.CI, Kind.PAR)
"""The kinds a board holds values of that the PC sets (SO values are measurements)."""
_WIRE = {Kind.CI: mca.Kind.CI, Kind.PAR: mca.Kind.PAR}
RUNNING = (BoardState.RUNNING_FLASH, BoardState.RUNNING_EXTRAM)
BITMASK = "(BitMask)"
"""Edges whose name ends so are bit masks: their values are written in hex."""


# ----------------------------------------------------------------------------- robot
def on_bus(trees: RobotTrees, bus: str | None) -> RobotTrees:
    """The boards of ``trees`` on ``bus`` (all when None); InputError when none is."""
    if bus is None:
        return trees
    boards = tuple(b for b in trees.boards if b.bus == bus)
    if not boards:
        have = sorted({b.bus for b in trees.boards})
        raise InputError(f"no board of {trees.topology.name} with an attribute tree is on "
                         f"bus {bus!r} (buses with trees: {', '.join(have)})", key="--bus")
    return replace(trees, boards=boards)


def _part_of(robot: Robot, trees: RobotTrees) -> Robot:
    """The buses of ``robot`` that ``trees`` has boards on, each expecting the boards of
    the trees' topology (placements, positions); InputError for a bus the connection
    does not have."""
    topology = trees.topology
    buses = {}
    for name in dict.fromkeys(b.bus for b in trees.boards):
        h = robot.buses.get(name)
        if h is None:
            have = ", ".join(robot.buses) or "none"
            every = ", ".join(dict.fromkeys(b.bus for b in trees.boards))
            hint = (f": give a channel for each of its buses ({every}), or --bus "
                    f"{next(iter(robot.buses))} for that bus alone" if robot.buses else "")
            raise InputError(f"{topology.name} ({topology.source}) has boards on bus "
                             f"{name}; the connection has {have}{hint}", key="--bus")
        buses[name] = replace(h, expected=topology.bus(name))
    return replace(robot, buses=buses, topology=topology)


def running(robot: Robot, trees: RobotTrees) -> tuple[set[tuple[str, int]], dict[
        tuple[str, int], str]]:
    """Which boards of ``trees`` run a program now (init chain and Info, nothing
    started): (bus, seq ID) of those, and why each other board does not count."""
    part = _part_of(robot, trees)
    found: set[tuple[str, int]] = set()
    why: dict[tuple[str, int], str] = {}
    for name, h in part.buses.items():
        init = h.client.init_chain()
        infos = h.client.info_many(ALL, expect=[seq(n) for n in init.numbers])
        states = {a.number: inf.state for a, inf in infos.items()}
        for b in trees.boards:
            if b.bus != name:
                continue
            n = b.spec.position + 1
            if n not in init.numbers:
                why[(name, n)] = "did not answer the init chain"
            elif n not in states:
                why[(name, n)] = "its Info did not arrive"
            elif states[n] not in RUNNING:
                why[(name, n)] = f"runs no program ({states[n].text})"
            else:
                found.add((name, n))
    return found, why


# ----------------------------------------------------------------------------- values
def value_text(raw: int, spec: EdgeSpec, original: Value | None = None) -> str:
    """How a dumped tree writes ``raw``: the original text when it denotes the same raw
    number, else hex for a bit mask, else the exact decimal (no exponent, no trailing
    zeros)."""
    if original is not None:
        try:
            if spec.raw(original.text) == raw:
                return original.text
        except (ValueError, InvalidOperation):
            pass
    if spec.name.endswith(BITMASK) and spec.exponent == 0:
        return f"-0x{-raw:X}" if raw < 0 else f"0x{raw:X}"
    return format(spec.value(raw).normalize(), "f")


@dataclass(frozen=True)
class EdgeValue:
    """One PAR or CI value a board holds."""

    kind: Kind
    index: int
    """The tree index (counting CI, SO, PAR)."""
    generic: str
    unique: str
    raw: int
    text: str
    """As a dumped tree writes it."""
    unit: str
    default: str | None
    """The default of the board's tree (None: it has none)."""

    @property
    def value(self) -> Decimal:
        return Decimal(int(self.text, 16) if "0x" in self.text else self.text)

    @property
    def changed(self) -> bool:
        """The board holds another value than its tree's default (or the tree has none)."""
        return self.default != self.text


@dataclass(frozen=True)
class BoardRead:
    """One board: its values, or why they could not be read."""

    bus: str
    board: int
    """Seq ID."""
    where: str
    placement: str
    prefix: str
    tree: Path
    block: int
    values: tuple[EdgeValue, ...] = ()
    error: str = ""
    """Why the values could not be read (the first difference from its tree, no answer)."""
    line: int = 0
    """The tree line of the first difference (0: none, or the file as a whole)."""
    skipped: str = ""
    """Why the board was not read at all (``running_only``: it runs no program)."""

    @property
    def ok(self) -> bool:
        return not self.error and not self.skipped

    @property
    def at(self) -> str:
        """``FILE:LINE`` of the first difference ("" when the tree is not at fault)."""
        return f"{self.tree}:{self.line}" if self.line else ""


@dataclass(frozen=True)
class Readout:
    topology: Topology
    boards: tuple[BoardRead, ...]

    @property
    def ok(self) -> bool:
        """Every board that was to be read was read."""
        return all(not b.error for b in self.boards)

    @property
    def read(self) -> list[BoardRead]:
        return [b for b in self.boards if b.ok]

    @property
    def failed(self) -> list[BoardRead]:
        return [b for b in self.boards if b.error]


def _first_difference(check: BoardCheck) -> tuple[str, int]:
    """Why a board failed its check (without the board's name), and the tree line."""
    if check.error:
        error = check.error
        return error.removeprefix(f"{check.where}: "), 0
    first = check.differences[0]
    n = len(check.differences)
    return (f"its program's edges differ from its tree ({n} difference{'s' * (n != 1)}), "
            f"first: {first.message}"), first.line


def _board_read(b: BoundBoard, check: BoardCheck) -> BoardRead:
    return BoardRead(check.bus, check.board, check.where, b.spec.placement, b.board.prefix,
                     b.file, b.board.number)


def _dump_kind(client: McaClient, n: int, edges: BoardEdges, kind: mca.Kind) -> list[int]:
    records = edges.of(kind)
    return client.dump(seq(n), kind, 0, len(records), records) if records else []


def _values(b: BoundBoard, edges: BoardEdges, raws: Mapping[mca.Kind, Sequence[int]],
            ) -> tuple[EdgeValue, ...]:
    first = {k: sum(len(edges.of(j)) for j in mca.Kind if j < k) for k in mca.Kind}
    out = []
    for e in b.board.edges:
        if e.kind not in KINDS:
            continue
        kind = _WIRE[e.kind]
        i = e.index - first[kind]
        record = edges.of(kind)[i]
        spec = spec_of(kind, record)
        raw = raws[kind][i]
        out.append(EdgeValue(e.kind, e.index, e.generic, e.unique, raw,
                             value_text(raw, spec, e.default), record.unit,
                             e.default.text if e.default else None))
    return tuple(out)


def read_values(robot: Robot, trees: RobotTrees, *, bus: str | None = None,
                running_only: bool = False) -> Readout:
    """Every PAR and CI value of the boards of ``trees`` (on ``bus``): each board's
    program started if needed (``running_only``: boards that run none are skipped, as
    they hold no values of their own), described and checked against its tree, then read
    back.  A board that fails does not stop the others."""
    trees = on_bus(trees, bus)
    bound = {(b.bus, b.spec.position + 1): b for b in trees.boards}
    skipped: dict[tuple[str, int], str] = {}
    if running_only:
        found, skipped = running(robot, trees)
        trees = replace(trees, boards=tuple(b for b in trees.boards
                                            if (b.bus, b.spec.position + 1) in found))
    reads: dict[tuple[str, int], BoardRead] = {}
    for key, why in skipped.items():
        b = bound[key]
        reads[key] = BoardRead(b.bus, key[1], b.where, b.spec.placement, b.board.prefix,
                               b.file, b.board.number, skipped=why)
    if trees.boards:
        with RemotePart(_part_of(robot, trees), trees) as part:
            for check in part.check().boards:
                key = (check.bus, check.board)
                b = bound[key]
                base = _board_read(b, check)
                edges = part.described(check.bus, check.board)
                if not check.ok or edges is None:
                    error, line = _first_difference(check)
                    reads[key] = replace(base, error=error, line=line)
                    continue
                client = part.exchanges[check.bus].mca
                try:
                    raws = {k: _dump_kind(client, check.board, edges, k)
                            for k in (mca.Kind.CI, mca.Kind.PAR)}
                except (BoardError, UcomTimeoutError) as err:
                    reads[key] = replace(base, error=f"read-back failed: {err}")
                    continue
                reads[key] = replace(base, values=_values(b, edges, raws))
    order = list(bound)
    return Readout(trees.topology, tuple(reads[k] for k in order if k in reads))


# ----------------------------------------------------------------------------- dump files
def live_tree(tree: Tree, reads: Iterable[BoardRead]) -> Tree:
    """``tree`` with a default for every PAR and CI edge of each block that was read: the
    value the board holds (blocks not read keep their defaults)."""
    by_block = {r.block: r for r in reads if r.ok and Path(r.tree) == Path(tree.source)}
    boards = []
    for b in tree.boards:
        read = by_block.get(b.number)
        if read is None:
            boards.append(b)
            continue
        texts = {v.unique: v.text for v in read.values}
        boards.append(replace(b, edges=tuple(
            replace(e, default=Value.parse(texts[e.unique])) if e.unique in texts else e
            for e in b.edges)))
    return replace(tree, boards=tuple(boards))


@dataclass(frozen=True)
class DumpTarget:
    """Where a dump writes one tree file of the robot."""

    tree: Tree
    path: Path


def dump_targets(trees: RobotTrees, output: Path, *, force: bool = False,
                 bus: str | None = None) -> list[DumpTarget]:
    """The file each tree of the robot (of the boards on ``bus``) is dumped to: ``output``
    itself when there is one tree file (or ``output``/its base name when ``output`` is a
    directory), else ``output``/base name of each.  InputError, before anything is read,
    for a file that exists (unless ``force``), a directory that is not one, two trees
    with one base name, or a tree file that also holds boards of another bus."""
    selected = on_bus(trees, bus)
    files = list(dict.fromkeys(str(b.file) for b in selected.boards))
    if bus is not None:
        for b in trees.boards:
            if b.bus != bus and str(b.file) in files:
                raise InputError(f"{b.file} also holds the block of {b.where}; dump every bus "
                                 "(without --bus) to write it", key="--bus")
    by_source = {t.source: t for t in trees.trees}
    chosen = [by_source[f] for f in files]
    directory = len(chosen) > 1 or output.is_dir() or str(output).endswith(("/", "\\"))
    if directory and output.exists() and not output.is_dir():
        raise InputError(f"{len(chosen)} tree files are dumped, but {output} is a file: give "
                         "a directory", key="-o")
    if not directory and not output.parent.is_dir():
        raise InputError(f"directory {output.parent} does not exist", key="-o")
    out: list[DumpTarget] = []
    names: dict[str, Tree] = {}
    for t in chosen:
        name = Path(t.source).name
        if directory and name in names:
            raise InputError(f"{t.source} and {names[name].source} have the same base name; "
                             "dump them separately (--bus) or rename one", key="-o")
        names[name] = t
        out.append(DumpTarget(t, output / name if directory else output))
    existing = [str(d.path) for d in out if d.path.exists()]
    if existing and not force:
        raise InputError(f"{', '.join(existing)} exist{'s' * (len(existing) == 1)}; "
                         "--force replaces them", key="-o")
    return out


def write_dump(readout: Readout, targets: Sequence[DumpTarget]) -> list[Path]:
    """Write the live trees: each one rendered and checked first (it must read back as
    the same values), then all staged beside their targets and renamed into place: every
    file or none (a full disk leaves the old files as they were)."""
    rendered: list[tuple[Tree, Path]] = []
    for d in targets:
        tree = live_tree(d.tree, readout.read)
        again = attrtree.parse(attrtree.dumps(tree), str(d.path))
        if again != tree:  # cannot happen with a valid tree; never write what does not
            raise UcomError(f"{d.path}: the dumped tree does not read back as written")
        rendered.append((tree, d.path))
    for directory in sorted({p.parent for _, p in rendered}):
        fileio.prepare_directory(directory, option="-o")
    with fileio.Batch(option="-o") as batch:  # every tree or none (ucom(1), FILES)
        for tree, path in rendered:
            batch.write_text(path, attrtree.dumps(tree))
    return [p for _, p in rendered]


# ----------------------------------------------------------------------------- load
def select_prefixes(trees: RobotTrees, prefixes: Iterable[str]) -> RobotTrees:
    """Only the boards of ``trees`` with these prefixes."""
    wanted = set(prefixes)
    return replace(trees, boards=tuple(b for b in trees.boards if b.board.prefix in wanted))


@dataclass(frozen=True)
class NotTaken:
    """A value a board does not hold after it was written and acknowledged."""

    unique: str
    sent: int
    read: int


@dataclass(frozen=True)
class BoardLoad:
    bus: str
    board: int
    where: str
    placement: str
    prefix: str
    tree: Path
    block: int
    written: int = 0
    """Values written (and acknowledged)."""
    not_taken: tuple[NotTaken, ...] = ()
    error: str = ""
    line: int = 0
    held: str = ""
    """Why nothing was written although the board is fine (another board failed)."""

    @property
    def ok(self) -> bool:
        return not self.error and not self.not_taken and not self.held

    @property
    def at(self) -> str:
        """``FILE:LINE`` of the first difference or the value ("" when the tree is not
        at fault)."""
        return f"{self.tree}:{self.line}" if self.line else ""


@dataclass(frozen=True)
class LoadResult:
    topology: Topology
    boards: tuple[BoardLoad, ...]
    sent: bool = field(default=False)
    """Something was written (False: a check failed first, every board is unchanged)."""

    @property
    def ok(self) -> bool:
        return bool(self.boards) and all(b.ok for b in self.boards)

    @property
    def failed(self) -> list[BoardLoad]:
        return [b for b in self.boards if b.error or b.not_taken]


def load_values(robot: Robot, trees: RobotTrees, *, bus: str | None = None,
                strict: bool = True) -> LoadResult:
    """Write the PAR and CI defaults of ``trees`` to their boards, acknowledged, then
    read them back.  Every board is checked first (program started if needed, edges
    compared with its block) and every value converted for its edge.

    ``strict`` (``ucom params load``): a board that fails the check leaves every board
    unchanged (the result says why), and a value its edge cannot carry raises
    InputError naming its file and line before anything is written.  Otherwise
    (``flash --keep-params``) each board that passes is written, whatever the others."""
    trees = on_bus(trees, bus)
    bound = {(b.bus, b.spec.position + 1): b for b in trees.boards}
    loads: dict[tuple[str, int], BoardLoad] = {}
    sent = False
    with RemotePart(_part_of(robot, trees), trees) as part:
        checks = part.check().boards
        plans: dict[tuple[str, int], list[tuple[mca.Kind, int, int, str]]] = {}
        for check in checks:
            key = (check.bus, check.board)
            b = bound[key]
            base = BoardLoad(check.bus, check.board, check.where, b.spec.placement,
                             b.board.prefix, b.file, b.board.number)
            edges = part.described(check.bus, check.board)
            if not check.ok or edges is None:
                error, line = _first_difference(check)
                loads[key] = replace(base, error=error, line=line)
                continue
            loads[key] = base
            try:
                plans[key] = defaults_raw(b.board, edges, check.where, str(b.file))
            except InputError as err:
                if strict:
                    raise
                loads[key] = replace(base, error=err.reason, line=err.line or 0)
        if strict and any(x.error for x in loads.values()):
            for key in plans:
                loads[key] = replace(loads[key], held="not written: another board failed "
                                     "its check")
            plans = {}
        for key, values in plans.items():
            name, n = key
            client = part.exchanges[name].mca
            edges = part.described(name, n)
            assert edges is not None
            try:
                for kind in (mca.Kind.PAR, mca.Kind.CI):
                    runs = [(i, raw) for k, i, raw, _ in values if k is kind]
                    if runs:
                        sent = True
                        write_runs(client, seq(n), kind, runs, edges.of(kind))
                back = {k: _dump_kind(client, n, edges, k) for k in (mca.Kind.CI, mca.Kind.PAR)}
            except (BoardError, UcomTimeoutError) as err:
                loads[key] = replace(loads[key], error=f"writing failed: {err}")
                continue
            missed = tuple(NotTaken(unique, raw, back[k][i]) for k, i, raw, unique in values
                           if back[k][i] != raw)
            loads[key] = replace(loads[key], written=len(values), not_taken=missed)
    return LoadResult(trees.topology, tuple(loads[k] for k in bound if k in loads), sent)


# ----------------------------------------------------------------------------- keep
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
        raise InputError("--keep-params needs the robot's topology (which tree each board "
                         "has): give --topology FILE or --virtual NAME", key="--keep-params")
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


def keep_after(robot: Robot, kept: Kept, programmed: Mapping[tuple[str, int], str]) -> KeepResult:
    """Load the kept values back into their boards (each program started if needed).
    ``programmed`` gives the flash outcome of every board of the job by (bus, seq ID);
    a board whose flash failed is not loaded (its values stay in the directory).  The
    temporary directory is removed when every board that was read got its values back;
    otherwise the result names it."""
    out: dict[tuple[str, int], KeptBoard] = {}
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
