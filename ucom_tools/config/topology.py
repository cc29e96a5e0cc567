"""Topology files: the buses of a robot and the boards on each, in init-chain order.

TOML, bundled ones are package data (``armar3``, ``lauron4``, ``kairo2``, ``odete``,
``puma200``, ``rosi``).  Every mistake is reported with file, line and key.  A topology
can describe wiring faults: ``init_link = "broken"`` (the init line into this board is
cut), ``powered = false``, and two boards with the same ``fixed_id``; and mutant boards,
``defect = "NAME"``, a documented protocol defect of :mod:`ucom_tools.virtual.board.mutants`
(``fault``, its old name, is still read).
``canopen_node = { A = 10, B = 11 }`` gives axes of a board their CANopen node IDs for
``ucom gateway`` (1..127, unique in the topology; :mod:`ucom_tools.gateway.joints`).
"""

from __future__ import annotations

import difflib
import math
import re
import sys
import tomllib
import zlib
from dataclasses import dataclass, fields, replace
from importlib import resources
from pathlib import Path
from typing import Any, TypeAlias

from ucom_tools import fileio
from ucom_tools.config import mutants
from ucom_tools.edgelists.axes import AXIS_LETTERS
from ucom_tools.errors import TopologyError
from ucom_tools.plugons import PLUG_ON_BOARDS
from ucom_tools.wire.fpga import FpgaVersion

BUNDLED = ("armar3", "lauron4", "kairo2", "odete", "puma200", "rosi")
_PACKAGE_PARENT = Path(__file__).resolve().parents[2]


def bundled_root(source: Path = _PACKAGE_PARENT,
                 prefixes: tuple[str, ...] = (sys.prefix, sys.base_prefix)) -> Path:
    """Where ``attribute_trees/`` and ``firmware_images/`` are: the ``source`` tree of a
    checkout (or an editable install), else ``share/ucom-tools`` of the environment a
    wheel was installed into (pyproject.toml, data-files)."""
    if (source / "attribute_trees").is_dir():
        return source
    for prefix in prefixes:
        shared = Path(prefix) / "share" / "ucom-tools"
        if (shared / "attribute_trees").is_dir():
            return shared
    return source


SOURCE_ROOT = bundled_root()
"""Relative paths in a bundled topology (programs, attribute trees) are relative to this
folder: the ucom-tools source tree (where ``firmware_images/`` and ``attribute_trees/``
are), or where an installed wheel put them."""
IMAGE_FOLDERS = (SOURCE_ROOT, SOURCE_ROOT / "firmware_images")
"""Where an ``image = "..."`` not found beside the topology file is looked for: the
bundled images (``image = "armar3.fl.S"`` or ``"firmware_images/armar3.fl.S"``)."""
MAX_BOARDS = 31
"""Boards one bus can hold: the protocol addresses seq IDs 1-31 (``ucom-protocol(7)``)."""
CANOPEN_NODES = range(1, 128)
"""The node IDs a CANopen device can have (CiA 301)."""
MAX_BUSES = 16
"""Buses one topology can have (ARMAR-III has 4; a PC rarely carries more than 16 CAN
channels): a larger file is a mistake, and each bus costs a thread or a process."""

BoardKey: TypeAlias = tuple[str, int]
"""A board of a robot, as every layer above this one keys it: its bus's name and its seq
ID (its place on that bus's init line, from 1): ``("CAN0", 3)``, written ``CAN0:3`` on the
command line (a fault's target also ``CAN0/3``)."""

BITRATES = (10_000, 20_000, 50_000, 100_000, 125_000, 250_000, 500_000, 800_000, 1_000_000)


@dataclass(frozen=True)
class Timing:
    """Time constants of a virtual board (microseconds), overridable per topology
    (``[timing]``; ``man/ucom-protocol.7``, TIMEOUTS)."""

    reply_us: float = 50.0
    settle_us: float = 100.0
    reset_us: float = 2000.0
    page_erase_us: float = 20000.0
    word_program_us: float = 20.0
    frame_overhead_us: float = 10.0
    extram_frame_us: float = 4.0
    verify_word_us: float = 0.05
    rx_capacity: int = 128
    high_water: int = 96
    low_water: int = 32


