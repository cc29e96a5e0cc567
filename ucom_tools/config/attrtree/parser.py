"""Reading attribute trees: :func:`load` a file, :func:`parse` its bytes or text.

The grammar and every rule are in ``man/ucom-tree.5``.  The first error ends the parse with
a :class:`~ucom_tools.errors.TreeError` naming ``FILE:LINE:COL`` of the offending token
(1-based, columns count characters; line 0 = the file as a whole).  A line is classified
by its first and last non-blank characters: ``#`` comment, ``}`` close, ``...{`` (with no
``:`` before it) open, anything else is a content line whose meaning depends on the block
it is in.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import NoReturn

from ucom_tools import fileio
from ucom_tools.config.attrtree.model import KIND_ORDER, BoardBlock, Edge, Tree, TreeEdgeKind, Value
from ucom_tools.errors import TreeError

BLANKS = " \t"
_CONTROL = re.compile(r"[\x00-\x08\x0b-\x1f\x7f]")
_MARKERS = {k.value: k for k in TreeEdgeKind}
_NAME_FORBIDDEN = re.compile(r"[:{}]")


def _start(s: str, pos: int) -> int:
    """Offset of the first non-blank character of ``s`` at or after ``pos``."""
    return len(s) - len(s[pos:].lstrip(BLANKS)) if pos < len(s) else pos


class _Block(Enum):
    ROOT = "the top level"
    DSP = "DSP"
    BOARD = "a board block"
    MAPPING = "MappingTable"
    PARAMETER = "Parameter"
    CONTROLLER_INPUT = "ControllerInput"


_DEFAULTS_OF = {_Block.PARAMETER: TreeEdgeKind.PAR, _Block.CONTROLLER_INPUT: TreeEdgeKind.CI}
_SECTIONS = {"MappingTable": _Block.MAPPING, "Parameter": _Block.PARAMETER,
             "ControllerInput": _Block.CONTROLLER_INPUT}


@dataclass
class _Open:
    """An open block on the stack."""

    kind: _Block
    name: str
    line: int
    column: int


@dataclass
class _BoardDraft:
    """A board block being read."""

    number: int
    line: int
    column: int
    prefix: str | None = None
    prefix_at: tuple[int, int] = (0, 0)
    edges: list[Edge] = field(default_factory=list)
    by_unique: dict[str, int] = field(default_factory=dict)
    by_generic: dict[str, int] = field(default_factory=dict)
    kind: TreeEdgeKind | None = None
    markers: dict[TreeEdgeKind, int] = field(default_factory=dict)
    sections: dict[_Block, int] = field(default_factory=dict)
    defaults: dict[int, tuple[Value, int]] = field(default_factory=dict)


def load(path: str | Path) -> Tree:
    """Read and check the attribute tree file at ``path``."""
    name = str(path)
    data = fileio.read_input(path, limit=fileio.TEXT_LIMIT, what="an attribute tree file",
                             error=lambda text: TreeError(
                                 "no such attribute tree file" if text == "no such file"
                                 else text, file=name))
    return parse(data, name)


def parse(data: bytes | str, source: str = "<tree>") -> Tree:
    """Parse and check an attribute tree; raises TreeError at the first mistake."""
    return _Parser(source).run(_decode(data, source))


def _decode(data: bytes | str, source: str) -> str:
    if isinstance(data, bytes):
        nul = data.find(b"\0")
        if nul >= 0:
            raise TreeError(f"NUL byte at byte offset {nul}: not a text file", file=source,
                            line=1, column=1)
        try:
            text = data.decode("utf-8")
        except UnicodeDecodeError as err:
            raise TreeError(f"not UTF-8: byte 0x{data[err.start]:02x} at byte offset "
                            f"{err.start}", file=source, line=1, column=1) from None
    else:
        text = data
        nul = text.find("\0")
        if nul >= 0:
            raise TreeError(f"NUL character at offset {nul}: not a text file", file=source,
                            line=1, column=1)
    text = text.removeprefix("\ufeff").replace("\r\n", "\n")
    if m := _CONTROL.search(text):
        line = text.count("\n", 0, m.start()) + 1
        column = m.start() - (text.rfind("\n", 0, m.start()) + 1) + 1
        what = "a carriage return without a line feed" if m.group() == "\r" else \
            f"control character U+{ord(m.group()):04X}"
        raise TreeError(f"{what} (lines end with LF or CR LF; no other control characters "
                        "than tab)", file=source, line=line, column=column)
    return text


class _Parser:
    def __init__(self, source: str) -> None:
        self.source = source
        self.stack: list[_Open] = [_Open(_Block.ROOT, "", 0, 0)]
        self.boards: list[BoardBlock] = []
        self.numbers: dict[int, int] = {}
        self.prefixes: dict[str, int] = {}
        self.board: _BoardDraft | None = None
        self.dsp_seen = False
        self.no = 0

    def fail(self, message: str, column: int, line: int | None = None) -> TreeError:
        return TreeError(message, file=self.source, line=self.no if line is None else line,
                         column=column)

    def run(self, text: str) -> Tree:
        for self.no, raw in enumerate(text.split("\n"), 1):
            s = raw.strip(BLANKS)
            if not s:
                continue
            col = len(raw) - len(raw.lstrip(BLANKS)) + 1
            first = s[0]
            if first == "#":
                if self.stack[-1].kind is _Block.MAPPING:
                    self.marker(s, col)
            elif first == "}":
                self.close(s, col)
            elif s[-1] == "{" and not _NAME_FORBIDDEN.search(s, 0, len(s) - 1):
                self.open(s[:-1].rstrip(BLANKS), col)
            else:
                self.content(s, col)
        top = self.stack[-1]
        if top.kind is not _Block.ROOT:
            raise self.fail(f"block '{top.name}' is never closed: expected '}}{top.name}' "
                            "before the end of the file", top.column, top.line)
        if not self.dsp_seen:
            raise TreeError("empty attribute tree: no 'DSP{' block", file=self.source,
                            line=0, column=0)
        return Tree(tuple(self.boards), self.source)

    # ------------------------------------------------------------------ blocks
    def open(self, name: str, col: int) -> None:
        where = self.stack[-1]
        if not name:
            raise self.fail("'{' without a block name", col)
        kind: _Block
        if where.kind is _Block.ROOT:
            if name != "DSP":
                raise self.fail(f"expected 'DSP{{' at the top level, got '{name}{{'", col)
            if self.dsp_seen:
                raise self.fail("a second DSP block (a file has one; put every board into "
                                "it)", col)
            self.dsp_seen = True
            kind = _Block.DSP
        elif where.kind is _Block.DSP:
            self.open_board(name, col)
            kind = _Block.BOARD
        elif where.kind is _Block.BOARD:
            kind = self.open_section(name, col)
        else:
            raise self.fail(f"'{name}{{' opens a block inside {where.name} (opened at line "
                            f"{where.line}); is '}}{where.name}' missing?", col)
        self.stack.append(_Open(kind, name, self.no, col))

    def open_board(self, name: str, col: int) -> None:
        if not (name.isascii() and name.isdigit()):
            raise self.fail("a board block is named by its number: expected '<n>{' with n = "
                            f"0, 1, 2 ..., got '{name}{{'", col)
        number = int(name)
        if number in self.numbers:
            raise self.fail(f"board number {number} is used twice (first at line "
                            f"{self.numbers[number]}); blocks are never merged", col)
        self.numbers[number] = self.no
        self.board = _BoardDraft(number, self.no, col)

    def open_section(self, name: str, col: int) -> _Block:
        board = self.board
        assert board is not None
        kind = _SECTIONS.get(name)
        if kind is None:
            raise self.fail(f"unknown block '{name}' in board {board.number}; expected "
                            "MappingTable, Parameter or ControllerInput", col)
        if kind in board.sections:
            raise self.fail(f"a second {name} block in board {board.number} (first at line "
                            f"{board.sections[kind]})", col)
        if kind is not _Block.MAPPING and _Block.MAPPING not in board.sections:
            raise self.fail(f"{name} before MappingTable in board {board.number}: defaults "
                            "name unique names of the MappingTable, so it comes first", col)
        board.sections[kind] = self.no
        return kind

    def close(self, s: str, col: int) -> None:
        name = s[1:].lstrip(BLANKS)
        top = self.stack[-1]
        if top.kind is _Block.ROOT:
            raise self.fail(f"'}}{name}' closes no open block", col)
        if name != top.name:
            if not name:
                raise self.fail(f"'}}' without a name: expected '}}{top.name}'", col)
            raise self.fail(f"'}}{name}' does not close the innermost open block "
                            f"'{top.name}' (opened at line {top.line}); expected "
                            f"'}}{top.name}'", col)
        if top.kind is _Block.BOARD:
            self.close_board()
        elif top.kind is _Block.MAPPING and self.board is not None and not self.board.edges:
            raise self.fail(f"MappingTable of board {self.board.number} has no edge",
                            top.column, top.line)
        elif top.kind is _Block.DSP and not self.boards:
            raise self.fail("DSP has no board block '<n>{ ... }<n>'", top.column, top.line)
        self.stack.pop()

    def close_board(self) -> None:
        d = self.board
        assert d is not None
        if d.prefix is None:
            raise self.fail(f"board {d.number} has no 'Prefix : <name>' line", d.column,
                            d.line)
        if _Block.MAPPING not in d.sections:
            raise self.fail(f"board {d.number} has no MappingTable", d.column, d.line)
        edges = tuple(e if (dv := d.defaults.get(e.index)) is None else
                      Edge(e.index, e.kind, e.generic, e.unique, dv[0], e.line, dv[1])
                      for e in d.edges)
        self.boards.append(BoardBlock(d.number, d.prefix, edges, d.line, d.column, *d.prefix_at))
        self.board = None

    # ------------------------------------------------------------------ lines
    def content(self, s: str, col: int) -> None:
        kind = self.stack[-1].kind
        if kind is _Block.MAPPING:
            self.mapping(s, col)
        elif kind in _DEFAULTS_OF:
            self.default(s, col, _DEFAULTS_OF[kind])
        elif kind is _Block.BOARD:
            self.prefix(s, col)
        elif kind is _Block.DSP:
            raise self.fail("expected a board block '<n>{' (n = 0, 1, 2 ...) inside DSP", col)
        else:
            raise self.fail("expected 'DSP{' at the top level", col)

    def prefix(self, s: str, col: int) -> None:
        d = self.board
        assert d is not None
        colon = s.find(":")
        key = s[:colon].rstrip(BLANKS) if colon >= 0 else s
        if key != "Prefix":
            raise self.fail(f"unexpected line in board {d.number}: expected 'Prefix : <name>' "
                            "or a MappingTable, Parameter or ControllerInput block", col)
        if colon < 0:
            raise self.fail("expected 'Prefix : <name>'", col)
        if d.prefix is not None:
            raise self.fail(f"a second Prefix in board {d.number} (first at line "
                            f"{d.prefix_at[0]})", col)
        rest = s[colon + 1:]
        value = rest.strip(BLANKS)
        vcol = col + colon + 1 + (len(rest) - len(rest.lstrip(BLANKS)))
        if not value:
            raise self.fail("Prefix without a name", vcol)
        self.check_name(value, vcol)
        if value in self.prefixes:
            raise self.fail(f"prefix '{value}' is also board {self.prefixes[value]}'s: "
                            "(prefix, unique name) must name an edge robot-wide", vcol)
        self.prefixes[value] = d.number
        d.prefix, d.prefix_at = value, (self.no, vcol)

    def marker(self, s: str, col: int) -> None:
        kind = _MARKERS.get(s[1:].strip(BLANKS))
        d = self.board
        if kind is None or d is None:
            return
        if kind in d.markers:
            raise self.fail(f"a second '# {kind}' marker (first at line {d.markers[kind]})",
                            col)
        if d.kind is not None and KIND_ORDER.index(kind) < KIND_ORDER.index(d.kind):
            raise self.fail(f"'# {kind}' after '# {d.kind}': kind markers come in the order "
                            "# CI, # SO, # PAR", col)
        d.markers[kind] = self.no
        d.kind = kind

    def mapping(self, s: str, col: int) -> None:
        d = self.board
        assert d is not None
        colon = s.find(":")
        arrow = s.find("==>", colon + 1) if colon > 0 else -1
        index_text = s[:colon].rstrip(BLANKS)
        if (arrow < 0 or not (index_text.isascii() and index_text.isdigit())
                or _NAME_FORBIDDEN.search(s, colon + 1) or s.find("==>", arrow + 3) >= 0):
            self.bad_mapping(s, col)
        generic = s[colon + 1:arrow].strip(BLANKS)
        unique = s[arrow + 3:].strip(BLANKS)
        if not generic or not unique or generic[0] == "#" or unique[0] == "#":
            self.bad_mapping(s, col)
        index = int(index_text)
        expected = len(d.edges)
        if index != expected:
            raise self.fail(f"index {index} out of sequence, expected {expected}", col)
        if d.kind is None:
            raise self.fail(f"edge {index} comes before any kind marker ('# CI', '# SO' or "
                            "'# PAR'): its kind is unknown", col)
        if (other := d.by_generic.get(generic)) is not None:
            raise self.fail(f"generic name '{generic}' is also edge {other} (line "
                            f"{d.edges[other].line})", col + _start(s, colon + 1))
        if (other := d.by_unique.get(unique)) is not None:
            raise self.fail(f"unique name '{unique}' is also edge {other} (line "
                            f"{d.edges[other].line})", col + _start(s, arrow + 3))
        d.by_generic[generic] = d.by_unique[unique] = index
        d.edges.append(Edge(index, d.kind, generic, unique, None, self.no))

    def bad_mapping(self, s: str, col: int) -> NoReturn:
        """Say what is wrong with the syntax of a mapping line (the slow path)."""
        colon = s.find(":")
        if colon < 0:
            raise self.fail("expected '<index>:<generic name> ==> <unique name>'", col)
        index_text = s[:colon].rstrip(BLANKS)
        if not (index_text.isascii() and index_text.isdigit()):
            raise self.fail(f"expected '<index>:<generic name> ==> <unique name>'; "
                            f"'{index_text}' is not an index (0, 1, 2 ...)", col)
        gstart = _start(s, colon + 1)
        arrow = s.find("==>", colon + 1)
        if arrow < 0:
            raise self.fail("missing '==>' between the generic and the unique name",
                            col + gstart)
        if not s[colon + 1:arrow].strip(BLANKS):
            raise self.fail("empty generic name before '==>'", col + arrow)
        if not s[arrow + 3:].strip(BLANKS):
            raise self.fail("empty unique name after '==>'", col + arrow + 3)
        self.check_name(s[colon + 1:arrow].strip(BLANKS), col + gstart)
        self.check_name(s[arrow + 3:].strip(BLANKS), col + _start(s, arrow + 3))
        raise AssertionError(f"mapping line without a fault: {s!r}")

    def check_name(self, name: str, col: int) -> None:
        if m := _NAME_FORBIDDEN.search(name):
            raise self.fail(f"'{m.group()}' is not allowed in a name", col + m.start())
        if "==>" in name:
            raise self.fail("a second '==>' in the line", col + name.index("==>"))
        if name[0] == "#":
            raise self.fail("a name must not begin with '#'", col)

    def default(self, s: str, col: int, kind: TreeEdgeKind) -> None:
        d = self.board
        assert d is not None
        section = self.stack[-1].name
        colon = s.find(":")
        if colon < 0:
            raise self.fail("expected '<unique name>:<value>'", col)
        name = s[:colon].rstrip(BLANKS)
        if not name:
            raise self.fail("expected '<unique name>:<value>'; the name is empty", col)
        index = d.by_unique.get(name)
        if index is None:
            hint = ""
            if (g := d.by_generic.get(name)) is not None:
                hint = (f"; it is the generic name of edge {g}, and defaults are keyed by "
                        f"unique names ('{d.edges[g].unique}')")
            raise self.fail(f"'{name}' is not a unique name of board {d.number}{hint}", col)
        edge = d.edges[index]
        if edge.kind is not kind:
            what = "SO edges take no defaults" if edge.kind is TreeEdgeKind.SO else \
                f"{edge.kind} defaults belong in {edge.kind.section}"
            raise self.fail(f"'{name}' is a {edge.kind} edge (index {index}); {section} takes "
                            f"{kind} edges only ({what})", col)
        if index in d.defaults:
            raise self.fail(f"a second default for '{name}' (first at line "
                            f"{d.defaults[index][1]})", col)
        rest = s[colon + 1:]
        text = rest.strip(BLANKS)
        vcol = col + colon + 1 + len(rest) - len(rest.lstrip(BLANKS))
        if not text:
            raise self.fail(f"no value after '{name}:'", vcol)
        try:
            value = Value.parse(text)
        except ValueError as err:
            hint = " (there are no inline comments)" if "#" in text else ""
            raise self.fail(f"bad value '{text}': {err}{hint}", vcol) from None
        d.defaults[index] = (value, self.no)
