"""A robot's edges by their robot-wide names: what ``ucom remote`` and ``ucom params``
address (``part["Right Eye Target"]``).

An edge's identity is (tree prefix, unique name) (``man/ucom-tree.5``): it is named
``Prefix/Unique name`` (``Eyes/Right Eye Target``), or by its unique name alone where no
other board of the robot uses that name (``Right Eye Target``; ``AD Channel 6`` is on every
ARMAR-III board and needs its prefix).  Values are in the edge's unit (raw x
10^exponent, as the board describes it); they convert exactly or not at all.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from decimal import Decimal, InvalidOperation

from ucom_tools.edgelists.model import EdgeKind, EdgeSpec
from ucom_tools.errors import InputError
from ucom_tools.wire import mca


@dataclass(frozen=True, eq=False)
class EdgeRef:
    """One edge of one board of the robot."""

    bus: str
    board: int
    """Seq ID on its bus."""
    where: str
    """'CAN0 board 3 (head right)'."""
    prefix: str
    unique: str
    generic: str
    kind: mca.Kind
    index: int
    """Per-kind index on the board."""
    spec: EdgeSpec
    """Encoding and range (from the board's description)."""

    def __hash__(self) -> int:  # the identity, not every field (a run hashes it often)
        return hash((self.bus, self.board, self.kind, self.index))

    def __eq__(self, other: object) -> bool:
        return isinstance(other, EdgeRef) and (self.bus, self.board, self.kind,
                                               self.index) == (other.bus, other.board,
                                                               other.kind, other.index)

    @property
    def qualified(self) -> str:
        return f"{self.prefix}/{self.unique}"

    def raw(self, value: object, *, key: str | None = None) -> int:
        """The raw number of ``value`` (a number, or text: decimal or 0x hex); InputError
        naming the edge and its range when it does not fit exactly."""
        spec = self.spec
        if type(value) is int and spec.exponent <= 0:  # the usual case, exact as below
            r = value * 10 ** -spec.exponent
            if spec.minimum <= r <= spec.maximum:
                return r
        try:
            if isinstance(value, float):
                value = Decimal(repr(value))
            if isinstance(value, str):
                text = value.strip()
                if not text:
                    raise ValueError("no value")
                return self.spec.raw(text)
            if not isinstance(value, int | Decimal):
                raise ValueError(f"{value!r} is not a number")
            return self.spec.raw(value)
        except (ValueError, InvalidOperation) as err:
            raise InputError(f"{self.qualified}: {err}", key=key) from None

    def value(self, raw: int) -> int | Decimal:
        """The edge's value of a raw number: an int when the edge has no decimals."""
        exponent = self.spec.exponent
        if exponent >= 0:  # no Decimal made to be thrown away (every SO value reported)
            return int(raw) * 10 ** exponent
        return self.spec.value(raw)

    def describe_range(self) -> str:
        return self.spec.describe_range()


def spec_of(kind: mca.Kind, record: mca.EdgeRecord) -> EdgeSpec:
    """The edge a board described, as an :class:`EdgeSpec` (for value conversion)."""
    return EdgeSpec(EdgeKind(kind), record.name, width=record.width, signed=record.signed,
                    exponent=record.exponent, minimum=record.minimum,
                    maximum=record.maximum, unit=record.unit,
                    default=min(max(0, record.minimum), record.maximum))


class Names:
    """Every edge of a robot, found by name."""

    def __init__(self, refs: Iterable[EdgeRef]) -> None:
        self.refs = list(refs)
        self._qualified = {r.qualified.casefold(): r for r in self.refs}
        self._bare: dict[str, list[EdgeRef]] = {}
        for r in self.refs:
            self._bare.setdefault(r.unique.casefold(), []).append(r)

    def __iter__(self) -> Iterator[EdgeRef]:
        return iter(self.refs)

    def __len__(self) -> int:
        return len(self.refs)

    def name_of(self, ref: EdgeRef) -> str:
        """The shortest name that finds ``ref``: its unique name where that is unique."""
        return ref.unique if len(self._bare[ref.unique.casefold()]) == 1 else ref.qualified

    def names(self) -> list[str]:
        """Every name that finds exactly one edge (for completion and suggestions)."""
        out = [r.qualified for r in self.refs]
        out += [rs[0].unique for rs in self._bare.values() if len(rs) == 1]
        return sorted(set(out))

    def resolve(self, name: str, *, key: str | None = None,
                kinds: Iterable[mca.Kind] | None = None) -> EdgeRef:
        """The edge called ``name`` (``Prefix/Unique`` or a unique name that only one board
        uses; case does not matter); InputError with the closest names otherwise.  With
        ``kinds``, an edge of another kind is refused (an SO cannot be set)."""
        folded = " ".join(name.split()).casefold()
        ref = self._qualified.get(folded.replace(" / ", "/"))
        if ref is None:
            found = self._bare.get(folded, [])
            if len(found) > 1:
                raise InputError(f"{name!r} is on {len(found)} boards; name one of: "
                                 + ", ".join(r.qualified for r in found), key=key)
            if not found:
                close = difflib.get_close_matches(name, self.names(), n=3, cutoff=0.6)
                hint = f"; did you mean {' or '.join(repr(c) for c in close)}?" if close \
                    else " (see 'ucom remote check' for the names)"
                raise InputError(f"no edge called {name!r}{hint}", key=key)
            ref = found[0]
        if kinds is not None and ref.kind not in set(kinds):
            allowed = "/".join(k.name for k in kinds)
            raise InputError(f"{ref.qualified} is {ref.kind.name}; only {allowed} edges can "
                             "be set", key=key)
        return ref
