"""The attribute tree as data: boards, their edges (the mapping table) and defaults.

The dissertation's *Attribute-Tree* (B.5) maps the generic edge names of a board's program
(``armar3.fl.S`` names them the same on every board) to robot-wide unique names and gives
default values for parameters and controller inputs.  Here a :class:`Tree` holds one
:class:`BoardBlock` per ``DSP{ <n>{ }<n> }DSP`` block; each edge carries its own default, so the
order of the default lines in a file is not part of the data (``man/ucom-tree.5``).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from decimal import Decimal
from enum import StrEnum
from functools import cached_property


class TreeEdgeKind(StrEnum):
    """The MCA2 edge kind of a mapping (set by the ``# CI``, ``# SO``, ``# PAR`` markers) as
    a tree names it (the program's is :class:`~ucom_tools.edgelists.model.EdgeKind`, the
    wire's :class:`~ucom_tools.wire.mca.Kind`)."""

    CI = "CI"
    """Controller Input: set points and commands from the PC (may have a default)."""
    SO = "SO"
    """Sensor Output: measurements from the board (never has a default)."""
    PAR = "PAR"
    """Parameter: configuration of the program (may have a default)."""

    @property
    def section(self) -> str | None:
        """The block that holds defaults of this kind, None for SO."""
        return _SECTION[self]


_SECTION = {TreeEdgeKind.CI: "ControllerInput", TreeEdgeKind.SO: None,
            TreeEdgeKind.PAR: "Parameter"}
KIND_ORDER = (TreeEdgeKind.CI, TreeEdgeKind.SO, TreeEdgeKind.PAR)
"""The order of the kind markers in a MappingTable."""

_VALUE = re.compile(r"-?(?:0x[0-9A-Fa-f]+|[0-9]+(?:\.[0-9]+)?)\Z", re.ASCII)
MAX_INT_BITS = 1024
"""Integers must be finite as a double (MCA2 edges carry doubles): |n| < 2**1024."""


@dataclass(frozen=True)
class Value:
    """A default value: the raw text as written (``0x444``, ``0.0005``) and its number.

    Hex and decimal integers are ``int``, decimal fractions ``float``.  Two values are equal
    when their texts are (``0x3`` and ``3`` differ: the file is what a reviewer reads)."""

    text: str
    number: int | float = field(compare=False)

    @classmethod
    def parse(cls, text: str) -> Value:
        """The value of ``text``; ValueError (with the reason) if it is not one."""
        if not _VALUE.match(text):
            raise ValueError("expected an integer, a decimal fraction (digits on both sides "
                             "of the point) or 0x and hex digits, each with an optional '-'")
        negative = text.startswith("-")
        body = text[1:] if negative else text
        number: int | float
        if body.startswith("0x"):
            number = int(body[2:], 16)
        elif "." in body:
            number = float(body)
            if math.isinf(number):
                raise ValueError("out of range (not a finite double)")
        else:
            if len(body) > 400:  # 2**1024 has 309 decimal digits; int() refuses > 4300
                raise ValueError("out of range (not a finite double)")
            number = int(body)
        if isinstance(number, int) and number.bit_length() > MAX_INT_BITS:
            raise ValueError("out of range (not a finite double)")
        return cls(text, -number if negative else number)

    @classmethod
    def of(cls, number: int | float) -> Value:
        """The value of a number, written without exponent (``1e-05`` -> ``0.00001``)."""
        if isinstance(number, bool):
            raise TypeError("a default is a number, not a bool")
        if isinstance(number, int):
            return cls.parse(str(number))
        if not math.isfinite(number):
            raise ValueError(f"not a finite number: {number!r}")
        text = format(Decimal(repr(number)), "f")
        if "." not in text:
            text += ".0"
        return cls.parse(text)


@dataclass(frozen=True)
class Edge:
    """One line of a MappingTable, ``<index>:<generic> ==> <unique>``, with its default."""

    index: int
    kind: TreeEdgeKind
    generic: str
    """The program's name of the edge (the same on every board running that program)."""
    unique: str
    """The robot-wide name (unique within its board; identity is (prefix, unique))."""
    default: Value | None = None
    """From the Parameter (PAR) or ControllerInput (CI) block; SO edges have none."""
    line: int = field(default=0, compare=False)
    """Line of the mapping in its file (0 when not read from a file)."""
    default_line: int = field(default=0, compare=False)
    """Line of the default in its file (0 when none or not read from a file)."""


@dataclass(frozen=True)
class BoardBlock:
    """One ``<n>{ ... }<n>`` block: the configuration of one board's program (a block of a
    tree, bound to a board of the robot by :mod:`~ucom_tools.config.attrtree.robot`)."""

    number: int
    """The block's number, unique within the file; it says nothing about the bus or the
    board's sequential ID (the robot's topology binds blocks to boards)."""
    prefix: str
    """The board's module name (``Prefix : Eyes``); (prefix, unique name) is robot-wide."""
    edges: tuple[Edge, ...]
    """In index order: ``edges[i].index == i``."""
    line: int = field(default=0, compare=False)
    column: int = field(default=0, compare=False)
    """Where the board number is in its file (0 when not read from a file)."""
    prefix_line: int = field(default=0, compare=False)
    prefix_column: int = field(default=0, compare=False)

    @cached_property
    def _by_unique(self) -> dict[str, Edge]:
        return {e.unique: e for e in self.edges}

    @cached_property
    def _by_generic(self) -> dict[str, Edge]:
        return {e.generic: e for e in self.edges}

    def edge(self, unique: str) -> Edge:
        """The edge with this unique name; KeyError if none."""
        return self._by_unique[unique]

    def generic(self, name: str) -> Edge:
        """The edge with this generic (program) name; KeyError if none."""
        return self._by_generic[name]

    def of_kind(self, kind: TreeEdgeKind) -> tuple[Edge, ...]:
        return tuple(e for e in self.edges if e.kind is kind)

    def defaults(self, kind: TreeEdgeKind | None = None) -> dict[str, Value]:
        """Unique name -> default, in index order (of one kind, or all)."""
        return {e.unique: e.default for e in self.edges
                if e.default is not None and (kind is None or e.kind is kind)}


@dataclass(frozen=True)
class Tree:
    """A whole attribute tree file: its boards in file order."""

    boards: tuple[BoardBlock, ...]
    source: str = field(default="", compare=False)
    """The file name it was read from (for messages)."""

    def board(self, number: int) -> BoardBlock:
        """The board block with this number; KeyError if none."""
        for b in self.boards:
            if b.number == number:
                return b
        raise KeyError(number)

    @property
    def numbers(self) -> tuple[int, ...]:
        return tuple(b.number for b in self.boards)
