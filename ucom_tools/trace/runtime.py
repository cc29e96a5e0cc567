"""Decoding the run time: MCA requests and descriptions, Admin Data, MCA Alive, SO and CI
maps and their periods, values with the edges' names."""

from __future__ import annotations

from collections.abc import Callable
from decimal import Decimal
from typing import Any

from ucom_tools.config.attrtree import TreeEdgeKind
from ucom_tools.errors import FrameError
from ucom_tools.trace.bus import (
    BusState,
)
from ucom_tools.trace.conversation import (
    BOARD_TO_PC,
    PC_TO_BOARD,
    Message,
    _board_order,
)
from ucom_tools.trace.state import (
    MAP_PERIODS_LATE,
    MAP_SLACK,
    Edge,
    Periodic,
    SoMap,
    TracedBoard,
)
from ucom_tools.trace.text import (
    _ms,
    _to,
    jsonable,
)
from ucom_tools.wire import mca
from ucom_tools.wire.digest import DescrDigest, DigestRequest
from ucom_tools.wire.ids import Function


class RuntimeDecoding(BusState):
    """The run-time traffic (a part of :class:`BusDecoder`)."""

    def _mca_request(self, board: str, target: str | None, msg: object) -> None:
        reply = self.owner.timeouts.reply
        bd = self.boards.get(board) if target else None
        if isinstance(msg, mca.MapFrame):
            self._ci_map(msg)
            return
        if isinstance(msg, mca.Alive):
            self._alive(board)
            return
        fn = int(msg.FUNCTION)  # type: ignore[attr-defined]
        label = Function(fn).label

        def acked(first: int) -> Callable[[str, object], bool]:
            return lambda _b, a: isinstance(a, mca.McaReady) and a.answers == fn and \
                a.echo[0] == first

        if isinstance(msg, mca.EdgeWrite):
            text, values = self._values_text(bd, msg.kind, msg.index, msg.data)
            self.add(board, label, text, {"kind": msg.kind, "index": msg.index,
                     "data": msg.data, "values": values}, direction=PC_TO_BOARD)
            if bd is not None and msg.kind is mca.Kind.PAR:
                self._maybe_cycle(bd, msg.index, msg.data)
            self.expect(f"{label} {msg.kind.name} {msg.index}{_to(board)}", fn, target,
                        reply, acked(msg.index), key=(msg.index, msg.data))
        elif isinstance(msg, mca.McaStart):
            self.add(board, label, msg.op.name, {"op": msg.op}, direction=PC_TO_BOARD)
            if msg.op is mca.StartOp.STOP:
                for b in self.boards.values():
                    if target is None or b.label == target:
                        self._stop_exchange(b, self.t)
            t0 = self.t

            def state(b: str, a: object, _t: float) -> None:
                if isinstance(a, mca.McaReady) and msg.op is mca.StartOp.START and \
                        a.state is mca.RunState.RUNNING:
                    self._run_exchange(self.board(b), t0)

            self.expect(f"{label} {msg.op.name}{_to(board)}", fn, target, reply,
                        acked(int(msg.op)), key=(msg.op,), on_answer=state)
        elif isinstance(msg, (mca.DescrRequest, DigestRequest)):
            self._descr_request(board, target, label, fn, msg)
        elif isinstance(msg, mca.DumpRequest):
            last = msg.index + msg.count - 1
            self.add(board, label, f"{msg.kind.name} {msg.index}-{last} ({msg.count} values)",
                     {"kind": msg.kind, "index": msg.index, "count": msg.count},
                     direction=PC_TO_BOARD)
            kind = msg.kind
            self.expect(f"{label} {kind.name} {msg.index}-{last}{_to(board)}", fn,
                        target, reply, lambda _b, a: isinstance(a, mca.DumpValues) and
                        a.kind is kind, needed=self._dump_frames(bd, msg),
                        key=(kind, msg.index, msg.count))
        elif isinstance(msg, mca.AdminData):
            self._admin(board, target, msg, acked)
        else:
            self.add(board, label, "", direction=PC_TO_BOARD)

    def _descr_request(self, board: str, target: str | None, label: str, fn: int,
                       msg: mca.DescrRequest | DigestRequest) -> None:
        """MCA DumpIO Descr Request: the records it asks for (complete with the last one
        the board's counts announce), or the description's digest."""
        reply = self.owner.timeouts.reply
        if isinstance(msg, DigestRequest):
            self.add(board, label, "the description's digest", direction=PC_TO_BOARD)
            self.expect(f"{label} (digest){_to(board)}", fn, target, reply,
                        lambda _b, a: isinstance(a, DescrDigest), key=("digest",))
            return
        what = "every edge" if msg.kind is None else f"{msg.kind.name} {msg.index}"
        self.add(board, label, what, {"kind": msg.kind, "index": msg.index},
                 direction=PC_TO_BOARD)
        kind, index = msg.kind, msg.index
        have: set[tuple[mca.Kind, int]] = set()

        def described(b: str, a: object, _t: float) -> None:
            # complete with the last record the board's counts announce
            bd_ = self.board(b)
            if not isinstance(a, mca.DescrSegment) or not a.last:
                return
            have.add((a.kind, a.index))
            wanted = {(kind, index)} if kind is not None else {
                (k, i) for k, n in zip(mca.Kind, bd_.counts or (), strict=False)
                for i in range(n)} if bd_.counts is not None else None
            if wanted is not None and wanted <= have:
                for e in self.expects:
                    if e.key == (fn, target, kind, index):
                        e.done = True

        self.expect(f"{label} ({what}){_to(board)}", fn, target, reply,
                    lambda _b, a: isinstance(a, mca.DescrSegment) and
                    (kind is None or (a.kind is kind and a.index == index)),
                    needed=None, key=(kind, index), on_answer=described)

    def _admin(self, board: str, target: str | None, msg: mca.AdminData,
               acked: Callable[[int], Callable[[str, object], bool]]) -> None:
        bd = self.boards.get(board) if target else None
        fields_: dict[str, Any] = {"op": msg.op}
        if msg.op is mca.AdminOp.ALIVE:
            text = f"ALIVE: watchdog {msg.alive_ms} ms"
            fields_["watchdog_ms"] = msg.alive_ms
        elif msg.op is mca.AdminOp.SO_MAP:
            names = [self._edge_label(bd, mca.Kind.SO, i) for i in msg.edges
                     if i != mca.NO_EDGE]
            text = f"SO_MAP map {msg.map_no}, every {msg.period} cycles: {', '.join(names)}"
            fields_.update(map=msg.map_no, period=msg.period, edges=list(msg.edges),
                           names=names)
            self.so_msgs.pop(msg.map_no, None)
            if target is not None:
                edges = tuple(i for i in msg.edges if i != mca.NO_EDGE)
                old = self.so_maps.get(msg.map_no)
                if old is not None:
                    self._check_map_end(old, self.t)
                if msg.period == 0:
                    self.so_maps.pop(msg.map_no, None)
                else:
                    self.so_maps[msg.map_no] = SoMap(msg.map_no, target, edges, msg.period,
                                                      self.t)
        elif msg.op is mca.AdminOp.CI_MAP:
            slots = [self._edge_label(bd, mca.Kind.CI, i) if i != mca.NO_EDGE else "-"
                     for i in msg.edges]
            text = f"CI_MAP map {msg.map_no}: slots {', '.join(slots)}"
            fields_.update(map=msg.map_no, slots=list(msg.edges), names=slots)
            self.ci_msgs.pop(msg.map_no, None)
            if target is not None:
                users = self.ci_maps.setdefault(msg.map_no, {})
                if all(i == mca.NO_EDGE for i in msg.edges):
                    users.pop(target, None)
                else:
                    users[target] = tuple(msg.edges)
        else:
            text = "CLEAR_MAPS"
            if target is not None:
                for no, so in list(self.so_maps.items()):
                    if so.board == target:
                        self._check_map_end(so, self.t)
                        del self.so_maps[no]
                for users in self.ci_maps.values():
                    users.pop(target, None)
        self.add(board, "MCA Admin Data", text, fields_, direction=PC_TO_BOARD)
        first = msg.args[0] if msg.args else 0
        self.expect(f"MCA Admin Data {msg.op.name}{_to(board)}",
                    Function.MCA_ADMIN_DATA, target, self.owner.timeouts.reply,
                    lambda _b, a: isinstance(a, mca.McaReady) and
                    a.answers == Function.MCA_ADMIN_DATA and a.echo == bytes((msg.op, first)),
                    key=(msg.op, first))

    def _alive(self, board: str) -> None:
        msg = self.alive_msg.get(board)
        last = self.alive_last.get(board)
        self.alive_last[board] = self.t
        if msg is None or last is None or self.t - last > 1.0:
            self.alive_msg[board] = self.add(board, "MCA Alive", "1 frame", {
                "frames": 1, "first_t": self.t, "last_t": self.t}, direction=PC_TO_BOARD)
            return
        msg.frames += 1
        msg.members.append(self.index)
        first = msg.fields["first_t"]
        every = (self.t - first) / (msg.frames - 1)
        msg.fields.update(frames=msg.frames, last_t=self.t, every_ms=round(every * 1000, 3))
        msg.text = f"{msg.frames} frames until {self.t:.6f} s, every {every * 1000:.3f} ms"

    def _ci_map(self, msg: mca.MapFrame) -> None:
        users = self.ci_maps.get(msg.map_no, {})
        items: list[tuple[str, Edge | None, int, dict[str, Any]]] = []
        for board, slots in sorted(users.items(), key=lambda kv: _board_order(kv[0])):
            bd = self.boards.get(board)
            for slot, index in enumerate(slots):
                if index == mca.NO_EDGE or 2 * slot + 2 > len(msg.data):
                    continue
                raw_bytes = msg.data[2 * slot:2 * slot + 2]
                edge = self._edge(bd, mca.Kind.CI, index)
                raw = int.from_bytes(raw_bytes, "big", signed=edge.signed if edge else True)
                items.append((f"{board}:{edge.label if edge else f'CI {index}'}", edge, raw,
                              {"board": board, "slot": slot, "index": index}))
        self._periodic(f"CI map {msg.map_no}", msg, items, PC_TO_BOARD, self.ci_msgs,
                       msg.map_no)

    def _periodic(self, board: str, msg: mca.MapFrame,
                  items: list[tuple[str, Edge | None, int, dict[str, Any]]],
                  direction: str, store: dict[int, Message], number: int) -> Message:
        """Process data summarised: one message per map (until the map is defined anew)
        with its frame count, interval, last values and their ranges (its text is
        written when the trace ends: :meth:`_summarise`)."""
        agg = store.get(number)
        if agg is None or agg.board != board:
            agg = store[number] = self.add(board, Function(msg.function).label, "", {
                "map": number, "first_t": round(self.t, 6)}, direction=direction)
            self.periodic[id(agg)] = Periodic(agg)
        else:
            agg.frames += 1
            agg.members.append(self.index)
        state = self.periodic[id(agg)]
        state.last_t, state.items, state.data = self.t, items, msg.data
        ranges = state.ranges
        for key, edge, raw, _ in items:
            value = edge.value(raw) if edge is not None else Decimal(raw)
            lo_hi = ranges.get(key)
            if lo_hi is None:
                ranges[key] = (value, value)
            elif value < lo_hi[0] or value > lo_hi[1]:
                ranges[key] = (min(lo_hi[0], value), max(lo_hi[1], value))
        return agg

    def _summarise(self) -> None:
        """The texts and fields of the process-data summaries."""
        for state in self.periodic.values():
            agg, ranges = state.agg, state.ranges
            last: list[dict[str, Any]] = []
            texts: list[str] = []
            for key, edge, raw, extra in state.items:
                if edge is None:
                    last.append({**extra, "raw": raw})
                    text = f"{key}=raw {raw}"
                else:
                    last.append({**extra, **edge.json(raw)})
                    text = f"{key}={edge.value(raw):f}" + (f" {edge.unit}" if edge.unit
                                                           else "")
                lo, hi = ranges[key]
                if lo != hi:
                    text += f" ({lo:f}..{hi:f})"
                texts.append(text)
            agg.fields.update(frames=agg.frames, last_t=round(state.last_t, 6),
                              values=jsonable(last),
                              ranges={k: [format(lo, "f"), format(hi, "f")]
                                      for k, (lo, hi) in ranges.items()},
                              data=state.data.hex(" ").upper())
            every = ""
            if agg.frames > 1:
                period = (state.last_t - agg.fields["first_t"]) / (agg.frames - 1)
                agg.fields["every_ms"] = round(period * 1000, 3)
                every = f", every {period * 1000:.3f} ms"
            shown = "; ".join(texts) if texts else \
                f"values {state.data.hex(' ').upper()} (map not defined in the trace)"
            owner = f"board {agg.fields['board']}, " if "board" in agg.fields else ""
            agg.text = (f"{owner}{agg.frames} frame{'s' if agg.frames != 1 else ''} until "
                        f"{state.last_t:.6f} s{every}; last: {shown}")

    def _so_map(self, board_label: str, msg: mca.MapFrame) -> None:
        so = self.so_maps.get(msg.map_no)
        items: list[tuple[str, Edge | None, int, dict[str, Any]]] = []
        if so is not None:
            bd = self.boards.get(so.board)
            edges = [self._edge(bd, mca.Kind.SO, i) for i in so.edges]
            known_edges = [e for e in edges if e is not None]
            if len(known_edges) == len(edges):
                try:
                    raws = mca.unpack_values([(e.width, e.signed) for e in known_edges],
                                             msg.data)
                except FrameError:
                    raws = []
                items = [(e.label, e, raw, {}) for e, raw in zip(known_edges, raws,
                                                                  strict=False)]
            self._check_map_gap(so)
            so.last = self.t
            agg = self.so_msgs.get(msg.map_no)
            if agg is None or agg.board != board_label:
                agg = None
            if agg is None:
                self.so_msgs.pop(msg.map_no, None)
        agg = self._periodic(board_label, msg, items, BOARD_TO_PC, self.so_msgs, msg.map_no)
        if so is not None and "board" not in agg.fields:
            agg.fields.update(board=so.board, edges=list(so.edges))

    # ------------------------------------------------------------------ SO map periods
    def _interval(self, so: SoMap) -> float:
        bd = self.boards.get(so.board)
        cycle = bd.cycle_us if bd is not None else 1000.0
        return so.period * cycle / 1e6

    def _tolerance(self, so: SoMap) -> float:
        return MAP_PERIODS_LATE * self._interval(so) + MAP_SLACK + self.owner.margin

    def _map_ref(self, so: SoMap) -> float | None:
        """Since when a frame of ``so`` is due: its last frame, the exchange's start or
        the map's definition, whichever was last; None while its board does not run."""
        bd = self.boards.get(so.board)
        if bd is None or bd.exchange_since is None:
            return None
        return max(x for x in (so.last, bd.exchange_since, so.defined) if x is not None)

    def _check_map_gap(self, so: SoMap) -> None:
        ref = self._map_ref(so)
        if ref is None or so.reported:
            return
        gap = self.t - ref
        if gap > self._tolerance(so):
            so.reported = True
            self.violation("so-map-stopped", f"SO map {so.number} of board {so.board}: no "
                           f"frame for {_ms(gap)} (since {ref:.6f} s), its period is "
                           f"{_ms(self._interval(so))}", so.board)

    def _check_map_end(self, so: SoMap, until: float) -> None:
        ref = self._map_ref(so)
        if ref is None or so.reported:
            return
        gap = until - ref
        if gap > self._tolerance(so):
            so.reported = True
            self.violation("so-map-stopped", f"SO map {so.number} of board {so.board}: no "
                           f"frame since {ref:.6f} s, {_ms(gap)} before its exchange ended "
                           f"or the trace did; its period is {_ms(self._interval(so))}",
                           so.board, t=until)

    def _run_exchange(self, bd: TracedBoard, since: float) -> None:
        if bd.exchange_since is None:
            bd.exchange_since = since
            for so in self.so_maps.values():
                if so.board == bd.label:
                    so.reported = False
        else:  # START again: every map starts its period afresh
            bd.exchange_since = since

    def _stop_exchange(self, bd: TracedBoard, until: float) -> None:
        if bd.exchange_since is None:
            return
        for so in self.so_maps.values():
            if so.board == bd.label:
                self._check_map_end(so, until)
        bd.exchange_since = None

    # ------------------------------------------------------------------ edges
    def _bind(self, bd: TracedBoard | None) -> None:
        if bd is None or bd.bound_done:
            return
        trees = self.owner.trees
        bd.bound_done = True
        if trees is None or not bd.label.isdigit():
            return
        mine = [b for b in trees.boards if b.bus == self.name]
        found = [b for b in mine if bd.serial is not None and b.spec.serial == bd.serial]
        if not found:
            found = [b for b in mine if b.spec.position == int(bd.label) - 1]
        bd.edges.clear()
        if found:
            bd.bound = found[0]
            bd.spec = self.owner.program(found[0])

    def _edge(self, bd: TracedBoard | None, kind: mca.Kind, index: int) -> Edge | None:
        """What is known of an edge of board ``bd`` (cached until its records or binding
        change)."""
        if bd is None:
            return None
        self._bind(bd)
        key = (kind, index)
        if key in bd.edges:
            return bd.edges[key]
        edge = bd.edges[key] = self._edge_of(bd, kind, index)
        return edge

    def _edge_of(self, bd: TracedBoard, kind: mca.Kind, index: int) -> Edge | None:
        unique = prefix = None
        if bd.bound is not None:
            block = bd.bound.board
            of_kind = block.of_kind(TreeEdgeKind[kind.name])
            if index < len(of_kind):
                unique, prefix = of_kind[index].unique, block.prefix
        rec = bd.records.get((kind, index))
        if rec is not None:
            return Edge(kind, index, rec.name, unique, prefix, rec.width, rec.signed,
                         rec.exponent, rec.unit)
        if bd.spec is not None:
            edges = bd.spec.of(kind)  # type: ignore[arg-type]
            if index < len(edges):
                e = edges[index]
                return Edge(kind, index, e.name, unique, prefix, e.width, e.signed,
                             e.exponent, e.unit)
        return None

    def _edge_label(self, bd: TracedBoard | None, kind: mca.Kind, index: int) -> str:
        e = self._edge(bd, kind, index)
        return e.label if e is not None else f"{kind.name} {index}"

    def _values_text(self, bd: TracedBoard | None, kind: mca.Kind, index: int, data: bytes
                     ) -> tuple[str, list[dict[str, Any]]]:
        """The values of consecutive edges from ``index`` in ``data``, as text and JSON;
        raw bytes when the edges are not known."""
        edges: list[Edge] = []
        size = 0
        while size < len(data):
            e = self._edge(bd, kind, index + len(edges))
            if e is None:
                break
            edges.append(e)
            size += e.width
        if not edges or size != len(data):
            return (f"{kind.name} {index}: {data.hex(' ').upper()}", [])
        raws = mca.unpack_values([(e.width, e.signed) for e in edges], data)
        return (f"{kind.name} {index}: " + ", ".join(e.text(r) for e, r in
                                                    zip(edges, raws, strict=True)),
                [e.json(r) for e, r in zip(edges, raws, strict=True)])

    def _dump_frames(self, bd: TracedBoard | None, msg: mca.DumpRequest) -> int | None:
        """MCA DSP CI frames that answer ``msg`` (a new frame when the next value would
        pass 6 bytes); None when the widths are not known."""
        frames, size = 0, 0
        for i in range(msg.index, msg.index + msg.count):
            e = self._edge(bd, msg.kind, i)
            if e is None:
                return None
            if frames == 0 or size + e.width > 6:
                frames, size = frames + 1, 0
            size += e.width
        return frames or None

    def _maybe_cycle(self, bd: TracedBoard, index: int, data: bytes) -> None:
        """A PAR write that sets the program's cycle time changes its SO map periods."""
        pos = 0
        i = index
        while pos < len(data):
            e = self._edge(bd, mca.Kind.PAR, i)
            if e is None:
                return
            if e.name in self.owner.cycle_edges and e.unit in ("ms", "us"):
                raw = int.from_bytes(data[pos:pos + e.width], "big", signed=e.signed)
                us = float(e.value(raw)) * (1000 if e.unit == "ms" else 1)
                if us > 0:
                    bd.cycle_us = us
            pos += e.width
            i += 1

    # ------------------------------------------------------------------ answers

    def _segment(self, bd: TracedBoard, seg: mca.DescrSegment) -> None:
        key = (seg.kind, seg.index)
        entry = bd.segments.get(key)
        if entry is None or (seg.segment == 0 and 0 in entry[1]):
            msg = self.add(bd.label, "MCA DumpIO Descr", f"{seg.kind.name} {seg.index}: "
                           "(incomplete record)", {"kind": seg.kind, "index": seg.index},
                           direction=BOARD_TO_PC)
            msg.frames = 0
            msg.members.clear()
            entry = bd.segments[key] = (msg, {})
        msg, parts = entry
        parts[seg.segment] = seg.data
        msg.frames += 1
        msg.members.append(self.index)
        self.answer(bd.label, seg)
        if seg.last and all(i in parts for i in range(seg.segment + 1)):
            del bd.segments[key]
            try:
                rec = mca.EdgeRecord.decode(b"".join(parts[i] for i in range(seg.segment + 1)))
            except FrameError as err:
                msg.text = f"{seg.kind.name} {seg.index}: malformed record: {err}"
                self.violation("malformed", f"MCA DumpIO Descr {seg.kind.name} {seg.index}: "
                               f"{err.field}: {err.message}", bd.label)
                return
            bd.records[key] = rec
            bd.edges.pop(key, None)
            edge = self._edge(bd, seg.kind, seg.index)
            name = rec.name + (f" = {edge.unique}" if edge is not None and edge.unique
                               and edge.unique != rec.name else "")
            lo, hi = (Decimal(x).scaleb(rec.exponent) for x in (rec.minimum, rec.maximum))
            msg.text = (f"{seg.kind.name} {seg.index} '{name}': {'s' if rec.signed else 'u'}"
                        f"{rec.width}, exponent {rec.exponent}, {lo:f}..{hi:f}"
                        + (f" {rec.unit}" if rec.unit else ""))
            msg.fields = jsonable({"kind": seg.kind, "index": seg.index, "name": rec.name,
                                   "unique": edge.unique if edge else None,
                                   "width": rec.width, "signed": rec.signed,
                                   "exponent": rec.exponent, "minimum": rec.minimum,
                                   "maximum": rec.maximum, "unit": rec.unit})

    def _flush_partial(self, bd: TracedBoard) -> None:
        self._flush_info(bd)
        self._flush_text(bd)

