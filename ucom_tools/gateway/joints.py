"""Which axes of a robot are joints, and their CANopen node IDs: from the robot's topology
and attribute trees alone (no running fleet), for ``ucom gateway`` (``man/ucom-gateway.7``).

A board's program is the one whose edges its tree block maps
(:func:`ucom_tools.config.attrtree.match.program_of`); an :class:`AxisModel` says how that
program names the edges of one axis (``MotorA Target`` ...).  A *joint* is an axis whose
Target edge the tree names: its robot-wide (unique) name differs from the generic one
(``MotorA Target ==> Upper Neck Pitch Target`` is a joint, ``MotorC Target ==> MotorC
Target`` an unused motor).  Its name is that unique name without the generic suffix
(`` Target``: "Right Eye"); where several boards give the same name (each LAURON-IV leg
has an "Alpha"), the board's placement goes in front ("Front Left Leg Alpha").

Node IDs: ``canopen_node = { A = 10 }`` in a board's table of the topology gives axis A
its ID; every other joint takes, in topology order (buses as listed, boards in init-chain
order, axes A, B, C), the lowest ID from :data:`FIRST_AUTO_NODE` up that no joint has.

The programs: ``armar3 cascaded PID`` (every edge of one axis, its own Command per axis)
and ``lauron4 leg``, whose edges fit where they exist: position and velocity set points,
joint position and velocity, Upper/Lower Limit, Velocity Limit and Reference Offset per
axis; its mode (``Leg Mode``) is one for the whole leg (:attr:`BoardEdge.shared`) and it
has neither Reset PWM nor a homing per axis (its Reference Run homes the whole leg).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from ucom_tools.config import attrtree
from ucom_tools.config import topology as topology_mod
from ucom_tools.config.attrtree import BoundBoard, TreeEdgeKind
from ucom_tools.config.attrtree.match import program_of
from ucom_tools.config.topology import AXIS_LETTERS, CANOPEN_NODES, Topology
from ucom_tools.edgelists.axes import MODELS, AxisModel, Role
from ucom_tools.edgelists.model import EdgeKind, EdgeSpec, ProgramSpec
from ucom_tools.errors import InputError, TopologyError, TreeError
from ucom_tools.image.formats import load_image

FIRST_AUTO_NODE = 2
"""The lowest node ID given to a joint the topology numbers not: 1 is left to the master
(``bus.yml``'s ``master: node_id: 1``)."""


_EDGE_KIND = {TreeEdgeKind.CI: EdgeKind.CI, TreeEdgeKind.SO: EdgeKind.SO,
              TreeEdgeKind.PAR: EdgeKind.PAR}


@dataclass(frozen=True)
class BoardEdge:
    """One edge of a joint's board: its program's encoding, its tree's names and default."""

    kind: EdgeKind
    index: int
    """Index among the board's edges of its kind (as MCA addresses it)."""
    generic: str
    unique: str
    """The robot-wide name (the tree's unique name)."""
    spec: EdgeSpec
    default: int
    """Raw: the tree's default, else the program's."""
    line: int
    """Line of its mapping in the tree file."""

    @property
    def shared(self) -> bool:
        """True for an edge of the whole board (no axis of its own): LAURON-IV's Leg Mode."""
        return self.spec.axis is None


@dataclass(frozen=True)
class JointBoard:
    """The board a joint is on."""

    bus: str
    position: int
    """0-based, in init-chain order."""
    placement: str
    where: str
    """'CAN0 board 3 (head right)'."""
    prefix: str
    tree: Path
    program: ProgramSpec
    model: AxisModel
    serial: int
    """The topology's ``serial``; 0 when it gives none (the run time knows the real one)."""
    progid: int
    """ProgID of the topology's ``image`` for the board; 0 when it names none."""
    edges: tuple[BoardEdge, ...]
    """Every edge, CI then SO then PAR."""


@dataclass(frozen=True)
class Joint:
    """One axis of the robot that is a joint, and its CANopen node."""

    name: str
    """'Right Eye'."""
    key: str
    """Lower snake case: 'right_eye' (bus.yml key, EDS file name)."""
    node_id: int
    node_given: bool
    """True when the topology's ``canopen_node`` gives it."""
    board: JointBoard
    axis: int
    """0-based axis of its program (A = 0)."""
    roles: tuple[tuple[Role, BoardEdge], ...]

    @property
    def letter(self) -> str:
        return AXIS_LETTERS[self.axis]

    @property
    def bus(self) -> str:
        return self.board.bus

    @property
    def where(self) -> str:
        return self.board.where

    def edge(self, role: Role) -> BoardEdge | None:
        """The edge in ``role``; None when the program has none."""
        for r, e in self.roles:
            if r is role:
                return e
        return None

    def unique(self, role: Role) -> str | None:
        """The robot-wide name of the edge in ``role`` ("Right Eye Target")."""
        e = self.edge(role)
        return None if e is None else e.unique


@dataclass(frozen=True)
class Skipped:
    """A board with a tree whose axes cannot be joints, and why."""

    where: str
    reason: str


@dataclass(frozen=True)
class RobotJoints:
    """The result of :func:`find`."""

    topology: Topology
    joints: tuple[Joint, ...]
    """In topology order."""
    skipped: tuple[Skipped, ...]

    def by_node(self, node_id: int) -> Joint:
        for j in self.joints:
            if j.node_id == node_id:
                return j
        raise KeyError(node_id)


def load(name_or_path: str) -> RobotJoints:
    """The joints of a bundled robot or a topology file."""
    return find(topology_mod.load(name_or_path))


def find(topology: Topology) -> RobotJoints:
    """Every joint of ``topology``'s boards that have a tree.  TreeError for a tree that
    cannot be used, TopologyError for a ``canopen_node`` that names no joint, InputError
    when no joint is found or names collide, ImageError for an image that cannot be read."""
    trees = attrtree.bind_present(topology)
    found: list[tuple[JointBoard, int, str, tuple[tuple[Role, BoardEdge], ...]]] = []
    skipped: list[Skipped] = []
    images: dict[Path, int] = {}
    axes: dict[tuple[str, int], tuple[AxisModel, list[int], Path]] = {}
    for bound in trees.boards:
        spec = program_of(bound.board)
        model = MODELS.get(spec.name) if spec is not None else None
        if spec is None or model is None:
            what = "no program ucom-tools knows" if spec is None else \
                f"'{spec.name}', whose axes ucom-tools cannot drive as joints"
            skipped.append(Skipped(bound.where, f"its tree maps {what}"))
            continue
        board = _board(bound, spec, model, images)
        joint_axes = axes[(bound.bus, bound.spec.position)] = (model, [], bound.file)
        for axis in range(model.axes):
            roles = _roles(board, model, axis)
            target = dict(roles)[Role.TARGET]
            if target.unique != target.generic:
                joint_axes[1].append(axis)
                found.append((board, axis, _name(target.unique, model), roles))
    _check_given(topology, axes, skipped)
    if not found:
        raise InputError(f"no joint found in {topology.name}: no board's tree names the "
                         "Target edge of an axis of a program ucom-tools can drive"
                         + "".join(f"; {s.where}: {s.reason}" for s in skipped),
                         file=topology.source)
    names = _qualified(found)
    nodes = _nodes(topology, found, names)
    joints = tuple(Joint(names[i], snake(names[i]), nodes[i][0], nodes[i][1], board, axis,
                         roles) for i, (board, axis, _, roles) in enumerate(found))
    _unique_keys(topology, joints)
    return RobotJoints(topology, joints, tuple(skipped))


def _board(bound: BoundBoard, spec: ProgramSpec, model: AxisModel,
           images: dict[Path, int]) -> JointBoard:
    counts = dict.fromkeys(EdgeKind, 0)
    edges = []
    for e, es in zip(bound.board.edges, spec.edges, strict=True):
        kind = _EDGE_KIND[e.kind]
        default = es.default
        if e.default is not None:
            try:
                default = es.raw(e.default.text)
            except ValueError as err:
                raise TreeError(f"default of '{e.unique}': {err}", file=str(bound.file),
                                line=e.default_line or e.line) from None
        edges.append(BoardEdge(kind, counts[kind], e.generic, e.unique, es, default, e.line))
        counts[kind] += 1
    progid = 0
    image = bound.spec.image
    if image is not None:
        if image not in images:
            images[image] = load_image(image).progid
        progid = images[image]
    return JointBoard(bound.bus, bound.spec.position, bound.spec.placement, bound.where,
                      bound.board.prefix, bound.file, spec, model,
                      bound.spec.serial if bound.spec.serial_explicit else 0, progid,
                      tuple(edges))


def _roles(board: JointBoard, model: AxisModel, axis: int
           ) -> tuple[tuple[Role, BoardEdge], ...]:
    by_generic = {e.generic: e for e in board.edges}
    out = []
    for role, _ in model.patterns:
        generic = model.generic(role, axis)
        assert generic is not None
        out.append((role, by_generic[generic]))  # the tree maps the program: it is there
    return tuple(out)


def _name(target: str, model: AxisModel) -> str:
    """The joint's name: its Target's unique name without the program's suffix."""
    if target.endswith(model.name_suffix) and len(target) > len(model.name_suffix):
        return target[:-len(model.name_suffix)].strip()
    return target


def _qualified(found: list[tuple[JointBoard, int, str, tuple[tuple[Role, BoardEdge], ...]]]
               ) -> list[str]:
    """Each joint's name, with its board's placement in front where another board has a
    joint of the same name."""
    boards: dict[str, set[str]] = {}
    for board, _, name, _ in found:
        boards.setdefault(name.casefold(), set()).add(board.where)
    return [name if len(boards[name.casefold()]) == 1 else f"{_title(board.placement)} {name}"
            for board, _, name, _ in found]


def _title(text: str) -> str:
    return " ".join(w[:1].upper() + w[1:] for w in text.split())


def snake(name: str) -> str:
    """Lower snake case: 'Right Eye' -> 'right_eye', 'Wheel 1' -> 'wheel_1'."""
    return re.sub(r"[^a-z0-9]+", "_", name.lower()).strip("_")


def _check_given(topology: Topology,
                 axes: dict[tuple[str, int], tuple[AxisModel, list[int], Path]],
                 skipped: list[Skipped]) -> None:
    """TopologyError for a ``canopen_node`` that names an axis that is no joint: of a
    board without a tree or a program with joints, beyond its program's axes, or whose
    Target the tree does not name."""
    why_not = {s.where: s.reason for s in skipped}
    for bus in topology.buses:
        for b in bus.boards:
            where = f"{bus.name} board {b.position + 1} ({b.placement})"
            model, joint_axes, tree = axes.get((bus.name, b.position), (None, [], None))
            for letter, node in b.canopen_nodes:
                axis = AXIS_LETTERS.index(letter)
                if model is None:
                    why = why_not.get(where, "it has no attribute tree (tree = \"FILE\")")
                elif axis >= model.axes:
                    why = (f"'{model.program}' has axes {AXIS_LETTERS[0]}-"
                           f"{AXIS_LETTERS[model.axes - 1]}")
                elif axis not in joint_axes:
                    why = (f"it is no joint: {tree} does not name its Target "
                           f"('{model.generic(Role.TARGET, axis)}' keeps its generic name)")
                else:
                    continue
                raise TopologyError(f"node {node} for axis {letter} of {where}: {why}",
                                    file=topology.source, line=b.canopen_line or None,
                                    key="canopen_node")


def _nodes(topology: Topology,
           found: list[tuple[JointBoard, int, str, tuple[tuple[Role, BoardEdge], ...]]],
           names: list[str]) -> list[tuple[int, bool]]:
    """(node ID, given) per joint: the topology's, else the lowest free one."""
    given: dict[tuple[str, int], dict[int, int]] = {}
    for bus in topology.buses:
        for b in bus.boards:
            given[(bus.name, b.position)] = {AXIS_LETTERS.index(letter): node
                                             for letter, node in b.canopen_nodes}
    taken = {n for nodes in given.values() for n in nodes.values()}
    free = (n for n in range(FIRST_AUTO_NODE, CANOPEN_NODES.stop) if n not in taken)
    out = []
    for (board, axis, _, _), name in zip(found, names, strict=True):
        node = given[(board.bus, board.position)].get(axis)
        if node is not None:
            out.append((node, True))
            continue
        node = next(free, None)
        if node is None:
            raise InputError(f"no node ID left for {name} ({board.where}, axis "
                             f"{AXIS_LETTERS[axis]}): a CANopen bus has IDs up to "
                             f"{CANOPEN_NODES.stop - 1}, and {FIRST_AUTO_NODE - 1} is the "
                             "master's", file=topology.source)
        out.append((node, False))
    return out


def _unique_keys(topology: Topology, joints: tuple[Joint, ...]) -> None:
    """Every joint's bus.yml key (and EDS file name) is its own and not empty."""
    seen: dict[str, Joint] = {}
    for j in joints:
        if not j.key:
            raise InputError(f"joint '{j.name}' ({j.where}, axis {j.letter}) has no letter "
                             "or digit for its bus.yml key: rename its Target in "
                             f"{j.board.tree}", file=topology.source)
        other = seen.get(j.key)
        if other is not None:
            raise InputError(f"joints '{other.name}' ({other.where}) and '{j.name}' "
                             f"({j.where}) have the same bus.yml key '{j.key}': rename one "
                             f"Target in {j.board.tree}", file=topology.source)
        seen[j.key] = j
