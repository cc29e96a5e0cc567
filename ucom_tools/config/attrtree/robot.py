"""A robot's attribute trees: the boards of a topology bound to their tree blocks.

The binding is stated in the topology (``tree = "..."`` and, for a file with several
blocks, ``tree_block = N`` per board), never guessed from file names.  :func:`check`
loads every tree once and reports every problem (a board without a tree, a block that is
not there or not chosen, a prefix used by two boards); :func:`bind` is the same for code
that needs all trees or nothing.  Robot-wide identity of an edge is (prefix, unique name).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

from ucom_tools.config.attrtree.model import BoardBlock, Edge, Tree
from ucom_tools.config.attrtree.parser import load
from ucom_tools.config.topology import BoardSpec, Topology
from ucom_tools.errors import InputError, TreeError


@dataclass(frozen=True)
class BoundBoard:
    """One board of the topology and its block of the tree."""

    bus: str
    spec: BoardSpec
    file: Path
    board: BoardBlock

    @property
    def where(self) -> str:
        """'CAN0 board 3 (head right)': the board in the words of ``ucom init``."""
        return _where(self.bus, self.spec)


@dataclass(frozen=True)
class RobotTrees:
    """The result of :func:`check`: what could be bound, and every problem found."""

    topology: Topology
    boards: tuple[BoundBoard, ...]
    trees: tuple[Tree, ...]
    """Every tree file the topology names, once each, in topology order."""
    problems: tuple[TreeError, ...]

    @property
    def ok(self) -> bool:
        return not self.problems

    def board(self, bus: str, position: int) -> BoardBlock:
        """The tree block of the board at 0-based ``position`` on ``bus``; KeyError if none."""
        for b in self.boards:
            if b.bus == bus and b.spec.position == position:
                return b.board
        raise KeyError((bus, position))

    def edge(self, prefix: str, unique: str) -> Edge:
        """The edge with this robot-wide identity; KeyError if none."""
        for b in self.boards:
            if b.board.prefix == prefix:
                return b.board.edge(unique)
        raise KeyError((prefix, unique))


def _where(bus: str, board_spec: BoardSpec) -> str:
    return f"{bus} board {board_spec.position + 1} ({board_spec.placement})"


def check(topology: Topology) -> RobotTrees:
    """Load and bind the trees of every board of ``topology``; never raises for a single
    board's problem (they are collected in ``problems``, one per board or file)."""
    bound: list[BoundBoard] = []
    problems: list[TreeError] = []
    trees: dict[Path, Tree | TreeError] = {}
    prefixes: dict[str, BoundBoard] = {}
    for bus in topology.buses:
        for board_spec in bus.boards:
            if board_spec.tree is None:
                problems.append(_fail(topology, board_spec,
                                      f"{_where(bus.name, board_spec)} has no "
                                      "attribute tree (set tree = \"FILE\" in its "
                                      "[[bus.board]] table)"))
                continue
            if board_spec.tree not in trees:
                try:
                    trees[board_spec.tree] = load(board_spec.tree)
                except TreeError as err:
                    trees[board_spec.tree] = err
                    problems.append(err)
            tree = trees[board_spec.tree]
            if isinstance(tree, TreeError):
                continue
            board = _block(tree, board_spec)
            if isinstance(board, str):
                problems.append(_fail(topology, board_spec,
                                      f"{_where(bus.name, board_spec)}: {board}"))
                continue
            b = BoundBoard(bus.name, board_spec, board_spec.tree, board)
            if (other := prefixes.get(board.prefix)) is not None:
                problems.append(TreeError(
                    f"prefix '{board.prefix}' of {b.where} is also {other.where}'s "
                    f"({other.file}): (prefix, unique name) must name an edge robot-wide",
                    file=str(board_spec.tree), line=board.prefix_line, column=board.prefix_column))
                continue
            prefixes[board.prefix] = b
            bound.append(b)
    loaded = tuple(t for t in trees.values() if isinstance(t, Tree))
    return RobotTrees(topology, tuple(bound), loaded, tuple(problems))


def _fail(topology: Topology, board_spec: BoardSpec, message: str) -> TreeError:
    """A problem of a board's binding, at its [[bus.board]] table in the topology."""
    return TreeError(message, file=topology.source, line=board_spec.line or None)


def _block(tree: Tree, board_spec: BoardSpec) -> BoardBlock | str:
    """The board's block of ``tree``, or why there is none."""
    numbers = ", ".join(map(str, tree.numbers))
    if board_spec.tree_block is None:
        if len(tree.boards) != 1:
            return (f"{board_spec.tree} has {len(tree.boards)} board blocks ({numbers}); set "
                    "tree_block to the one of this board")
        return tree.boards[0]
    try:
        return tree.board(board_spec.tree_block)
    except KeyError:
        return (f"tree_block {board_spec.tree_block} is not in {board_spec.tree} "
                f"(its blocks: {numbers})")


def bind(topology: Topology) -> RobotTrees:
    """Like :func:`check`, but raises the first problem: for code that needs every board
    of the robot configured."""
    result = check(topology)
    if result.problems:
        raise result.problems[0]
    return result


def bind_present(topology: Topology) -> RobotTrees:
    """The trees of every board of ``topology`` that names one (boards without a tree
    are not part of the run time); TreeError for a tree that cannot be used, InputError
    when no board has one."""
    with_trees = replace(topology, buses=tuple(
        replace(b, boards=tuple(s for s in b.boards if s.tree is not None))
        for b in topology.buses))
    result = check(with_trees)
    if result.problems:
        raise result.problems[0]
    if not result.boards:
        raise InputError(f"no board of {topology.name} has an attribute tree (set "
                         "tree = \"FILE\" in its [[bus.board]] table)", file=topology.source)
    return replace(result, topology=topology)


def with_files(trees: RobotTrees, files: Sequence[str | Path], *, only: bool = False
               ) -> RobotTrees:
    """``trees`` with the board blocks of tree ``files`` in place of the robot's blocks of
    the same Prefix (the robot's trees say which board has which prefix); ``only``: just
    the boards the files name.  TreeError naming the prefix line for a prefix no board
    has, or one given twice; InputError when ``only`` and the files hold no block."""
    by_prefix = {b.board.prefix: b for b in trees.boards}
    given: dict[str, tuple[BoundBoard, Path]] = {}
    loaded: list[Tree] = []
    for f in files:
        path = Path(f)
        tree = load(path)
        loaded.append(tree)
        for block in tree.boards:
            b = by_prefix.get(block.prefix)
            if b is None:
                raise TreeError(f"no board of {trees.topology.name} has prefix "
                                f"'{block.prefix}' (its prefixes: "
                                f"{', '.join(sorted(by_prefix))})", file=str(path),
                                line=block.prefix_line or None,
                                column=block.prefix_column or None)
            if block.prefix in given:
                raise TreeError(f"prefix '{block.prefix}' is also in "
                                f"{given[block.prefix][1]}: one block per board",
                                file=str(path), line=block.prefix_line or None,
                                column=block.prefix_column or None)
            given[block.prefix] = (replace(b, file=path, board=block), path)
    if only:
        if not given:
            raise InputError("the tree files hold no board block")
        order = [b.board.prefix for b in trees.boards if b.board.prefix in given]
        return replace(trees, boards=tuple(given[p][0] for p in order), trees=tuple(loaded))
    return replace(trees, boards=tuple(given[b.board.prefix][0] if b.board.prefix in given
                                       else b for b in trees.boards))
