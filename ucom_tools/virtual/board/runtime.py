"""A running program's side of the run-time protocol (``man/ucom-protocol.7``, RUN TIME).

:class:`McaRuntime` sits between the board's CAN interface and a program model
(:mod:`ucom_tools.virtual.programs.base`): it takes the generic MCA messages (edge writes,
MCA Start, descriptions, dumps, Admin Data, Alive) and the CI process-data maps, range
checks every value before it reaches the model, sends the SO maps at their periods, runs
the control loop at the program's LoopTime on the fleet clock, accounts the load, keeps
the watchdog and drives the run-mode LEDs (B.2.3).

Safety: after Start the exchange is STOPPED and every motor off; only MCA Start START
lets the program drive.  While RUNNING, no MCA Alive for the watchdog time stops every
motor at once (PWM 0, controllers off) and LATCHES: CI is refused, the motors stay off,
until the PC sends MCA Start START again.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from operator import itemgetter
from typing import Final

from ucom_tools.edgelists.model import EdgeKind, EdgeSpec, ProgramSpec
from ucom_tools.errors import FrameError
from ucom_tools.virtual.board import mutants
from ucom_tools.virtual.board.port import BoardPort
from ucom_tools.virtual.programs.base import Plant, ProgramModel
from ucom_tools.wire import mca
from ucom_tools.wire.answers import AppReport
from ucom_tools.wire.codes import ErrorCode
from ucom_tools.wire.digest import DescrDigest, DigestRequest, digest_of
from ucom_tools.wire.ids import Function

_FORMAT: Final = {(2, True): "h", (2, False): "H", (4, True): "i", (4, False): "I"}
_MASK_TABLE: Final = bytes(b ^ mca.MAP_MASK for b in range(256))
_ALIVE: Final = int(Function.MCA_ALIVE)
"""``bytes.translate`` table of :func:`ucom_tools.wire.mca.mask`."""

FRAME_COST_US: Final = 4.0
"""Execution time the program spends per CAN frame it handles (added to the load)."""
BLINK_CYCLES: Final = 250
"""The green LED toggles every 250 cycles: 2 Hz at 1 ms, 6 Hz at 333 us."""
OVERRUN_FLASH_US: Final = 50_000.0
"""The yellow LED lights this long after a cycle overran."""
CAN_ERROR_FLASH_US: Final = 50_000.0
"""The red LED lights this long after a CAN error (an error frame, or a frame the program
could not take)."""
NO_FUNCTION: Final = 0xFF
"""Error byte 1 when an error answers no frame (an overrun)."""
LOAD_WINDOW: Final = 100
"""The load figure is the share of the last completed window of this many cycles."""
REPORT_EVERY: Final = 1000
"""Errors that could repeat every cycle (an overrun, refused CI, a bad CI map frame) are
sent for the first occurrence and then for every 1000th."""


@dataclass
class SoMap:
    number: int
    period: int
    edges: tuple[int, ...]
    layout: struct.Struct
    """The values' big-endian layout (built once, when the map is defined)."""
    arbitration_id: int
    countdown: int = 0
    pick: Callable[[list[int]], tuple[int, ...]] = field(init=False, repr=False,
                                                          compare=False)
    """The map's values out of the SO list, as a tuple (built once)."""
    pack: Callable[..., bytes] = field(init=False, repr=False, compare=False)
    """:attr:`layout`'s ``pack``, bound once (not looked up for every frame)."""

    def __post_init__(self) -> None:
        self.pack = self.layout.pack
        if len(self.edges) == 1:
            only = self.edges[0]
            self.pick = lambda so: (so[only],)
        else:
            self.pick = itemgetter(*self.edges)


@dataclass
class CiMap:
    number: int
    slots: tuple[int, ...]
    layout: struct.Struct
    """Four 16-bit slots, each signed as its edge (an unused slot unsigned)."""
    needs: int
    """Bytes a frame of this map must have: up to its last used slot."""
    checks: tuple[tuple[int, int, int, int], ...] = ()
    """Per used slot, in slot order: (slot, edge index, the edge's minimum, maximum)."""
    unpack: Callable[[bytes], tuple[int, ...]] = field(init=False, repr=False,
                                                       compare=False)
    """:attr:`layout`'s ``unpack``, bound once (not looked up for every frame)."""

    def __post_init__(self) -> None:
        self.unpack = self.layout.unpack


