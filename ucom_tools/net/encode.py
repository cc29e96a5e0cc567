"""A board's ``values`` sample and an edge's sample, encoded from precompiled parts
(``man/ucom-network.7``, PAYLOADS and THE LOOP'S COST).

:meth:`PartImage.decode <ucom_tools.ops.remote.image.PartImage.decode>` turns a
snapshot into (time stamp, value) per :class:`EdgeRef` (dict look-ups, a Decimal per
value) and :func:`keys.dumps` walks the result again: about
4 us per value in Python, on a thread that competes with the 1 kHz loop for the GIL.
Here everything that does not change while the loop runs is done once, when the share
declares its publishers: the JSON text around the values (names, keys, separators), one
:class:`struct.Struct` per SO map (big endian, as MCA packs a map), and for each value
how to write it (``%d`` for a whole number; a small function for an edge with decimals).
Encoding a board's sample is then, per SO map, one ``unpack`` and one ``%`` formatting,
and the CI values likewise: the same JSON document as ``keys.dumps`` of the decoded
values gives (a test compares them), at a fraction of the cost.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from operator import itemgetter
from typing import TYPE_CHECKING, Any

from ucom_tools.net import keys
from ucom_tools.ops.edges import EdgeRef
from ucom_tools.ops.remote.image import PartImage
from ucom_tools.ops.remote.report import RawSnapshot
from ucom_tools.wire import mca

if TYPE_CHECKING:
    from ucom_tools.config.topology import BoardKey

Conv = Callable[[int], Any] | None
"""How a raw value is written: None for ``%d`` of the raw number itself, else a function
whose result goes into its ``%d`` (a whole number) or ``%s`` (text) place."""

_FORMATS = {(1, False): "B", (1, True): "b", (2, False): "H", (2, True): "h",
            (4, False): "I", (4, True): "i", (8, False): "Q", (8, True): "q"}


def _json(value: str) -> str:
    """A JSON string."""
    return json.dumps(value, ensure_ascii=False)


def _text(value: str) -> str:
    """A JSON string, as a fragment of a ``%`` template."""
    return _json(value).replace("%", "%%")


def _decimal(k: int) -> Callable[[int], str]:
    """raw / k as JSON writes ``keys.number(raw x 10^-n)``: a whole number as an integer,
    else the float nearest the exact value (Python's int division rounds correctly, as
    ``float(Decimal)`` does)."""
    def write(raw: int) -> str:
        q, r = divmod(raw, k)
        return str(q) if r == 0 else repr(raw / k)
    return write


def _scale(m: int) -> Callable[[int], int]:
    return lambda raw: raw * m


def conv_of(ref: EdgeRef) -> tuple[Conv, str]:
    """How an edge's raw value is written, and its place in a template (``%d``, ``%s``)."""
    e = ref.spec.exponent
    if e == 0:
        return None, "%d"
    if e > 0:
        return _scale(10 ** e), "%d"
    return _decimal(10 ** -e), "%s"


def write(conv: Conv, raw: int) -> str:
    """One raw value as its JSON text."""
    return str(raw) if conv is None else str(conv(raw))


def _stamp(t: float) -> str:
    return repr(round(float(t), 6))


@dataclass
class _SoMap:
    """One SO map of a board: the values it carries into the board's sample."""

    number: int
    layout: struct.Struct | None
    """The frame's values (None where a width has no struct code: unpacked one by one)."""
    specs: list[tuple[int, bool]]
    picks: list[int]
    """Positions in the map of the values the sample carries (the edges the part names)."""
    refs: list[EdgeRef]
    convs: list[Conv]
    template: str
    """``"name":%d,"other":%s`` for the picked values."""
    last: tuple[bytes, str | None] | None = None
    """The latest frame encoded and its text (a frame of the same bytes is not again)."""

    def raws(self, frame: bytes) -> Sequence[int]:
        try:
            if self.layout is not None:
                values: Sequence[int] = self.layout.unpack(frame)
            else:
                values = mca.unpack_values(self.specs, frame)
        except (struct.error, ValueError):
            return ()  # not this map's length: a frame the loop will not decode either
        return values if len(self.picks) == len(values) else [values[i] for i in self.picks]

    def fragment(self, frame: bytes) -> str | None:
        last = self.last
        if last is not None and last[0] == frame:
            return last[1]
        raws = self.raws(frame)
        text = None if not raws else fill(self.template, self.convs, raws)
        self.last = (frame, text)
        return text


def fill(template: str, convs: Sequence[Conv], raws: Sequence[int]) -> str:
    """``template`` with the values of ``raws`` in its places."""
    if not any(convs):
        return template % tuple(raws)
    return template % tuple(r if c is None else c(r) for c, r in zip(convs, raws,
                                                                     strict=True))


class _Slots:
    """A board's CI (or PAR) values, read from one of the snapshot's dicts by their keys
    (``(board, index)`` for a CI, the EdgeRef for a PAR)."""

    def __init__(self, refs: list[EdgeRef], slot: Callable[[EdgeRef], Any]) -> None:
        self.refs = refs
        convs, places = zip(*(conv_of(r) for r in refs), strict=True) if refs else ((), ())
        self.convs: list[Conv] = list(convs)
        self.slots = [slot(r) for r in refs]
        self.names = [f"{_json(r.unique)}:" for r in refs]
        """Each value's ``"name":`` (plain text, for the values of a partial dict)."""
        self.template = ",".join(f"{_text(r.unique)}:{p}"
                                 for r, p in zip(refs, places, strict=True))
        self._get = itemgetter(*self.slots) if len(refs) > 1 else None
        self._seen: dict[Any, int] | None = None
        self._text = ""

    def text(self, values: dict[Any, int]) -> str:
        """The values' fragment (the same dict as last time: the same text)."""
        if not self.refs:
            return ""
        if values is self._seen or values == self._seen:
            return self._text
        try:
            raws = self._get(values) if self._get is not None else (values[self.slots[0]],)
            text = fill(self.template, self.convs, raws)
        except KeyError:  # some have no value (a PAR nobody wrote): those are left out
            text = ",".join(n + write(c, values[k]) for n, c, k in zip(
                self.names, self.convs, self.slots, strict=True) if k in values)
        self._seen, self._text = values, text
        return text


