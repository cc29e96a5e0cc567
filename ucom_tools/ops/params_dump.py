"""The files ``ucom params dump`` writes: a robot's trees with the live values of its
boards as defaults (:func:`live_tree`), each to the file chosen for it
(:func:`dump_targets`), every file or none (:func:`write_dump`).  The values come from
:func:`ucom_tools.ops.params.read_values`.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

from ucom_tools import fileio
from ucom_tools.config import attrtree
from ucom_tools.config.attrtree import RobotTrees, Tree, Value
from ucom_tools.errors import InputError, OutputExists, UcomError
from ucom_tools.ops.params import BoardRead, Readout, on_bus


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
                                 "to write it", key="bus")
    by_source = {t.source: t for t in trees.trees}
    chosen = [by_source[f] for f in files]
    directory = len(chosen) > 1 or output.is_dir() or str(output).endswith(("/", "\\"))
    if directory and output.exists() and not output.is_dir():
        raise InputError(f"{len(chosen)} tree files are dumped, but {output} is a file: give "
                         "a directory", key="output")
    if not directory and not output.parent.is_dir():
        raise InputError(f"directory {output.parent} does not exist", key="output")
    out: list[DumpTarget] = []
    names: dict[str, Tree] = {}
    for t in chosen:
        name = Path(t.source).name
        if directory and name in names:
            raise InputError(f"{t.source} and {names[name].source} have the same base name; "
                             "dump them one bus at a time or rename one", key="output")
        names[name] = t
        out.append(DumpTarget(t, output / name if directory else output))
    existing = [str(d.path) for d in out if d.path.exists()]
    if existing and not force:
        raise OutputExists(existing, key="output")
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
        fileio.prepare_directory(directory, key="output")
    with fileio.Batch(key="output") as batch:  # every tree or none (ucom(1), FILES)
        for tree, path in rendered:
            batch.write_text(path, attrtree.dumps(tree))
    return [p for _, p in rendered]
