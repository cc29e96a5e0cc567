"""The values of a running robot by their robot-wide names: what ``part["Right Eye
Target"]`` reads and sets (:mod:`ucom_tools.ops.edges` resolves the names).

An SO value is the latest its map brought (decoded once per frame, latest-value
semantics: nothing queues), a CI value what the PC sends, a PAR value what the PC
wrote.  :meth:`RemoteValues.snapshot` takes the raw state on the loop's thread in a few
dict copies, :meth:`RemoteValues.decode` turns it into values on any other thread.
:class:`~ucom_tools.ops.remote.RemotePart` is a :class:`RemoteValues`.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import TYPE_CHECKING

from ucom_tools.errors import InputError
from ucom_tools.native import mypyc_attr
from ucom_tools.ops.edges import EdgeRef, Names
from ucom_tools.ops.exchange import BusExchange
from ucom_tools.ops.remote.faults import LostBoard, LostBoardWrite
from ucom_tools.ops.remote.report import RawSnapshot, Value
from ucom_tools.ops.robot import Robot
from ucom_tools.protocol.mca import ProcessImage, values_of
from ucom_tools.wire import mca
from ucom_tools.wire.ids import seq

if TYPE_CHECKING:
    from ucom_tools.config.topology import BoardKey


@mypyc_attr(allow_interpreted_subclasses=True)  # RemotePart extends it (see compiled.py)
class RemoteValues:
    """The values of the boards of ``exchanges`` (one per bus of ``robot``) by name;
    :attr:`names` knows the edges once the boards are checked, :meth:`_bind_values`
    the maps once they are configured."""

    def __init__(self, robot: Robot, exchanges: dict[str, BusExchange]) -> None:
        self.robot = robot
        self.exchanges = exchanges
        self._first_clock: Callable[[], float] | None = None
        """The first bus's clock (:meth:`_clock`), looked up once."""
        self.names = Names(())
        self._so_cache: dict[tuple[str, int], tuple[int, list[int]]] = {}
        self._par: dict[EdgeRef, int] = {}
        self._map_refs: dict[tuple[str, int], list[EdgeRef | None]] = {}
        """(bus, SO map number) -> the edge of each of its slots (None: not named)."""
        self._seen: dict[BoardKey, int] = {}
        self._last_raw: dict[EdgeRef, int] = {}
        self._feeds: list[_SoFeed] = []
        """Per SO map with named slots, what :meth:`_report_so` needs (:meth:`_bind_values`)."""
        self._lost: dict[BoardKey, LostBoard] = {}
        """(bus, board) -> the board, while it is lost (its values are stale, writes to
        it refused): replaced, never changed in place, so other threads may copy it."""
        self.on_values: Callable[[float, EdgeRef, Value], None] | None = None
        """Called with (time, edge, value) for every SO value a cycle saw change (and its
        first), and for every CI or PAR value set (recorders); the time on the base of the
        bus's frame timestamps, as --record logs the frames."""

    def _clock(self) -> float:
        """The bus clock (of the first bus: in virtual time they share one)."""
        clock = self._first_clock
        if clock is None:
            clock = self._first_clock = next(iter(self.robot.buses.values())).link.clock
        return clock()

    def _bind_values(self) -> None:
        """After the boards are configured: the edge of every slot of their SO maps, and
        the PAR values their trees wrote."""
        self._par = {}
        self._map_refs = {}
        self._feeds = []
        by_slot = {(r.bus, r.board, r.index): r for r in self.names if r.kind is mca.Kind.SO}
        for bus, x in self.exchanges.items():
            for m in x.plan.so_maps:
                if m.board in x.configured:
                    refs = [by_slot.get((bus, m.board, i)) for i in m.edges]
                    self._map_refs[(bus, m.number)] = refs
                    records = x.configured[m.board].edges.so
                    self._feeds.append(_SoFeed(bus, m.number, x.mca.image, refs,
                                               [records[i] for i in m.edges]))
        owners: dict[EdgeRef, int] = {}
        for feed in self._feeds:
            for ref in feed.refs:
                if ref is not None:
                    owners[ref] = owners.get(ref, 0) + 1
        for feed in self._feeds:  # an edge in two maps: compared edge by edge only
            feed.alone = all(ref is None or owners[ref] == 1 for ref in feed.refs)
        for ref in self.names:
            if ref.kind is mca.Kind.PAR:
                written = self.exchanges[ref.bus].configured[ref.board].written
                if ref.unique in written:
                    self._par[ref] = written[ref.unique]

    # ------------------------------------------------------------------ SO maps
    def _map_values(self, bus: str, number: int) -> list[int] | None:
        """The decoded values of SO map ``number`` of ``bus`` (decoded once per frame)."""
        x = self.exchanges[bus]
        frame = x.mca.image.frames.get(number)
        if frame is None:
            return None
        count = x.mca.image.counts[number]
        cached = self._so_cache.get((bus, number))
        if cached is None or cached[0] != count:
            m = next(m for m in x.plan.so_maps if m.number == number)
            records = x.configured[m.board].edges.so
            cached = (count, values_of(frame, [records[i] for i in m.edges]))
            self._so_cache[(bus, number)] = cached
        return cached[1]

    def _so(self, ref: EdgeRef) -> int | None:
        for m in self.exchanges[ref.bus].plan.maps_of(ref.board):
            if ref.index in m.edges:
                values = self._map_values(ref.bus, m.number)
                return None if values is None else values[m.edges.index(ref.index)]
        return None

    def _report_so(self) -> None:
        """Hand every SO value of the maps that came since the last cycle to on_values
        (each map decoded once per frame, by its precompiled struct; a map whose values
        are those it brought last time reports nothing, as edge by edge)."""
        on_values = self.on_values
        assert on_values is not None
        last = self._last_raw
        for feed in self._feeds:
            image = feed.image
            number = feed.number
            count = image.counts.get(number, 0)
            if count == feed.seen:
                continue
            feed.seen = count
            frame = image.frames.get(number)
            if frame is None:
                continue
            values = feed.decode(frame)
            self._so_cache[(feed.bus, number)] = (count, values)  # what _map_values gives
            if feed.alone and values == feed.last:
                continue
            stamp = image.stamps[number]
            for ref, raw in zip(feed.refs, values, strict=True):
                if ref is not None and last.get(ref) != raw:
                    last[ref] = raw
                    on_values(stamp, ref, ref.value(raw))
            feed.last = values

    # ------------------------------------------------------------------ other threads
    def snapshot(self) -> RawSnapshot:
        """Every value's raw state as it is now, for another thread to decode
        (:meth:`decode`): references to the maps' latest frames (bytes, never changed in
        place) and copies of the CI and PAR values, a few dict copies per bus.  The loop's
        thread takes it (:attr:`RemotePart.each_cycle
        <ucom_tools.ops.remote.RemotePart.each_cycle>`); nothing is decoded here."""
        frames, stamps, ci = {}, {}, {}
        for bus, x in self.exchanges.items():
            image = x.mca.image
            frames[bus] = dict(image.frames)
            stamps[bus] = dict(image.stamps)
            ci[bus] = dict(x.ci)
        return RawSnapshot(self._clock(), frames, stamps, ci, dict(self._par))

    def decode(self, snap: RawSnapshot) -> dict[EdgeRef, tuple[float, Value]]:
        """(time stamp, value) of every edge a :meth:`snapshot` holds a value of: an SO's
        stamped with its map's frame, a CI's and a PAR's with the snapshot's time (both
        on the base of the bus's frame time stamps).  Reads only what :meth:`RemotePart.start
        <ucom_tools.ops.remote.RemotePart.start>` set up, so any thread may call it while
        the loop runs."""
        out: dict[EdgeRef, tuple[float, Value]] = {}
        for (bus, number), refs in self._map_refs.items():
            frame = snap.frames[bus].get(number)
            if frame is None:
                continue
            x = self.exchanges[bus]
            m = next(m for m in x.plan.so_maps if m.number == number)
            records = x.configured[m.board].edges.so
            raws = values_of(frame, [records[i] for i in m.edges])
            stamp = snap.stamps[bus].get(number, snap.clock)
            for ref, raw in zip(refs, raws, strict=True):
                if ref is not None:
                    out[ref] = (stamp, ref.value(raw))
        for ref in self.names:
            if ref.kind is mca.Kind.CI:
                sent = snap.ci[ref.bus].get((ref.board, ref.index))
                if sent is not None:
                    out[ref] = (snap.clock, ref.value(sent))
            elif ref.kind is mca.Kind.PAR and ref in snap.par:
                out[ref] = (snap.clock, ref.value(snap.par[ref]))
        return out

    # ------------------------------------------------------------------ by name
    def raw(self, name: str | EdgeRef) -> int | None:
        """The raw value of an edge: SO the latest from its map (None before the first,
        or when it is not cyclic), CI what the PC sends, PAR what the PC wrote."""
        ref = name if isinstance(name, EdgeRef) else self.names.resolve(name)
        if ref.kind is mca.Kind.SO:
            return self._so(ref)
        if ref.kind is mca.Kind.CI:
            return self.exchanges[ref.bus].ci.get((ref.board, ref.index))
        return self._par.get(ref)

    def cyclic(self, name: str | EdgeRef) -> bool:
        """Does the edge travel in a process-data map (a CI the loop sends every period,
        an SO the board sends)?  Others are written, or read, on request."""
        ref = name if isinstance(name, EdgeRef) else self.names.resolve(name)
        plan = self.exchanges[ref.bus].plan
        if ref.kind is mca.Kind.CI:
            return any((ref.board, ref.index) in c.slots for c in plan.ci_maps)
        if ref.kind is mca.Kind.SO:
            return any(ref.index in m.edges for m in plan.maps_of(ref.board))
        return False

    def __getitem__(self, name: str) -> Value | None:
        ref = self.names.resolve(name)
        raw = self.raw(ref)
        return None if raw is None else ref.value(raw)

    def __setitem__(self, name: str, value: object) -> None:
        self.set(name, value)

    def set(self, name: str | EdgeRef, value: object, *, key: str | None = None,
            wait: bool = True) -> EdgeRef:
        """Set a CI or PAR by name, in the edge's unit; range-checked before anything is
        sent (InputError).  The write of a PAR, or of a CI outside the CI maps, waits for
        the board's acknowledgement unless ``wait`` is False: then, while the loop runs,
        the loop steps it beside its cycles (:mod:`ucom_tools.ops.remote.par_write`)."""
        ref = name if isinstance(name, EdgeRef) else self.names.resolve(
            name, key=key, kinds=(mca.Kind.CI, mca.Kind.PAR))
        if ref.kind is mca.Kind.SO:
            raise InputError(f"{ref.qualified} is a sensor output; only CI and PAR edges "
                             "can be set", key=key)
        raw = ref.raw(value, key=key)
        lost = self._lost.get((ref.bus, ref.board))
        if lost is not None:
            raise LostBoardWrite(f"{ref.qualified}: {lost.where} is lost since "
                                 f"{lost.since:.3f} s ({lost.seen}); writes to it are "
                                 "refused until it rejoins", key=key)
        x = self.exchanges[ref.bus]
        if ref.kind is mca.Kind.CI:
            if wait or x.ci_mapped(ref.board, ref.index) or not self._write_later(ref, raw):
                x.set_ci(ref.board, ref.generic, raw)
            else:  # a CI outside the maps (a Command): acknowledged, stepped by the loop
                x.ci[(ref.board, ref.index)] = raw
        elif wait or not self._write_later(ref, raw):
            x.mca.write(seq(ref.board), mca.Kind.PAR, ref.index, [raw],
                        x.configured[ref.board].edges.par)
            self._par[ref] = raw
        else:
            self._par[ref] = raw
        if self.on_values is not None:  # stamped as the frames are (SO values, --record)
            self.on_values(x.link.dispatcher.stamp(), ref, ref.value(raw))
        return ref

    def _write_later(self, ref: EdgeRef, raw: int) -> bool:
        """Write a PAR, or a CI outside the CI maps, without waiting for its
        acknowledgement; False where that cannot be (the loop does not run): the caller
        writes it and waits."""
        return False

    def _held(self, ref: EdgeRef) -> int | None:
        """What the PC holds of a CI or PAR (what it sends or wrote)."""
        if ref.kind is mca.Kind.CI:
            return self.exchanges[ref.bus].ci.get((ref.board, ref.index))
        return self._par.get(ref)

    def _hold(self, ref: EdgeRef, raw: int) -> None:
        if ref.kind is mca.Kind.CI:
            self.exchanges[ref.bus].ci[(ref.board, ref.index)] = raw
        else:
            self._par[ref] = raw

    # ------------------------------------------------------------------ validity
    @property
    def lost(self) -> dict[BoardKey, LostBoard]:
        """The boards lost now, (bus, board) -> since when, what was seen last, what the
        PC does about it (``man/ucom-protocol.7``, RUN TIME, Faults); a copy."""
        return dict(self._lost)

    def valid(self, name: str | EdgeRef) -> bool:
        """Whether an edge's value is current: its board is not lost and, for an SO, a
        value of it has arrived (a lost board's values are its last before the loss)."""
        ref = name if isinstance(name, EdgeRef) else self.names.resolve(name)
        if (ref.bus, ref.board) in self._lost:
            return False
        return ref.kind is not mca.Kind.SO or self._so(ref) is not None

    def age(self, name: str | EdgeRef) -> float | None:
        """Seconds since an SO value's map arrived (by the frame's time stamp, on its bus's
        time base), None before the first or for a CI or PAR (set by the PC)."""
        ref = name if isinstance(name, EdgeRef) else self.names.resolve(name)
        if ref.kind is not mca.Kind.SO:
            return None
        image = self.exchanges[ref.bus].mca.image
        for m in self.exchanges[ref.bus].plan.maps_of(ref.board):
            if ref.index in m.edges and m.number in image.stamps:
                stamp = image.stamps[m.number]
                return max(0.0, self.robot.buses[ref.bus].link.dispatcher.stamp() - stamp)
        return None

    @property
    def so(self) -> Mapping[str, Value | None]:
        """The latest SO values by name, looked up when read (nothing is copied)."""
        return _SoView(self)

    def values(self, kinds: tuple[mca.Kind, ...] = tuple(mca.Kind)) -> dict[str, Value]:
        """Every known value of the given kinds by name (SO: the latest that arrived)."""
        out: dict[str, Value] = {}
        for ref in self.names:
            if ref.kind in kinds:
                raw = self.raw(ref)
                if raw is not None:
                    out[self.names.name_of(ref)] = ref.value(raw)
        return out