@dataclass
class LoopStats:
    cycles: int = 0
    overruns: int = 0
    last_work_us: float = 0.0
    last_late_us: float = 0.0
    work_us: float = 0.0
    """Work since the last load figure."""
    span_us: float = 0.0
    load: float = 0.0
    """Share of the cycle time the program used over the last window of cycles."""
    refused_ci: int = 0
    map_errors: int = 0
    frames: int = 0
    history: list[float] = field(default_factory=list)


class McaRuntime:
    """The run-time exchange of one running program."""

    def __init__(self, port: BoardPort, spec: ProgramSpec, model: ProgramModel,
                 plant: Plant | None, t: float, *, defect: str | None = None) -> None:
        self.port = port
        self.defect = defect
        """The board's defect (:mod:`~ucom_tools.virtual.board.mutants`), None if it conforms."""
        self._watchdog = defect != mutants.IGNORE_ALIVE
        self._range_check = defect != mutants.NO_RANGE_CHECK
        self._refuse_latched = defect != mutants.CI_WHILE_LATCHED
        self._so_slow = defect == mutants.SO_SLOW
        self.spec = spec
        self.model = model
        self.plant = plant
        self.state = mca.RunState.STOPPED
        self.alive_ms = mca.ALIVE_DEFAULT_MS
        self.last_alive = t
        self.so_maps: dict[int, SoMap] = {}
        self.ci_maps: dict[int, CiMap] = {}
        self.stats = LoopStats()
        self.overrun_at = -1e18
        self.can_error_at = -1e18
        self.can_errors = 0
        self.overrun_depth = 0.0
        self.flags = 0
        self.latched_by_watchdog = False
        self.latched_at: float | None = None
        """Fleet time (us) of the last watchdog latch."""
        self.stopped = False
        self.digest: int | None = None
        """The description's digest, once asked for (:meth:`_digest`)."""
        self.last_tick = t
        """When the loop last ran (and moved the plant)."""
        self._on_tick: Callable[[float], None] = self._tick
        """:meth:`_tick` bound once (each read of ``self._tick`` makes a new bound method)."""
        self._kinds = {k: spec.of(EdgeKind(k)) for k in mca.Kind}
        self._values = {mca.Kind.CI: model.ci, mca.Kind.SO: model.so, mca.Kind.PAR: model.par}
        model.stop()
        port.at(t + model.loop_us(), self._on_tick)
        self._ready(t, Function.MCA_READY, b"\0\0")

    # ------------------------------------------------------------------ life
    def end(self) -> None:
        """The program ends (reset, power loss): the loop stops scheduling itself."""
        self.stopped = True
        self.model.stop()

    def settle(self, t: float) -> None:
        """The plant moves on to ``t`` with the outputs as the last cycle set them (the
        board loses power at ``t``: they drove until then)."""
        if self.plant is not None and not self.stopped and t > self.last_tick:
            self.plant.advance(t - self.last_tick)
            self.last_tick = t

    def _tick(self, t: float) -> None:
        if self.stopped:
            return
        dt = t - self.last_tick
        self.last_tick = t
        if self.plant is not None:
            self.plant.advance(dt)
        running = self.state is mca.RunState.RUNNING
        if running and t - self.last_alive > self.alive_ms * 1000.0 and self._watchdog:
            self._latch(t)
            running = False
        model, s = self.model, self.stats
        work = model.step(dt) + FRAME_COST_US * s.frames
        s.frames = 0
        loop = model.loop_us()
        # the cycle's accounting
        s.cycles += 1
        s.last_work_us = work
        s.work_us += work
        span = work if work > loop else loop  # max(loop, work)
        s.span_us += span
        if s.cycles % LOAD_WINDOW == 0:
            s.load = s.work_us / s.span_us if s.span_us else 0.0
            s.work_us = s.span_us = 0.0
        if work > loop:
            self._overrun(t, work, loop)
        if running:
            if self._so_slow:
                self._send_maps_slow(t + (loop if loop < work else work))
            else:
                self._send_maps(t + (loop if loop < work else work))  # min(work, loop)
        self.port.at(t + span, self._on_tick)

    def _overrun(self, t: float, work: float, loop: float) -> None:
        s = self.stats
        s.overruns += 1
        s.last_late_us = work - loop
        self.overrun_at = t
        # a cycle time of 0 or less only reaches a board that does not range-check
        # (mutants.NO_RANGE_CHECK): then every cycle overruns in full
        self.overrun_depth = min(1.0, (work - loop) / loop) if loop > 0 else 1.0
        self.flags |= mca.FLAG_OVERRUN
        if s.overruns == 1 or s.overruns % REPORT_EVERY == 0:
            self.port.error(t, ErrorCode.OVERRUN, NO_FUNCTION,
                            min(int(work - loop), 0xFFFFFFFF))

    def load(self) -> float:
        """The load over the last :data:`LOAD_WINDOW` cycles, or so far if fewer."""
        s = self.stats
        if s.load:
            return s.load
        return s.work_us / s.span_us if s.span_us else 0.0

    def can_error(self, t: float) -> None:
        """A CAN error: an error frame on the bus, or a frame that could not be taken."""
        self.can_errors += 1
        self.can_error_at = t

    def _latch(self, t: float) -> None:
        self.model.stop()
        self.state = mca.RunState.LATCHED
        self.latched_by_watchdog = True
        self.latched_at = t
        self.flags |= mca.FLAG_LATCHED_BY_WATCHDOG
        since = int((t - self.last_alive) / 1000.0)
        self.port.error(t, ErrorCode.WATCHDOG, Function.MCA_ALIVE, since)
        self.port.report_text(t, f"watchdog: no MCA Alive for {since} ms; every motor "
                                 "stopped until MCA Start")

    # ------------------------------------------------------------------ SO maps
    def _send_maps(self, t: float) -> None:
        so = self.model.so
        send = self.port.send_raw
        for m in self.so_maps.values():
            countdown = m.countdown - 1
            if countdown > 0:
                m.countdown = countdown
                continue
            m.countdown = m.period
            send(t, m.arbitration_id, m.pack(*m.pick(so)).translate(_MASK_TABLE))

    def _send_maps_slow(self, t: float) -> None:
        """so-slow: :meth:`_send_maps` with each map's countdown in tenths of a cycle, so
        that a map goes out every 1.1 x its period (on average, on the cycle grid)."""
        so = self.model.so
        for m in self.so_maps.values():
            due, m.countdown = mutants.so_slow_step(m.countdown, m.period)
            if due:
                self.port.send_raw(t, m.arbitration_id,
                                   m.pack(*m.pick(so)).translate(_MASK_TABLE))

    # ------------------------------------------------------------------ frames
    def on_map(self, number: int, data: bytes, t: float) -> None:
        """A CI process-data frame (map ``number``) on the bus."""
        m = self.ci_maps.get(number)
        if m is None:
            return
        self.stats.frames += 1
        if self.state is mca.RunState.LATCHED and self._refuse_latched:
            self._refuse_ci(t)
            return
        if len(data) < m.needs:
            self.can_error(t)
            self._map_error(t, ErrorCode.BAD_LENGTH, number << 8 | len(data))
            return
        raws = m.unpack((data if len(data) == 8 else data[:8].ljust(8, b"\x55"))
                        .translate(_MASK_TABLE))
        checks = m.checks
        for slot, _index, minimum, maximum in checks:
            raw: int = raws[slot]
            if not minimum <= raw <= maximum and self._range_check:
                # nothing of the frame is taken (a value cannot be trusted, its neighbours
                # neither)
                self._map_error(t, ErrorCode.OUT_OF_RANGE, number << 8 | slot)
                return
        ci = self.model.ci
        for slot, index, _minimum, _maximum in checks:
            ci[index] = raws[slot]

    def _map_error(self, t: float, code: ErrorCode, detail: int) -> None:
        """An Error about a CI map frame (function byte 0x80 | 13: process data), the
        first and every :data:`REPORT_EVERY`-th."""
        s = self.stats
        if s.map_errors % REPORT_EVERY == 0:
            self.port.error(t, code, mca.PROCESS_DATA | Function.MCA_CONTROLLER_INPUT, detail)
        s.map_errors += 1

    def on_frame(self, function: int, data: bytes, t: float) -> None:
        """A generic MCA frame addressed to this board (or broadcast)."""
        self.stats.frames += 1
        if function == _ALIVE and not data:  # the PC's, every few ms: what decode() gives
            self.last_alive = t
            return
        try:
            _, msg = mca.decode(function << 6, data)
        except FrameError as err:  # wrong length or reserved value
            code = ErrorCode.BAD_LENGTH if "length" in err.field else ErrorCode.BAD_VALUE
            self.can_error(t)
            self.port.error(t, code, function)
            return
        if isinstance(msg, mca.Alive):
            self.last_alive = t
        elif isinstance(msg, mca.EdgeWrite):
            self._write(msg, t)
        elif isinstance(msg, mca.McaStart):
            self._start(msg, t)
        elif isinstance(msg, mca.DescrRequest):
            self._describe(msg, t)
        elif isinstance(msg, DigestRequest):
            self._digest(t)
        elif isinstance(msg, mca.DumpRequest):
            self._dump(msg, t)
        elif isinstance(msg, mca.AdminData):
            self._admin(msg, t)
        else:  # a board -> PC message sent to us
            self.port.error(t, ErrorCode.UNKNOWN_FUNCTION, function)

    def _ready(self, t: float, answers: int, echo: bytes) -> None:
        k = self._kinds
        so = len(k[mca.Kind.SO]) + (1 if self.defect == mutants.READY_COUNTS_WRONG else 0)
        self.port.send(t + self.port.timing.reply_us, mca.McaReady(
            self.state, answers, echo, len(k[mca.Kind.CI]), so,
            len(k[mca.Kind.PAR]), self.flags))
        self.flags &= ~mca.FLAG_OVERRUN

    def _edges(self, kind: mca.Kind, index: int, count: int, t: float,
               function: int) -> tuple[EdgeSpec, ...] | None:
        edges = self._kinds[kind]
        if index + count > len(edges):
            self.port.error(t, ErrorCode.UNKNOWN_EDGE, function, kind << 8 | index)
            return None
        return edges[index:index + count]

    def _write(self, msg: mca.EdgeWrite, t: float) -> None:
        function = int(msg.FUNCTION)
        if msg.kind is mca.Kind.CI and self.state is mca.RunState.LATCHED and \
                self._refuse_latched:
            self._refuse_ci(t)
            return
        edges = self._kinds[msg.kind]
        if msg.index >= len(edges):
            self.port.error(t, ErrorCode.UNKNOWN_EDGE, function, msg.kind << 8 | msg.index)
            return
        specs, size = [], 0
        for e in edges[msg.index:]:
            if size >= len(msg.data):
                break
            specs.append(e)
            size += e.width
        if size != len(msg.data):
            self.port.error(t, ErrorCode.BAD_LENGTH, function, msg.kind << 8 | msg.index)
            return
        raws = mca.unpack_values([(e.width, e.signed) for e in specs], msg.data)
        for i, (e, raw) in enumerate(zip(specs, raws, strict=True)):
            if not e.minimum <= raw <= e.maximum and self._range_check:
                self.port.error(t, ErrorCode.OUT_OF_RANGE, function,
                                msg.kind << 8 | (msg.index + i))
                return  # nothing of the frame is taken
        values = self._values[msg.kind]
        values[msg.index:msg.index + len(raws)] = raws
        self._ready(t, function, bytes((msg.index, msg.data[0])))

    def _refuse_ci(self, t: float) -> None:
        s = self.stats
        if s.refused_ci % REPORT_EVERY == 0:
            self.port.error(t, ErrorCode.LATCHED, Function.MCA_CONTROLLER_INPUT, s.refused_ci)
        s.refused_ci += 1

    def _start(self, msg: mca.McaStart, t: float) -> None:
        if msg.op is mca.StartOp.START:
            self.state = mca.RunState.RUNNING
            self.latched_by_watchdog = False
            self.flags &= ~mca.FLAG_LATCHED_BY_WATCHDOG
            self.last_alive = t
            self.stats.refused_ci = 0
            for m in self.so_maps.values():
                m.countdown = 0
            self.model.release()
        elif msg.op is mca.StartOp.STOP:
            self.model.stop()
            self.state = mca.RunState.STOPPED
            self.flags &= ~mca.FLAG_LATCHED_BY_WATCHDOG
        self._ready(t, Function.MCA_START, bytes((msg.op, 0)))

    def _describe(self, msg: mca.DescrRequest, t: float) -> None:
        if msg.kind is None:
            wanted = [(k, i) for k in mca.Kind for i in range(len(self._kinds[k]))]
        elif self._edges(msg.kind, msg.index, 1, t, Function.MCA_DUMPIO_DESCR_REQUEST) is None:
            return
        else:
            wanted = [(msg.kind, msg.index)]
        when = t + self.port.timing.reply_us
        for kind, index in wanted:
            for segment in self._record(kind, index).segments(kind, index):
                self.port.send(when, segment)

    def _record(self, kind: mca.Kind, index: int) -> mca.EdgeRecord:
        """The record of an edge as MCA DumpIO Descr sends it."""
        e = self._kinds[kind][index]
        name = e.name[:mutants.DESCR_NAME_CHARS] \
            if self.defect == mutants.DESCR_TRUNCATED else e.name
        return mca.EdgeRecord(e.width, e.signed, e.exponent, e.minimum, e.maximum, name,
                              e.unit)

    def _digest(self, t: float) -> None:
        """The description's digest (a constant of the program, computed once: the DSP's
        program carries it with its record table), in one frame at the reply time."""
        if self.defect == mutants.DIGEST_UNKNOWN:  # an older program: DLC 1 is no request
            self.can_error(t)
            self.port.error(t, ErrorCode.BAD_LENGTH, Function.MCA_DUMPIO_DESCR_REQUEST)
            return
        if self.digest is None:
            self.digest = digest_of([self._record(k, i) for k in mca.Kind
                                     for i in range(len(self._kinds[k]))])
        value = self.digest ^ mutants.DIGEST_FLIP if self.defect == mutants.DIGEST_WRONG \
            else self.digest
        self.port.send(t + self.port.timing.reply_us, DescrDigest(value))

    def _dump(self, msg: mca.DumpRequest, t: float) -> None:
        edges = self._edges(msg.kind, msg.index, msg.count, t, Function.MCA_DUMP_CI)
        if edges is None:
            return
        values = self._values[msg.kind]
        when = t + self.port.timing.reply_us
        first, size = msg.index, 0
        chunk: list[EdgeSpec] = []
        for i, e in enumerate(edges, msg.index):
            if size + e.width > 6 and chunk:
                self._send_dump(when, msg.kind, first, chunk, values)
                first, chunk, size = i, [], 0
            chunk.append(e)
            size += e.width
        if chunk:
            self._send_dump(when, msg.kind, first, chunk, values)

    def _send_dump(self, t: float, kind: mca.Kind, first: int, edges: list[EdgeSpec],
                   values: list[int]) -> None:
        specs = [(e.width, e.signed) for e in edges]
        raws = values[first:first + len(edges)] if self.defect != mutants.DUMP_OFF_BY_ONE \
            else mutants.shifted_values(values, first, specs)
        data = mca.pack_values(specs, raws)
        self.port.send(t, mca.DumpValues(kind, first, data))

    def _admin(self, msg: mca.AdminData, t: float) -> None:
        function = int(Function.MCA_ADMIN_DATA)
        if msg.op is mca.AdminOp.ALIVE:
            self.alive_ms = msg.alive_ms
        elif msg.op is mca.AdminOp.CLEAR_MAPS:
            self.so_maps.clear()
            self.ci_maps.clear()
            self.port.filters_changed()
        elif msg.op is mca.AdminOp.SO_MAP:
            so = self._kinds[mca.Kind.SO]
            used = [i for i in msg.edges if i != mca.NO_EDGE]
            if msg.period == 0:
                self.so_maps.pop(msg.map_no, None)
            elif not used or any(i >= len(so) for i in used) or \
                    sum(so[i].width for i in used) > 8:
                self.port.error(t, ErrorCode.BAD_MAP, function, msg.map_no)
                return
            else:
                layout = struct.Struct(">" + "".join(_FORMAT[so[i].width, so[i].signed]
                                                     for i in used))
                frame = mca.MapFrame(Function.MCA_SENSOR_OUTPUT, msg.map_no,
                                     bytes(layout.size))
                self.so_maps[msg.map_no] = SoMap(msg.map_no, msg.period, tuple(used), layout,
                                                 frame.arbitration_id())
        elif msg.op is mca.AdminOp.CI_MAP:
            ci = self._kinds[mca.Kind.CI]
            slots = msg.edges
            if any(i != mca.NO_EDGE and (i >= len(ci) or ci[i].width != 2) for i in slots):
                self.port.error(t, ErrorCode.BAD_MAP, function, msg.map_no)
                return
            if all(i == mca.NO_EDGE for i in slots):
                self.ci_maps.pop(msg.map_no, None)
                self.port.filters_changed()
            else:
                layout = struct.Struct(">" + "".join(
                    "H" if i == mca.NO_EDGE else _FORMAT[2, ci[i].signed] for i in slots))
                needs = 2 * (max(n for n, i in enumerate(slots) if i != mca.NO_EDGE) + 1)
                checks = tuple((n, i, ci[i].minimum, ci[i].maximum)
                               for n, i in enumerate(slots) if i != mca.NO_EDGE)
                self.ci_maps[msg.map_no] = CiMap(msg.map_no, tuple(slots), layout, needs,
                                                 checks)
                self.port.filters_changed()
        self._ready(t, function, bytes((msg.op, msg.args[0] if msg.args else 0)))

    # ------------------------------------------------------------------ shown
    def leds(self, t: float) -> dict[str, str]:
        """Run-mode LEDs (B.2.3): green blinks (the rate shows the cycle time), yellow
        flashes after an overrun (brightness in ``yellow_level``), red flashes after a CAN
        error and is steady while the watchdog latch holds (the PC was lost)."""
        blink = (self.stats.cycles // BLINK_CYCLES) % 2 == 0
        yellow = t - self.overrun_at < OVERRUN_FLASH_US
        red = self.state is mca.RunState.LATCHED or t - self.can_error_at < CAN_ERROR_FLASH_US
        loop = self.model.loop_us()
        if loop <= 0:  # no-range-check took a cycle time of 0 or less: cycles take their work
            loop = max(self.stats.last_work_us, 1.0)
        return {"red": "on" if red else "off",
                "yellow": "on" if yellow else "off",
                "green": "blink",
                "green_phase": "on" if blink else "off",
                "green_hz": f"{1e6 / (2 * BLINK_CYCLES * loop):.1f}",
                "yellow_level": f"{self.overrun_depth:.2f}" if yellow else "0"}

    def report(self) -> AppReport:
        """Report channel 3 (APPLICATION): :class:`~ucom_tools.wire.mca.AppStatus`."""
        s = self.stats
        status = mca.AppStatus(self.state, min(int(self.load() * 1000), 0xFFFF),
                               max(0, min(int(self.model.loop_us()), 0xFFFF)),
                               min(s.overruns, 0xFFFF), self.flags & 0xFF)
        return AppReport(status.encode())
