"""What a DSP program presents at run time: its edges (dissertation 4.3.2, Abb. 4.8).

An edge is one value of the program's Controller Input (CI, from the PC), Sensor Output
(SO, to the PC) or Parameter (PAR) interface.  On the wire a value is a signed or
unsigned integer of 2 or 4 bytes (``raw``); its meaning is ``raw * 10**exponent`` in
``unit``, so every decimal a tree can hold within the edge's range travels exactly
(``man/ucom-protocol.7``, RUN TIME, Values).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from decimal import Decimal
from enum import IntEnum, StrEnum

_US_PER = {"ms": 1000, "us": 1}

MAX_NAME = 40
"""Longest edge name (the longest in B.5 has 35 characters)."""


class EdgeKind(IntEnum):
    """The edge kinds a UCoM offers, numbered as on the wire."""

    CI = 0
    SO = 1
    PAR = 2


@dataclass(frozen=True)
class EdgeSpec:
    """One edge: its generic name (as the program names it), its encoding and range."""

    kind: EdgeKind
    name: str
    width: int = 2
    """Bytes on the wire: 2 or 4."""
    signed: bool = True
    exponent: int = 0
    """The value is raw * 10**exponent."""
    minimum: int = -32768
    """Smallest raw value."""
    maximum: int = 32767
    """Largest raw value."""
    unit: str = ""
    default: int = 0
    """Raw value when the program starts."""
    axis: int | None = None
    """The axis (motor) the edge belongs to, 0-based; None for a board-wide edge."""
    period: int = 0
    """Default exchange period in program cycles.  SO: the board sends the value every
    ``period`` cycles in an SO map; CI: the PC sends it every ``period`` cycles in a CI map
    (2-byte edges only).  0: not cyclic (a CI is written with acknowledgement when it
    changes; an SO is read on request).  PAR edges are never cyclic."""

    def __post_init__(self) -> None:
        if self.width not in (2, 4):
            raise ValueError(f"{self.name}: width must be 2 or 4")
        low, high = self.raw_limits()
        if not low <= self.minimum <= self.maximum <= high:
            raise ValueError(f"{self.name}: range {self.minimum}..{self.maximum} does not fit "
                             f"{'' if self.signed else 'un'}signed {8 * self.width} bit")
        if not self.minimum <= self.default <= self.maximum:
            raise ValueError(f"{self.name}: default {self.default} out of range")
        if self.period < 0 or (self.period and (self.kind is EdgeKind.PAR or
                                                 (self.kind is EdgeKind.CI and self.width != 2))):
            raise ValueError(f"{self.name}: only SO edges and 2-byte CI edges have a period")
        if not 0 < len(self.name) <= MAX_NAME:
            raise ValueError(f"edge name {self.name!r}: 1..{MAX_NAME} characters")

    def raw_limits(self) -> tuple[int, int]:
        bits = 8 * self.width
        return (-(1 << bits - 1), (1 << bits - 1) - 1) if self.signed else (0, (1 << bits) - 1)

    def value(self, raw: int) -> Decimal:
        """The edge's value of a raw number, exactly."""
        return Decimal(raw).scaleb(self.exponent)

    def raw(self, value: Decimal | int | str) -> int:
        """The raw number of a value (a number, or a tree's text: decimal or ``0x`` hex);
        ValueError when it is not exact or out of range."""
        if isinstance(value, str) and value.lstrip("-").lower().startswith("0x"):
            value = int(value, 16)
        d = Decimal(value).scaleb(-self.exponent)
        if not d.is_finite():
            raise ValueError(f"{value} is not a finite number ({self.name} takes "
                             f"{self.describe_range()})")
        if d != d.to_integral_value():
            raise ValueError(f"{value} needs more than {-self.exponent} decimal places "
                             f"({self.name} carries {max(0, -self.exponent)})")
        r = int(d)
        if not self.minimum <= r <= self.maximum:
            raise ValueError(f"{value} is outside {self.describe_range()}")
        return r

    def describe_range(self) -> str:
        lo, hi = self.value(self.minimum), self.value(self.maximum)
        return f"{lo}..{hi}" + (f" {self.unit}" if self.unit else "")