@dataclass(frozen=True)
class BoardSpec:
    position: int
    placement: str
    board: str
    fixed_id: int
    serial: int
    flashed: Path | None
    """The image in its flash when the virtual fleet first powers it on (the topology's
    ``program``); None = an empty flash."""
    autostart: bool
    powered: bool
    init_link_broken: bool
    joints: tuple[str, ...]
    line: int
    fpga: FpgaVersion
    """The FPGA configuration (the topology's, or one made for the plug-on board)."""
    serial_explicit: bool = False
    """True when the file gave the serial (so a real robot's boards can be recognised)."""
    tree: Path | None = None
    """The attribute tree file of this board (``man/ucom-tree.5``), if the topology names one."""
    tree_block: int | None = None
    """Which ``DSP{ <n>{ }<n> }DSP`` block of :attr:`tree` is this board's; None = the
    file's only block."""
    defect: str | None = None
    """The documented defect of a mutant board (:mod:`ucom_tools.virtual.board.mutants`); None =
    the board conforms (or takes its fleet's defect)."""
    image: Path | None = None
    """The image this board should run (the manifest ``ucom deploy`` brings the robot to,
    with :attr:`autostart`); None = deploy leaves the board alone."""
    canopen_nodes: tuple[tuple[str, int], ...] = ()
    """``canopen_node``: (axis letter, CANopen node ID) of the axes given one, by letter;
    the gateway numbers the other joints (:mod:`ucom_tools.gateway.joints`)."""
    canopen_line: int = 0
    """Line of ``canopen_node`` in the topology file (0: not given)."""


@dataclass(frozen=True)
class BusSpec:
    name: str
    bitrate: int
    boards: tuple[BoardSpec, ...]


@dataclass(frozen=True)
class Topology:
    name: str
    description: str
    source: str
    buses: tuple[BusSpec, ...]
    timing: Timing

    def bus(self, name: str) -> BusSpec:
        for b in self.buses:
            if b.name == name:
                return b
        raise KeyError(name)

    def with_flashed(self, image: Path, *, autostart: bool = False) -> Topology:
        """The same robot with ``image``'s program already in every board's flash (as a
        robot comes from its last flashing); boards that name their own program keep it."""
        buses = tuple(replace(bus, boards=tuple(
            b if b.flashed is not None else replace(b, flashed=image, autostart=autostart)
            for b in bus.boards)) for bus in self.buses)
        return replace(self, buses=buses)


class _Lines:
    """Finds the line of a key in a TOML file with ``[[bus]]``/``[[bus.board]]`` tables."""

    _HEADER = re.compile(r"^\s*\[\[?\s*([A-Za-z0-9_.]+)\s*\]\]?")
    _KEY = re.compile(r"^\s*([A-Za-z0-9_]+)\s*=")

    def __init__(self, text: str) -> None:
        self.lines: dict[tuple[Any, ...], int] = {}
        path: tuple[Any, ...] = ()
        bus = board = -1
        for no, line in enumerate(text.splitlines(), 1):
            if h := self._HEADER.match(line):
                name = h.group(1)
                if name == "bus":
                    bus, board = bus + 1, -1
                    path = ("bus", bus)
                elif name == "bus.board":
                    board += 1
                    path = ("bus", bus, "board", board)
                else:
                    path = (name,)
                self.lines.setdefault(path, no)
            elif k := self._KEY.match(line):
                self.lines.setdefault((*path, k.group(1)), no)

    def of(self, *path: Any) -> int | None:
        while path:
            if path in self.lines:
                return self.lines[path]
            path = path[:-1]
        return None


class _Checker:
    def __init__(self, source: str, text: str) -> None:
        self.source = source
        self.lines = _Lines(text)

    def fail(self, path: tuple[Any, ...], key: str, message: str) -> TopologyError:
        return TopologyError(message, file=self.source, line=self.lines.of(*path, key),
                             key=_key_name(path, key))

    def take(self, table: dict[str, Any], path: tuple[Any, ...], key: str, kind: type | tuple,
             default: Any = ..., what: str = "") -> Any:
        if key not in table:
            if default is ...:
                raise self.fail(path, key, "missing; " + (what or f"expected {_kind(kind)}"))
            return default
        value = table[key]
        if isinstance(value, bool) and kind is not bool and bool not in _tuple(kind):
            raise self.fail(path, key, f"expected {_kind(kind)}, got {value!r}")
        if not isinstance(value, kind):
            raise self.fail(path, key, f"expected {_kind(kind)}, got {value!r}")
        if isinstance(value, float) and not math.isfinite(value):
            raise self.fail(path, key, f"expected a finite number, got {value!r}")
        return value

    def no_extra(self, table: dict[str, Any], path: tuple[Any, ...], allowed: set[str],
                 old: frozenset[str] = frozenset()) -> None:
        """Every key of ``table`` is ``allowed`` (or an ``old`` name of one, not listed)."""
        for key in table:
            if key not in allowed and key not in old:
                raise self.fail(path, key, "unknown key; allowed: " + ", ".join(sorted(allowed)))


