"""What ``benchmarks/soak.py`` makes of a soak: each injected fault matched to the lost
and rejoined events of the boards it hit (those after its request and before the next
fault's), the joints after each rejoin, the watchdog stops; and the records both sides
keep (:class:`Injected`, :class:`Seen`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from benchmarks.runtime import percentile
from ucom_tools.ops.edges import EdgeRef
from ucom_tools.ops.remote.faults import BoardFault
from ucom_tools.wire.codes import ErrorCode

HOLD_S = 1.0
"""After a board's rejoin its joints are watched (their targets untouched) this long."""
JUMP_COUNTS = 50
"""A joint sensor further than this from its value at the loss after the rejoin jumped."""
STRAY_S = 5.0
"""A watchdog stop of a board this long after a fault that hit it ended is the fault's."""


@dataclass
class Injected:
    """One injected fault: when it was asked for (``sent``, ``done``: time.monotonic()),
    what the fleet answered, the boards it hits."""

    kind: str
    target: str
    for_s: float
    boards: list[tuple[str, int]]
    sent: float = 0.0
    done: float = 0.0
    answer: str = ""
    ok: bool = False


@dataclass
class Seen:
    """A fault event as the loop's hook saw it: the event, time.monotonic() then, and for
    a lost board the time since its last frame and its joint sensors' (and targets')
    raw values at that moment."""

    fault: BoardFault
    at: float
    since_frame: float | None = None
    sensors: dict[EdgeRef, int] = field(default_factory=dict)
    targets: dict[EdgeRef, int] = field(default_factory=dict)
    worst: dict[EdgeRef, tuple[int, int, float]] = field(default_factory=dict)
    """After the rejoin: each joint sensor's largest difference from its value here, the
    value, when (seconds after the rejoin)."""


def stats(values: list[float]) -> dict[str, float | None]:
    """p50, p99, max of seconds, in ms."""
    if not values:
        return {"p50": None, "p99": None, "max": None, "n": 0}
    return {"p50": round(percentile(values, 50) * 1e3, 2),
            "p99": round(percentile(values, 99) * 1e3, 2),
            "max": round(max(values) * 1e3, 2), "n": len(values)}


@dataclass
class Tally:
    """What the matching found, over every fault."""

    used: set[int] = field(default_factory=set)
    """Indices of :attr:`Soak.seen` already matched to a fault."""
    detect: list[float] = field(default_factory=list)
    detect_inj: list[float] = field(default_factory=list)
    by_kind: dict[str, list[float]] = field(default_factory=dict)
    rejoin: list[float] = field(default_factory=list)
    back: list[float] = field(default_factory=list)
    how: dict[str, int] = field(default_factory=lambda: {"rejoin": 0, "maps again": 0})
    undetected: list[str] = field(default_factory=list)
    never: list[str] = field(default_factory=list)
    stopped: list[str] = field(default_factory=list)
    gaps: list[int] = field(default_factory=list)
    worst: list[int] = field(default_factory=list)
    jumps: list[str] = field(default_factory=list)
    rows: list[dict[str, Any]] = field(default_factory=list)


