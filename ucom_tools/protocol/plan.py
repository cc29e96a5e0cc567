"""The cyclic exchange of one bus, planned: which values travel in which process-data maps
and what that costs in bus time (``man/ucom-protocol.7``, RUN TIME, Bus budget).

Pure computation, no I/O.  Input: every board's cyclic edges (index, width, period in
cycles) and its cycle time; output: the SO maps each board sends, the CI maps the PC sends
(four 16-bit slots, shared by the boards of the bus), the MCA Alive interval, and the
load these frames put on the bus, computed from Tab. B.2's ``47 + 8n`` bits per frame:
``nominal`` without stuff bits, ``worst`` with the most stuff bits a frame of that length
can carry (the measured load of real values lies between).

Packing: values of equal interval (period x cycle time) travel together; a board's SO
values of one interval fill frames of up to 8 bytes (largest first), the CI values of one
interval fill four-slot maps in board order.  When a bus would need more than 31 SO maps,
a slower frame whose values fit into the spare bytes of a board's faster frames is folded
into them (those values then come more often than asked).  Map numbers are the
identifiers' low five bits: shorter intervals get lower numbers (win arbitration).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from ucom_tools.edgelists.model import EdgeKind, EdgeSpec, ProgramSpec
from ucom_tools.errors import InputError
from ucom_tools.wire.canbits import unstuffed_bits, worst_frame_bits

MAX_MAPS = 31
"""Map numbers 1-31 per function (identifier bits 4-0; 0 is not a map)."""
MAP_BYTES = 8
CI_SLOTS = 4
NO_EDGE = 0xFF
ALIVE_DIVISOR = 5
"""The PC sends MCA Alive at least this many times per watchdog time."""


class PlanError(InputError):
    """The requested exchange does not fit the protocol or the bus (nothing was sent)."""


@dataclass(frozen=True)
class CyclicEdge:
    """One value exchanged cyclically: the per-kind edge index, its width, its period."""

    index: int
    width: int
    period: int
    name: str = ""


@dataclass(frozen=True)
class BoardNeeds:
    """What one board exchanges cyclically."""

    board: int
    """Seq ID."""
    label: str
    loop_us: float
    so: tuple[CyclicEdge, ...]
    ci: tuple[CyclicEdge, ...]


@dataclass(frozen=True)
class SoMapPlan:
    number: int
    board: int
    period: int
    """In the board's cycles."""
    interval_us: float
    edges: tuple[int, ...]
    size: int


@dataclass(frozen=True)
class CiMapPlan:
    number: int
    interval_us: float
    slots: tuple[tuple[int, int] | None, ...]
    """Per slot: (board, CI index), or None for an unused slot."""

    @property
    def size(self) -> int:
        """Bytes sent: up to the last used slot."""
        used = [n for n, s in enumerate(self.slots) if s is not None]
        return 2 * (used[-1] + 1) if used else 0

    def slots_of(self, board: int) -> tuple[int, ...]:
        """The slot list Admin Data CI_MAP gives ``board``: its CI index per slot, or
        :data:`NO_EDGE`."""
        return tuple(s[1] if s is not None and s[0] == board else NO_EDGE
                     for s in self.slots)


@dataclass(frozen=True)
class Load:
    """Bus time of a set of frames."""

    frames_per_s: float
    nominal_bits_per_s: float
    worst_bits_per_s: float


@dataclass(frozen=True)
class BusPlan:
    bus: str
    bitrate: int
    so_maps: tuple[SoMapPlan, ...]
    ci_maps: tuple[CiMapPlan, ...]
    alive_ms: int
    alive_interval_us: float
    so_load: Load
    ci_load: Load
    alive_load: Load

    def total(self) -> Load:
        parts = (self.so_load, self.ci_load, self.alive_load)
        return Load(sum(p.frames_per_s for p in parts),
                    sum(p.nominal_bits_per_s for p in parts),
                    sum(p.worst_bits_per_s for p in parts))

    @property
    def nominal(self) -> float:
        """Share of the bus, without stuff bits."""
        return self.total().nominal_bits_per_s / self.bitrate

    @property
    def worst(self) -> float:
        """Share of the bus, every frame with its most stuff bits."""
        return self.total().worst_bits_per_s / self.bitrate

    def maps_of(self, board: int) -> list[SoMapPlan]:
        return [m for m in self.so_maps if m.board == board]


def needs_of(board: int, label: str, spec: ProgramSpec, *, axes: int | None = None,
             periods: dict[str, int] | None = None, loop_us: float | None = None,
             ) -> BoardNeeds:
    """A board's cyclic edges from its program's defaults: edges of axes beyond ``axes``
    (a board driving fewer joints than the program has axes) are left out; ``periods``
    overrides the period of edges by generic name (0 = not cyclic; names the program does
    not have are for other programs)."""
    periods = periods or {}  # names of other programs' edges do not concern this board

    def cyclic(kind: EdgeKind) -> tuple[CyclicEdge, ...]:
        out = []
        for i, e in enumerate(spec.of(kind)):
            if axes is not None and e.axis is not None and e.axis >= axes:
                continue
            period = periods.get(e.name, e.period)
            if period:
                _check_period(label, e, period)
                out.append(CyclicEdge(i, e.width, period, e.name))
        return tuple(out)

    return BoardNeeds(board, label, spec.cycle_us() if loop_us is None else loop_us,
                      cyclic(EdgeKind.SO), cyclic(EdgeKind.CI))