def _tuple(kind: type | tuple) -> tuple:
    return kind if isinstance(kind, tuple) else (kind,)


def _kind(kind: type | tuple) -> str:
    names = {str: "a string", int: "an integer", bool: "true or false", list: "a list",
             dict: "a table", float: "a number"}
    return " or ".join(names.get(k, k.__name__) for k in _tuple(kind))


def _key_name(path: tuple[Any, ...], key: str) -> str:
    parts = []
    i = 0
    while i < len(path):
        if i + 1 < len(path) and isinstance(path[i + 1], int):
            parts.append(f"{path[i]}[{path[i + 1] + 1}]")
            i += 2
        else:
            parts.append(str(path[i]))
            i += 1
    return ".".join([*parts, key])


def resolve(name_or_path: str) -> tuple[str, str]:
    """(source name, text) of a bundled topology name or a topology file path."""
    if name_or_path in BUNDLED:
        res = resources.files("ucom_tools.config") / "topologies" / f"{name_or_path}.toml"
        return name_or_path, res.read_text(encoding="utf-8")
    path = Path(name_or_path)

    def refuse(text: str) -> TopologyError:
        if text == "no such file":
            text = (f"no such topology file{did_you_mean(name_or_path)} (bundled ones: "
                    f"{', '.join(BUNDLED)})")
        return TopologyError(text, file=name_or_path)

    data = fileio.read_input(path, limit=fileio.TEXT_LIMIT, what="a topology file",
                             error=refuse)
    try:
        return str(path), data.decode("utf-8")
    except UnicodeDecodeError as err:
        raise TopologyError(f"cannot read: {err}", file=name_or_path) from None


def did_you_mean(name_or_path: str) -> str:
    """"; did you mean armar3?" for a name close to a bundled topology's (a misspelt
    ``armr3``, ``ARMAR3``, ``armar3.toml``), else ""."""
    stem = Path(name_or_path).stem.lower() if name_or_path else ""
    close = difflib.get_close_matches(stem, BUNDLED, n=1, cutoff=0.6)
    return f"; did you mean {close[0]}?" if close else ""


def load(name_or_path: str) -> Topology:
    source, text = resolve(name_or_path)
    base = SOURCE_ROOT if name_or_path in BUNDLED else Path(name_or_path).parent
    return parse(text, source, base)


