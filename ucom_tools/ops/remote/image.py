"""What does not change while a part runs, as plain data: its edges by name, each
board's description and SO maps, the buses, the loop's rate (:class:`PartImage`).

A consumer of the run (the live view, ``--record``, the Zenoh share) needs the part's
structure to make values of a snapshot (:class:`~ucom_tools.ops.remote.publish.
LoopSnapshot`) and to describe the robot; it must not read the running part for it.
:meth:`PartImage.of` takes it from a checked part once, on the thread that runs it; the
image is then read by any thread, and it pickles (the compiled run time's own objects do
not), so that another process can have it (``ucom remote run`` runs its consumers in a
process of their own: :mod:`ucom_tools.ops.remote.feed`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from ucom_tools.edgelists.model import EdgeSpec
from ucom_tools.ops.edges import EdgeRef, Names
from ucom_tools.ops.remote.report import CheckReport, RawSnapshot, Value
from ucom_tools.protocol.mca import BoardEdges, values_of
from ucom_tools.protocol.plan import BusPlan, SoMapPlan
from ucom_tools.wire import mca

if TYPE_CHECKING:
    from ucom_tools.config.topology import BoardKey

Record = tuple[int, bool, int, int, int, str, str]
"""An :class:`~ucom_tools.wire.mca.EdgeRecord` as plain data: width, signed, exponent,
minimum, maximum, name, unit."""
Edge = tuple[str, int, str, str, str, str, int, int, EdgeSpec]
"""An :class:`~ucom_tools.ops.edges.EdgeRef` as plain data (its fields in order, the
kind as its number)."""


def _record(r: mca.EdgeRecord) -> Record:
    return (r.width, r.signed, r.exponent, r.minimum, r.maximum, r.name, r.unit)


@dataclass
class PartImage:
    """A started (or checked) part's structure as plain data (see the module docstring);
    :meth:`of` makes it, the properties rebuild what the run time's code works with."""

    source: str
    """The topology's source (its file, or the bundled robot's name)."""
    name: str
    """The topology's name ('ARMAR-III')."""
    period_s: float
    virtual: bool
    bitrates: dict[str, int]
    """Bus -> bitrate, in the robot's order."""
    edges: list[Edge]
    """Every named edge, in the part's order (``part.names``)."""
    plans: dict[str, BusPlan]
    boards: dict[BoardKey, tuple[list[Record], list[Record], list[Record]]]
    """(bus, board) -> the CI, SO and PAR edges it described, of the boards named."""
    report: CheckReport | None = None
    cyclic_edges: set[tuple[str, int, int, int]] = field(default_factory=set)
    """(bus, board, kind, index) of every edge that travels in a map."""
    serials: dict[BoardKey, int] = field(default_factory=dict)
    """(bus, board) -> the board's serial number, as its Init Ack gave it at the start."""

    @classmethod
    def of(cls, part: Any) -> PartImage:
        """The image of a checked :class:`~ucom_tools.ops.remote.RemotePart` (its own
        thread, or before it runs)."""
        topology = part.robot.topology
        edges: list[Edge] = []
        boards: dict[BoardKey, tuple[list[Record], list[Record], list[Record]]] = {}
        cyclic: set[tuple[str, int, int, int]] = set()
        for ref in part.names:
            edges.append((ref.bus, ref.board, ref.where, ref.prefix, ref.unique, ref.generic,
                          int(ref.kind), ref.index, ref.spec))
            key = (ref.bus, ref.board)
            if key not in boards:
                x = part.exchanges[ref.bus]
                described = (x.configured[ref.board].edges if ref.board in x.configured
                             else part.described(ref.bus, ref.board))
                if described is not None:
                    boards[key] = ([_record(r) for r in described.ci],
                                   [_record(r) for r in described.so],
                                   [_record(r) for r in described.par])
            if part.cyclic(ref):
                cyclic.add((ref.bus, ref.board, int(ref.kind), ref.index))
        return cls(source=topology.source if topology is not None else "",
                   name=topology.name if topology is not None else "",
                   period_s=part.period_s, virtual=part.virtual,
                   bitrates={n: h.link.bitrate for n, h in part.robot.buses.items()},
                   edges=edges, plans={n: x.plan for n, x in part.exchanges.items()},
                   boards=boards, report=part.report, cyclic_edges=cyclic,
                   serials=dict(getattr(part, "_serials", {})))

    # ------------------------------------------------------------------ rebuilt
    def __post_init__(self) -> None:
        self._refs: list[EdgeRef] | None = None
        self._names: Names | None = None
        self._described: dict[BoardKey, BoardEdges] = {}
        self._map_refs: list[tuple[str, SoMapPlan, list[mca.EdgeRecord],
                                   list[EdgeRef | None]]] | None = None
        self._raw_plans: dict[frozenset[EdgeRef], list[tuple[
            str, int, list[mca.EdgeRecord], list[tuple[int, EdgeRef]]]]] = {}

    def __getstate__(self) -> dict[str, Any]:
        return {k: v for k, v in self.__dict__.items() if not k.startswith("_")}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self.__post_init__()

    @property
    def refs(self) -> list[EdgeRef]:
        """Every named edge, in the part's order."""
        if self._refs is None:
            self._refs = [EdgeRef(bus, board, where, prefix, unique, generic, mca.Kind(kind),
                                  index, spec)
                          for bus, board, where, prefix, unique, generic, kind, index, spec
                          in self.edges]
        return self._refs

    @property
    def names(self) -> Names:
        if self._names is None:
            self._names = Names(self.refs)
        return self._names

    def described(self, bus: str, board: int) -> BoardEdges | None:
        """The edges board ``board`` of ``bus`` described."""
        got = self._described.get((bus, board))
        if got is None and (bus, board) in self.boards:
            ci, so, par = self.boards[(bus, board)]
            got = self._described[(bus, board)] = BoardEdges(
                *(tuple(mca.EdgeRecord(*r) for r in rs) for rs in (ci, so, par)))
        return got

    def so_maps(self, bus: str) -> list[SoMapPlan]:
        """The SO maps of the boards named on ``bus``."""
        return [m for m in self.plans[bus].so_maps if (bus, m.board) in self.boards]

    def cyclic(self, ref: EdgeRef) -> bool:
        """Does the edge travel in a map (see ``RemotePart.cyclic``)?"""
        return (ref.bus, ref.board, int(ref.kind), ref.index) in self.cyclic_edges

    def _maps(self) -> list[tuple[str, SoMapPlan, list[mca.EdgeRecord],
                                  list[EdgeRef | None]]]:
        if self._map_refs is None:
            by_slot = {(r.bus, r.board, r.index): r for r in self.refs
                       if r.kind is mca.Kind.SO}
            out = []
            for bus in self.plans:
                for m in self.so_maps(bus):
                    described = self.described(bus, m.board)
                    assert described is not None
                    out.append((bus, m, [described.so[i] for i in m.edges],
                                [by_slot.get((bus, m.board, i)) for i in m.edges]))
            self._map_refs = out
        return self._map_refs

    def decode(self, snap: RawSnapshot, kinds: tuple[mca.Kind, ...] = tuple(mca.Kind),
               ) -> dict[EdgeRef, tuple[float, Value]]:
        """(time stamp, value) of every edge of ``kinds`` ``snap`` holds a value of, as
        :meth:`RemotePart.decode <ucom_tools.ops.remote.values.RemoteValues.decode>`
        gives it (an SO stamped with its map's frame, a CI or PAR with the snapshot)."""
        out: dict[EdgeRef, tuple[float, Value]] = {}
        if mca.Kind.SO not in kinds:
            return self._decode_set(snap, kinds, out)
        for bus, m, records, refs in self._maps():
            frame = snap.frames[bus].get(m.number)
            if frame is None:
                continue
            raws = values_of(frame, records)
            stamp = snap.stamps[bus].get(m.number, snap.clock)
            for ref, raw in zip(refs, raws, strict=True):
                if ref is not None:
                    out[ref] = (stamp, ref.value(raw))
        return self._decode_set(snap, kinds, out)

    def raw_so(self, snap: RawSnapshot, wanted: frozenset[EdgeRef]) -> dict[EdgeRef, int]:
        """The raw values of the SO edges ``wanted`` that ``snap`` holds (only the maps
        that carry one of them are unpacked: a consumer that reads a few edges at the
        snapshots' rate, such as the CANopen gateway)."""
        plan = self._raw_plans.get(wanted)
        if plan is None:
            plan = self._raw_plans[wanted] = [
                (bus, m.number, records,
                 [(i, r) for i, r in enumerate(refs) if r is not None and r in wanted])
                for bus, m, records, refs in self._maps()
                if any(r is not None and r in wanted for r in refs)]
        out: dict[EdgeRef, int] = {}
        frames = snap.frames
        for bus, number, records, picks in plan:
            frame = frames[bus].get(number)
            if frame is None:
                continue
            raws = values_of(frame, records)
            for i, ref in picks:
                out[ref] = raws[i]
        return out

    def _decode_set(self, snap: RawSnapshot, kinds: tuple[mca.Kind, ...],
                    out: dict[EdgeRef, tuple[float, Value]],
                    ) -> dict[EdgeRef, tuple[float, Value]]:
        """:meth:`decode` of the CI and PAR values (those the PC sets) into ``out``."""
        ci, par = mca.Kind.CI in kinds, mca.Kind.PAR in kinds
        if not (ci or par):
            return out
        for ref in self.refs:
            if ci and ref.kind is mca.Kind.CI:
                sent = snap.ci[ref.bus].get((ref.board, ref.index))
                if sent is not None:
                    out[ref] = (snap.clock, ref.value(sent))
            elif par and ref.kind is mca.Kind.PAR and ref in snap.par:
                out[ref] = (snap.clock, ref.value(snap.par[ref]))
        return out


def boards_of(refs: Sequence[EdgeRef]) -> Mapping[BoardKey, list[EdgeRef]]:
    """The edges by board, in order."""
    out: dict[BoardKey, list[EdgeRef]] = {}
    for ref in refs:
        out.setdefault((ref.bus, ref.board), []).append(ref)
    return out


__all__ = ["PartImage", "boards_of"]