class BoardEncoder:
    """One board's ``values`` sample from a :class:`RawSnapshot`, and the samples of its
    edges' own keys."""

    def __init__(self, image: PartImage, robot: str, bus: str, board: int,
                 refs: Sequence[EdgeRef]) -> None:
        self.bus, self.board = bus, board
        self.key = keys.board_key(robot, bus, board)
        self._head = (f'{{"v":{keys.VERSION},"robot":{_json(robot)},"bus":{_json(bus)},'
                      f'"board":{board},"t":')
        by_index = {r.index: r for r in refs if r.kind is mca.Kind.SO}
        described = image.described(bus, board)
        records = described.so if described is not None else ()
        self._maps: list[_SoMap] = []
        self.edge_source: dict[EdgeRef, tuple[str, Any, int]] = {}
        """Where an edge's raw value is: ("so", the map, its position among the picked
        values), ("ci", its key, 0) or ("par", its key, 0)."""
        for m in image.so_maps(bus):
            if m.board != board:
                continue
            specs = [(records[i].width, records[i].signed) for i in m.edges]
            picks = [p for p, i in enumerate(m.edges) if i in by_index]
            if not picks:
                continue
            code = "".join(_FORMATS.get(s, "?") for s in specs)
            layout = struct.Struct(">" + code) if "?" not in code else None
            mrefs = [by_index[m.edges[p]] for p in picks]
            convs, places = zip(*(conv_of(r) for r in mrefs), strict=True)
            template = ",".join(f"{_text(r.unique)}:{place}"
                                for r, place in zip(mrefs, places, strict=True))
            so = _SoMap(m.number, layout, specs, picks, mrefs, list(convs), template)
            self._maps.append(so)
            for pos, r in enumerate(mrefs):
                self.edge_source[r] = ("so", so, pos)
        self._ci = _Slots([r for r in refs if r.kind is mca.Kind.CI],
                          lambda r: (board, r.index))
        self._par = _Slots([r for r in refs if r.kind is mca.Kind.PAR], lambda r: r)
        for r in self._ci.refs:
            self.edge_source[r] = ("ci", (board, r.index), 0)
        for r in self._par.refs:
            self.edge_source[r] = ("par", r, 0)
        self._edge_heads = {r: f',"name":{_json(r.unique)},"value":' for r in refs}

    def sample(self, snap: RawSnapshot, lost: tuple[float, str] | None = None) -> bytes:
        """The board's ``values`` sample (``man/ucom-network.7``): JSON, as
        ``keys.dumps({"robot", "bus", "board", "t", "values", "valid"})`` of the decoded
        values; where the board is ``lost`` (since when, on the frames' time base, and what
        was seen last) ``"valid": false`` and ``"lost": {"since", "seen"}``: its values
        are its last before the loss."""
        frames, stamps = snap.frames[self.bus], snap.stamps[self.bus]
        parts = []
        t: float | None = None
        for m in self._maps:
            frame = frames.get(m.number)
            if frame is None:
                continue
            text = m.fragment(frame)
            if text is None:
                continue
            parts.append(text)
            s = stamps.get(m.number, snap.clock)
            if t is None or s > t:
                t = s
        for text in (self._ci.text(snap.ci[self.bus]), self._par.text(snap.par)):
            if text:
                parts.append(text)
        tail = ('},"valid":true}' if lost is None else
                '},"valid":false,"lost":{"since":' + _stamp(lost[0]) + ',"seen":'
                + _json(lost[1]) + "}}")
        return (self._head + _stamp(snap.clock if t is None else t) + ',"values":{'
                + ",".join(parts) + tail).encode()

    def edge_sample(self, ref: EdgeRef, snap: RawSnapshot, valid: bool = True,
                    ) -> bytes | None:
        """The sample of one edge's own key (``{"v", "t", "name", "value", "valid"}``),
        None where the snapshot has no value of it; ``valid`` false: its board is lost."""
        where, what, pos = self.edge_source[ref]
        t: float = snap.clock
        raw: int | None
        if where == "so":
            frame = snap.frames[self.bus].get(what.number)
            raws = what.raws(frame) if frame is not None else ()
            if not raws:
                return None
            raw, conv = raws[pos], what.convs[pos]
            t = snap.stamps[self.bus].get(what.number, snap.clock)
        elif where == "ci":
            raw, conv = snap.ci[self.bus].get(what), conv_of(ref)[0]
        else:
            raw, conv = snap.par.get(what), conv_of(ref)[0]
        if raw is None:
            return None
        return (f'{{"v":{keys.VERSION},"t":{_stamp(t)}{self._edge_heads[ref]}'
                f'{write(conv, raw)},"valid":{"true" if valid else "false"}}}').encode()


def encoders(image: PartImage, robot: str) -> dict[BoardKey, BoardEncoder]:
    """A :class:`BoardEncoder` for every board the part names edges of (checked)."""
    by_board: dict[BoardKey, list[EdgeRef]] = {}
    for ref in image.refs:
        by_board.setdefault((ref.bus, ref.board), []).append(ref)
    return {b: BoardEncoder(image, robot, b[0], b[1], refs) for b, refs in by_board.items()}