def _check_period(label: str, e: EdgeSpec, period: int) -> None:
    if e.kind is EdgeKind.PAR:
        raise PlanError(f"{label}: {e.name} is a parameter; parameters are not cyclic")
    if e.kind is EdgeKind.CI and e.width != 2:
        raise PlanError(f"{label}: {e.name} is {e.width} bytes wide; CI maps carry 2-byte "
                        "values only")
    if not 1 <= period <= 0xFFFF:
        raise PlanError(f"{label}: period of {e.name} must be 1..65535 cycles, not {period}")


def _load(sizes: Iterable[tuple[int, float]]) -> Load:
    """Load of frames given as (data bytes, interval in us)."""
    frames = nominal = worst = 0.0
    for size, interval_us in sizes:
        rate = 1e6 / interval_us
        frames += rate
        nominal += rate * unstuffed_bits(size)
        worst += rate * worst_frame_bits(size)
    return Load(frames, nominal, worst)


def _pack(values: Sequence[CyclicEdge]) -> list[list[CyclicEdge]]:
    """First-fit decreasing into frames of :data:`MAP_BYTES`, each frame's values in
    edge order."""
    frames: list[list[CyclicEdge]] = []
    for v in sorted(values, key=lambda v: (-v.width, v.index)):
        for f in frames:
            if sum(x.width for x in f) + v.width <= MAP_BYTES:
                f.append(v)
                break
        else:
            frames.append([v])
    return [sorted(f, key=lambda v: v.index) for f in frames]


def _fold(frames: list[tuple[int, list[CyclicEdge]]]) -> None:
    """Fewer maps for one board: the values of a slower frame move into the spare bytes
    of its faster frames (they are then sent more often than asked) when all of them
    fit; slowest frames first."""
    for k in range(len(frames) - 1, -1, -1):
        period, frame = frames[k]
        faster = [f for p, f in frames[:k] if p < period]
        room = [MAP_BYTES - sum(v.width for v in f) for f in faster]
        placed: list[tuple[int, CyclicEdge]] = []
        for v in sorted(frame, key=lambda v: -v.width):
            for i, r in enumerate(room):
                if r >= v.width:
                    room[i] -= v.width
                    placed.append((i, v))
                    break
            else:
                break
        else:
            for i, v in placed:
                faster[i].append(v)
                faster[i].sort(key=lambda x: x.index)
            del frames[k]


def plan(bus: str, bitrate: int, boards: Sequence[BoardNeeds], *,
         alive_ms: int = 50) -> BusPlan:
    """The maps and the load of ``boards``' cyclic exchange on one bus; PlanError when
    the maps run out of numbers or the frames need more than the whole bus."""
    per_board: dict[int, list[tuple[int, list[CyclicEdge]]]] = {}
    for b in boards:
        by_period: dict[int, list[CyclicEdge]] = {}
        for e in b.so:
            by_period.setdefault(e.period, []).append(e)
        per_board[b.board] = [(period, frame) for period in sorted(by_period)
                              for frame in _pack(by_period[period])]
    if sum(len(f) for f in per_board.values()) > MAX_MAPS:
        for frames in per_board.values():
            _fold(frames)
    loop = {b.board: b.loop_us for b in boards}
    so_raw = [(period * loop[board], board, period, frame)
              for board, frames in per_board.items() for period, frame in frames]
    so_raw.sort(key=lambda r: (r[0], r[1], r[3][0].index))
    if len(so_raw) > MAX_MAPS:
        raise PlanError(f"{bus}: the SO values need {len(so_raw)} maps; a bus has "
                        f"{MAX_MAPS} (fewer cyclic values, or equal periods)")
    so_maps = tuple(SoMapPlan(n, board, period, interval, tuple(v.index for v in frame),
                              sum(v.width for v in frame))
                    for n, (interval, board, period, frame) in enumerate(so_raw, 1))

    ci_by_interval: dict[float, list[tuple[int, int]]] = {}
    for b in boards:
        for e in b.ci:
            ci_by_interval.setdefault(e.period * b.loop_us, []).append((b.board, e.index))
    ci_maps: list[CiMapPlan] = []
    for interval in sorted(ci_by_interval):
        wanted = ci_by_interval[interval]
        for i in range(0, len(wanted), CI_SLOTS):
            chunk: list[tuple[int, int] | None] = list(wanted[i:i + CI_SLOTS])
            slots = tuple(chunk) + (None,) * (CI_SLOTS - len(chunk))
            ci_maps.append(CiMapPlan(len(ci_maps) + 1, interval, slots))
    if len(ci_maps) > MAX_MAPS:
        raise PlanError(f"{bus}: the CI values need {len(ci_maps)} maps; a bus has "
                        f"{MAX_MAPS}")

    alive_interval = alive_ms * 1000.0 / ALIVE_DIVISOR
    result = BusPlan(bus, bitrate, so_maps, tuple(ci_maps), alive_ms, alive_interval,
                     _load((m.size, m.interval_us) for m in so_maps),
                     _load((m.size, m.interval_us) for m in ci_maps),
                     _load([(0, alive_interval)]))
    if result.nominal > 1.0:
        raise PlanError(f"{bus}: the cyclic exchange needs {result.nominal:.0%} of the bus "
                        f"even without stuff bits (longer periods, or fewer values)")
    return result