class _SoFeed:
    """One SO map as :meth:`RemoteValues._report_so` follows it: where its frames land,
    the edge of each slot, a struct that unpacks its values (big-endian, as
    :func:`~ucom_tools.wire.mca.unpack_values`; None when a width has no struct code),
    the count of its frames seen and the values it brought last."""

    def __init__(self, bus: str, number: int, image: ProcessImage,
                 refs: list[EdgeRef | None], records: Sequence[mca.EdgeRecord]) -> None:
        self.bus = bus
        self.number = number
        self.image = image
        self.refs = refs
        self.records = list(records)
        self.unpacker: struct.Struct | None = mca.values_struct(
            [(r.width, r.signed) for r in records])
        self.seen = 0
        self.last: list[int] | None = None
        self.alone = True
        """No edge of this map is in another one (then equal values say nothing new)."""

    def decode(self, frame: bytes) -> list[int]:
        """The map's raw values (:func:`~ucom_tools.protocol.mca.values_of`'s, and its
        FrameError when the length is wrong)."""
        unpacker = self.unpacker
        if unpacker is not None and len(frame) == unpacker.size:
            return list(unpacker.unpack(frame))
        return values_of(frame, self.records)


class _SoView(Mapping[str, "Value | None"]):
    """:attr:`RemoteValues.so`: a read-only view of the latest SO values by name."""

    def __init__(self, part: RemoteValues) -> None:
        self._part = part

    def __getitem__(self, name: str) -> Value | None:
        ref = self._part.names.resolve(name)
        if ref.kind is not mca.Kind.SO:
            raise KeyError(name)
        raw = self._part.raw(ref)
        return None if raw is None else ref.value(raw)

    def __iter__(self) -> Iterator[str]:
        names = self._part.names
        return (names.name_of(r) for r in names if r.kind is mca.Kind.SO)

    def __len__(self) -> int:
        return sum(1 for r in self._part.names if r.kind is mca.Kind.SO)