class Seed(StrEnum):
    """What a CI edge is given when its board rejoins a running exchange after it was lost
    (``man/ucom-protocol.7``, RUN TIME, Faults): never a value that would move a joint."""

    KEEP = "keep"
    """The value the PC holds (a mode, a limit: the board had it before it was lost)."""
    SENSOR = "sensor"
    """The present value of an SO edge: a position target takes the joint sensor's reading,
    so the joint holds where it stands."""
    ZERO = "zero"
    """0: a velocity target (the joint stands still)."""
    BOARD = "board"
    """The value the board holds now (read back): a counter whose growth starts something,
    a reference run say, so that nothing is started again."""


@dataclass(frozen=True)
class CiSeed:
    """How one CI edge is seeded on a rejoin: ``seed``, with ``sensor`` the SO edge whose
    present value a :attr:`Seed.SENSOR` takes, and ``replace`` values of a
    :attr:`Seed.KEEP` that are given another one (a homing command: not resumed)."""

    ci: str
    seed: Seed
    sensor: str = ""
    replace: tuple[tuple[int, int], ...] = ()

    def kept(self, raw: int) -> int:
        """A :attr:`Seed.KEEP` value as it is written again (:attr:`replace` applied)."""
        for old, new in self.replace:
            if raw == old:
                return new
        return raw


@dataclass(frozen=True)
class ProgramSpec:
    """A DSP program's edges, in the order the board and its attribute trees list them:
    CI, then SO, then PAR (a tree's indices count across all three)."""

    name: str
    """The program name of its image descriptor (e.g. ``armar3 cascaded PID``)."""
    title: str
    edges: tuple[EdgeSpec, ...]
    cycle_edge: str = ""
    """The PAR edge that sets the cycle time (unit ``ms`` or ``us``); "" = fixed 1 ms."""
    seeds: tuple[CiSeed, ...] = ()
    """How its CI edges are seeded when a board rejoins (:class:`CiSeed`; a CI not named
    here keeps the PC's value).  A program without seeds does not rejoin: nothing says
    which value would hold its joints."""
    by_kind: dict[EdgeKind, tuple[EdgeSpec, ...]] = field(init=False, repr=False,
                                                           compare=False)

    def __post_init__(self) -> None:
        if self.cycle_edge:
            cycle = [e for e in self.edges if e.name == self.cycle_edge]
            if not cycle or cycle[0].kind is not EdgeKind.PAR or cycle[0].unit not in _US_PER:
                raise ValueError(f"{self.name}: cycle edge {self.cycle_edge!r} must be a "
                                 "PAR edge in ms or us")
        order = [e.kind for e in self.edges]
        if order != sorted(order):
            raise ValueError(f"{self.name}: edges must be CI, then SO, then PAR")
        names = [e.name for e in self.edges]
        if len(set(names)) != len(names):
            raise ValueError(f"{self.name}: edge names must be unique")
        object.__setattr__(self, "by_kind", {
            k: tuple(e for e in self.edges if e.kind is k) for k in EdgeKind})
        kinds = {e.name: e.kind for e in self.edges}
        for s in self.seeds:
            if kinds.get(s.ci) is not EdgeKind.CI or (
                    s.seed is Seed.SENSOR and kinds.get(s.sensor) is not EdgeKind.SO):
                raise ValueError(f"{self.name}: seed of {s.ci!r} must name a CI edge (and "
                                 "a SENSOR seed an SO edge)")

    def seed_of(self, ci: str) -> CiSeed:
        """How CI edge ``ci`` is seeded on a rejoin (:attr:`Seed.KEEP` when not named)."""
        for s in self.seeds:
            if s.ci == ci:
                return s
        return CiSeed(ci, Seed.KEEP)

    def of(self, kind: EdgeKind) -> tuple[EdgeSpec, ...]:
        return self.by_kind[kind]

    def cycle_us(self, raw: int | None = None) -> float:
        """The cycle time in microseconds for the cycle edge's ``raw`` value (its
        default when None)."""
        if not self.cycle_edge:
            return 1000.0
        e = next(e for e in self.edges if e.name == self.cycle_edge)
        value = e.value(e.default if raw is None else raw)
        return float(value) * _US_PER[e.unit]

    def tree_index(self, kind: EdgeKind, index: int) -> int:
        """The attribute-tree index of the ``index``-th edge of ``kind``."""
        return sum(len(self.by_kind[k]) for k in EdgeKind if k < kind) + index