class Matcher:
    """Matches the soak's faults (``soak.faults``) to its events (``soak.seen``, the run's
    ``events``) into a :class:`Tally`."""

    def __init__(self, soak: Any, started_clock: float, still_lost: dict[tuple[str, int], Any],
                 events: list[Any]) -> None:
        self.soak, self.started_clock = soak, started_clock
        self.still_lost, self.events = still_lost, events
        part = soak.part
        self.where = {(b.bus, b.board): b.where for b in part.report.boards} \
            if part.report else {}
        self.t = Tally()

    def fault(self, f: Injected, until: float) -> None:
        """Every board ``f`` hit: its loss, its return, its joints, a stop after it."""
        detected = rejoined = 0
        for key in f.boards:
            got = self._board(f, until, key)
            detected += got > 0
            rejoined += got > 1
        self.t.rows.append({"at_s": round(f.sent - self.soak.start, 2), "kind": f.kind,
                            "target": f.target, "for_s": f.for_s, "answer": f.answer,
                            "ok": f.ok, "boards": len(f.boards), "detected": detected,
                            "rejoined": rejoined})

    def _board(self, f: Injected, until: float, key: tuple[str, int]) -> int:
        """0: not detected, 1: detected and not back, 2: back."""
        soak, t = self.soak, self.t
        name = self.where.get(key, f"{key[0]} board {key[1]}")
        when = f"{f.kind} at {f.sent - soak.start:.1f} s"
        loss = next((j for j, s in enumerate(soak.seen) if j not in t.used
                     and s.fault.event == "lost" and (s.fault.bus, s.fault.board) == key
                     and f.sent - 0.05 <= s.at < until), None)
        if loss is None:
            t.undetected.append(f"{name} ({when})")
            return 0
        lost = soak.seen[loss]
        t.used.add(loss)
        t.detect_inj.append(lost.at - f.sent)
        if lost.since_frame is not None:
            t.detect.append(lost.since_frame)
            t.by_kind.setdefault(f.kind, []).append(lost.since_frame)
        t.gaps += [abs(target - lost.sensors[sensor])
                   for sensor, target in lost.targets.items() if sensor in lost.sensors]
        for j, s in enumerate(soak.seen):  # losses again before it was back: its own
            if j not in t.used and (s.fault.bus, s.fault.board) == key and \
                    lost.at <= s.at < until and s.fault.event == "lost":
                t.used.add(j)
        back_at = next((s for s in soak.seen if s.fault.event == "rejoined"
                        and (s.fault.bus, s.fault.board) == key
                        and lost.at <= s.at < until), None)
        if back_at is None or (key in self.still_lost and until == math.inf):
            t.never.append(f"{name} ({when})")
            return 1
        self._back(f, until, key, name, when, lost, back_at)
        return 2

    def _back(self, f: Injected, until: float, key: tuple[str, int], name: str, when: str,
              lost: Seen, back_at: Seen) -> None:
        t, soak = self.t, self.soak
        end = f.sent + f.for_s
        t.back.append(back_at.at - end)
        if back_at.fault.answered is not None:
            t.how["rejoin"] += 1
            t.rejoin.append(back_at.fault.time - back_at.fault.answered)
        else:
            t.how["maps again"] += 1
            t.rejoin.append(max(0.0, back_at.at - end))
        for ref, (d, raw, after) in lost.worst.items():
            t.worst.append(d)
            if d > JUMP_COUNTS:
                t.jumps.append(f"{soak.part.names.name_of(ref)} ({when}): "
                               f"{lost.sensors[ref]} at the loss, {raw} {after:.3f} s after "
                               "the rejoin")
        for e in self.events:
            at = self.started_clock + e.time
            if (e.bus, e.board) == key and back_at.at <= at < min(
                    until, back_at.at + 2 * HOLD_S) and e.code in (
                    ErrorCode.WATCHDOG, ErrorCode.LATCHED):
                t.stopped.append(f"{name} ({when}): {e.text} at {at - soak.start:.3f} s")
                break


def analyse(soak: Any, started_clock: float, still_lost: dict[tuple[str, int], Any],
            events: list[Any]) -> dict[str, Any]:
    """Each injected fault matched to the lost and rejoined events of the boards it hit
    (those after its request and before the next fault's); the rest."""
    injected = [f for f in soak.faults if f.sent]
    m = Matcher(soak, started_clock, still_lost, events)
    for i, f in enumerate(injected):
        m.fault(f, injected[i + 1].sent if i + 1 < len(injected) else math.inf)
    t = m.t
    spurious = [f"{s.fault.where} at {s.at - soak.start:.3f} s: {s.fault.seen}"
                for j, s in enumerate(soak.seen) if s.fault.event == "lost" and j not in t.used]
    stops = [e for e in events if e.code is ErrorCode.WATCHDOG]
    outside = [e for e in stops if not any(
        (e.bus, e.board) in f.boards
        and f.sent <= started_clock + e.time <= f.sent + f.for_s + STRAY_S
        for f in injected)]
    return {
        "faults_injected": t.rows, "faults": len(injected),
        "boards_hit": sum(len(f.boards) for f in injected),
        "undetected": t.undetected, "spurious": spurious[:20],
        "spurious_count": len(spurious),
        "detect_ms": stats(t.detect),
        "detect_ms_by_kind": {k: stats(v) for k, v in t.by_kind.items()},
        "detect_from_injection_ms": stats(t.detect_inj),
        "rejoin_ms": stats(t.rejoin), "back_ms": stats(t.back), "rejoined_how": t.how,
        "never_rejoined": t.never + [f"{v.where} (lost at the end: {v.status})"
                                     for v in still_lost.values()],
        "joints_checked": len(t.worst),
        "joint_jump_max_counts": max(t.worst, default=None),
        "jumps": t.jumps[:20],
        "jumps_after_spurious": [
            f"{soak.part.names.name_of(ref)} ({s.fault.where} lost at "
            f"{s.at - soak.start:.1f} s without a fault): {s.sensors[ref]} at the loss, "
            f"{raw} {after:.3f} s after the rejoin" for j, s in enumerate(soak.seen)
            if j not in t.used for ref, (d, raw, after) in s.worst.items()
            if d > JUMP_COUNTS][:20],
        "target_gap_max_counts": max(t.gaps, default=None),
        "stopped_after_rejoin": t.stopped,
        "watchdog_stops": len(stops),
        "watchdog_stops_outside_faults": len(outside),
        "watchdog_stops_outside": [f"{e.where} at {started_clock + e.time - soak.start:.3f}"
                                   " s" for e in outside][:10],
    }