def parse(text: str, source: str, base: Path | None = None) -> Topology:
    """Parse and check topology text; raises :class:`TopologyError` naming line and key."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        m = re.search(r"line (\d+)", str(err))
        raise TopologyError(f"not valid TOML: {err}", file=source,
                            line=int(m.group(1)) if m else None) from None
    c = _Checker(source, text)
    c.no_extra(data, (), {"name", "description", "timing", "bus"})
    name = c.take(data, (), "name", str)
    description = c.take(data, (), "description", str, "")
    timing = _timing(c, c.take(data, (), "timing", dict, {}))
    buses_raw = c.take(data, (), "bus", list, what="at least one [[bus]] table")
    if not buses_raw:
        raise c.fail((), "bus", "at least one [[bus]] table is needed")
    if len(buses_raw) > MAX_BUSES:
        raise c.fail((), "bus", f"at most {MAX_BUSES} buses per topology, got "
                     f"{len(buses_raw)}")
    buses = []
    serials: set[int] = set()
    names: set[str] = set()
    placements: dict[str, tuple[str, int]] = {}
    for i, braw in enumerate(buses_raw):
        path = ("bus", i)
        if not isinstance(braw, dict):
            raise c.fail((), "bus", "must be [[bus]] tables")
        c.no_extra(braw, path, {"name", "bitrate", "board"})
        bname = c.take(braw, path, "name", str)
        if bname in names:
            raise c.fail(path, "name", f"bus {bname!r} is defined twice")
        names.add(bname)
        bitrate = c.take(braw, path, "bitrate", int, 1_000_000)
        if bitrate not in BITRATES:
            raise c.fail(path, "bitrate", "expected one of " + ", ".join(map(str, BITRATES)))
        boards_raw = c.take(braw, path, "board", list, [])
        if len(boards_raw) > MAX_BOARDS:
            raise c.fail(path, "board", f"at most {MAX_BOARDS} boards per bus (the seq IDs "
                         f"1-31), got {len(boards_raw)}")
        boards = tuple(_board(c, name, bname, i, j, b, base, serials)
                       for j, b in enumerate(boards_raw))
        for j, b in enumerate(boards):
            first = placements.setdefault(b.placement, (bname, b.position))
            if first != (bname, b.position):
                raise c.fail(("bus", i, "board", j), "placement",
                             f"{b.placement!r} is also the placement of board "
                             f"{first[1] + 1} on {first[0]}; every board needs its own")
        buses.append(BusSpec(bname, bitrate, boards))
    _unique_nodes(c, buses)
    return Topology(name, description, source, tuple(buses), timing)


def _unique_nodes(c: _Checker, buses: list[BusSpec]) -> None:
    """Every ``canopen_node`` ID is given once in the topology."""
    first: dict[int, str] = {}
    for i, bus in enumerate(buses):
        for j, b in enumerate(bus.boards):
            for letter, node in b.canopen_nodes:
                where = f"axis {letter} of {bus.name} board {j + 1} ({b.placement})"
                if node in first:
                    raise c.fail(("bus", i, "board", j), "canopen_node",
                                 f"node {node} of {where} is also {first[node]}'s; every "
                                 "joint needs its own node ID")
                first[node] = where


def _canopen_nodes(c: _Checker, raw: dict[str, Any], path: tuple[Any, ...]
                   ) -> tuple[tuple[str, int], ...]:
    """``canopen_node = { A = 10, C = 12 }``: node IDs 1..127 by axis letter."""
    table = c.take(raw, path, "canopen_node", dict, {})
    out = []
    for letter, node in table.items():
        if len(letter) != 1 or letter not in AXIS_LETTERS:
            raise c.fail(path, "canopen_node", f"{letter!r} is not an axis: expected a "
                         "capital letter (A = the program's first axis, B, C ...), e.g. "
                         "canopen_node = { A = 10, B = 11 }")
        if isinstance(node, bool) or not isinstance(node, int):
            raise c.fail(path, "canopen_node", f"axis {letter}: expected a node ID "
                         f"{CANOPEN_NODES.start}..{CANOPEN_NODES.stop - 1}, got {node!r}")
        if node not in CANOPEN_NODES:
            raise c.fail(path, "canopen_node", f"axis {letter}: node ID must be "
                         f"{CANOPEN_NODES.start}..{CANOPEN_NODES.stop - 1}, got {node}")
        out.append((letter, node))
    return tuple(sorted(out))


def _timing(c: _Checker, raw: dict[str, Any]) -> Timing:
    allowed = {f.name: f for f in fields(Timing)}
    c.no_extra(raw, ("timing",), set(allowed))
    values: dict[str, Any] = {}
    for key in raw:
        want = int if allowed[key].type in ("int", int) else (int, float)
        v = c.take(raw, ("timing",), key, want)
        if v < 0:
            raise c.fail(("timing",), key, "must not be negative")
        values[key] = v
    t = Timing(**values)
    if not 0 < t.low_water < t.high_water <= t.rx_capacity:
        key = next((k for k in ("high_water", "low_water", "rx_capacity") if k in raw),
                   "high_water")
        raise c.fail(("timing",), key, "need 0 < low_water < high_water <= rx_capacity "
                     f"(now {t.low_water}, {t.high_water}, {t.rx_capacity})")
    return t


FPGA_KEYS = {"board_id": 4, "app_id": 7, "major": 6, "minor": 6, "ikl": 2, "ikh": 2}


def _fpga(c: _Checker, path: tuple[Any, ...], raw: dict[str, Any], board_id: int
          ) -> FpgaVersion:
    fpath = (*path, "fpga")
    values = {"board_id": board_id, "app_id": 1, "major": 1, "minor": 0, "ikl": 0, "ikh": 0}
    for key in raw:
        if key not in FPGA_KEYS:
            raise c.fail(path, "fpga", f"unknown key {key!r} in the fpga table; allowed: "
                         + ", ".join(FPGA_KEYS))
        value = c.take(raw, fpath, key, int)
        bits = FPGA_KEYS[key]
        if not 0 <= value < (1 << bits):
            raise c.fail(path, "fpga", f"{key} must be 0..{(1 << bits) - 1}, got {value}")
        values[key] = value
    return FpgaVersion(**values)


def _file(c: _Checker, raw: dict[str, Any], path: tuple[Any, ...], key: str,
          base: Path | None, what: str, fallback: tuple[Path, ...] = ()) -> Path | None:
    """The file a board's ``key`` names (relative to ``base``, else to one of the
    ``fallback`` folders), which must exist."""
    text = c.take(raw, path, key, str, "")
    if not text:
        return None
    given = Path(text)
    file = given
    if not given.is_absolute() and base is not None:
        file = base / given
    if not file.is_file() and not given.is_absolute():
        for folder in fallback:
            if (folder / given).is_file():
                return folder / given
    if not file.is_file():
        raise c.fail(path, key, f"no such {what}: {file}")
    return file


def _board(c: _Checker, topo: str, bus: str, i: int, j: int, raw: Any, base: Path | None,
           serials: set[int]) -> BoardSpec:
    path = ("bus", i, "board", j)
    if not isinstance(raw, dict):
        raise c.fail(path[:2], "board", "must be [[bus.board]] tables")
    c.no_extra(raw, path, {"placement", "board", "fixed_id", "serial", "program", "autostart",
                           "powered", "init_link", "joints", "fpga", "tree", "tree_block",
                           "defect", "image", "canopen_node"}, old=frozenset({"fault"}))
    placement = c.take(raw, path, "placement", str)
    board = c.take(raw, path, "board", str)
    if board not in PLUG_ON_BOARDS:
        raise c.fail(path, "board", f"unknown plug-on board {board!r}; known: "
                     + ", ".join(PLUG_ON_BOARDS))
    fixed_id = c.take(raw, path, "fixed_id", int, 0)
    if not 0 <= fixed_id <= 31:
        raise c.fail(path, "fixed_id", f"must be 1..31 (0 = sequential ID), got {fixed_id}")
    default_serial = zlib.crc32(f"{topo}/{bus}/{j}".encode())
    while default_serial in serials:
        default_serial = (default_serial * 1103515245 + 12345) & 0xFFFFFFFF
    serial = c.take(raw, path, "serial", int, default_serial)
    if not 0 <= serial <= 0xFFFFFFFF:
        raise c.fail(path, "serial", "must be a 32-bit unsigned number")
    if serial in serials:
        raise c.fail(path, "serial", f"0x{serial:08X} is used by another board")
    serials.add(serial)
    flashed = _file(c, raw, path, "program", base, "S-record file")
    image = _file(c, raw, path, "image", base, "firmware image", IMAGE_FOLDERS)
    tree = _file(c, raw, path, "tree", base, "attribute tree file")
    tree_block = c.take(raw, path, "tree_block", int, None)
    if tree_block is not None:
        if not tree:
            raise c.fail(path, "tree_block", "needs 'tree' (the file the block is in)")
        if tree_block < 0:
            raise c.fail(path, "tree_block", f"must be a block number >= 0, got {tree_block}")
    link = c.take(raw, path, "init_link", str, "ok")
    if link not in ("ok", "broken"):
        raise c.fail(path, "init_link", f"expected \"ok\" or \"broken\", got {link!r}")
    joints = c.take(raw, path, "joints", list, [])
    if not all(isinstance(x, str) for x in joints):
        raise c.fail(path, "joints", "expected a list of strings")
    fpga = _fpga(c, path, c.take(raw, path, "fpga", dict, {}), PLUG_ON_BOARDS[board].board_id)
    defect = _defect(c, raw, path)
    nodes = _canopen_nodes(c, raw, path)
    return BoardSpec(
        position=j, fpga=fpga, placement=placement, board=board, fixed_id=fixed_id, serial=serial,
        flashed=flashed, autostart=c.take(raw, path, "autostart", bool, False),
        powered=c.take(raw, path, "powered", bool, True), init_link_broken=link == "broken",
        joints=tuple(joints), line=c.lines.of(*path) or 0, serial_explicit="serial" in raw,
        tree=tree, tree_block=tree_block, defect=defect, image=image, canopen_nodes=nodes,
        canopen_line=(c.lines.of(*path, "canopen_node") or 0) if nodes else 0)


def _defect(c: _Checker, raw: dict[str, Any], path: tuple[Any, ...]) -> str | None:
    """A mutant board's ``defect = "NAME"`` (or ``fault``, its old name); None: it conforms."""
    if "defect" in raw and "fault" in raw:
        raise c.fail(path, "fault", "the old name of 'defect': give one of them")
    key = "fault" if "fault" in raw else "defect"
    defect = c.take(raw, path, key, str, None)
    if defect is not None and defect not in mutants.BY_NAME:
        raise c.fail(path, key, mutants.unknown(defect))
    return defect
