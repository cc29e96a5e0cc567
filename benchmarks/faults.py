#!/usr/bin/env python3
"""Faults at run time over fleet serve: detection latency, time to rejoin, lateness.

How fast the PC notices a lost board, how fast it brings it back, and what a rejoin
costs the other boards' cycles, per kind of fault.

ARMAR-III (11 boards, 4 buses, armar3.fl.S flashed) runs in ``ucom fleet serve`` in
another process; this process is the PC: ``RemotePart`` over socketcand at 1 kHz with
``on_fault="hold", rejoin=True``. Every joint whose target a rejoin seeds from its joint
sensor is first moved off its rest position and held there. Then ``--repeat`` rounds
(default 20), each injecting one fault of every kind in turn (:data:`KINDS`, with
:func:`~ucom_tools.transport.fault_request.request_fault`, as ``ucom fleet fault`` does,
on a thread of its own while the loop runs on), each waited for until every board it
took is ``rejoined`` (with a deadline), then ``--gap`` seconds (default 0.15) of the
undisturbed exchange. The board-level kinds hit the head-right board (CAN0/3: its SO map
every 1 ms, as every board of ARMAR-III has one), ``cable`` cuts CAN0, ``estop`` powers
off all 11 boards.

Figures, per kind (``kinds``):

- ``detect_p50_ms``, ``detect_p99_ms``, ``detect_max_ms``: from the lost board's last SO
  map frame that reached the PC (the newest time stamp of its maps in the run time's
  process image: the served bus's time of the frame, translated to this machine's clock
  by the socketcand client, never later than its arrival) to the moment the loop
  declared it lost (its ``fault_hooks`` call, on the same clock); one sample per board
  lost (``estop``: 11 a round, ``cable``: 3).  ``beyond_rule_p99_ms``: the same less the
  silence the rule itself waits for (:func:`~ucom_tools.ops.remote.faults.lost_after`:
  5 ms for a 1 ms map), the part the loop adds.  ``seen``: how the losses were told
  (the start of their ``seen``), with counts.
- ``rejoin_p50_s``, ``rejoin_p99_s``, ``rejoin_max_s``: from the board's return to its
  ``rejoined`` event, per board.  The return is the fault's end: the request's sending
  plus its ``for`` (the served fleet applies the fault when it answers, so this is at
  most the request's round trip early: ``request_ms_max``).  A returning ARMAR-III board
  sends nothing by itself (no seq ID after a power-off or reset; a latched program after
  a bus-off or a cut cable sends no maps), so no frame marks the return; the answer to
  the PC's REJOIN comes up to 25 ms later and is reported apart: ``configure_p50_s``,
  ``configure_p99_s`` (REJOIN answered to rejoined, the board's ``answered``).
- ``joint_jump_max``: the largest difference, in raw counts, of a joint sensor of a
  rejoined board between its last value before the loss and its value ``--gap``
  seconds after the rejoin (it must hold where it stands).
- ``lateness_p99_rejoin_ms``, ``missed_rejoin_pct``, ``lateness_ratio``: the loop's
  lateness while this kind's boards were brought back, and its ratio to the lateness
  without a fault (below).
- ``lost_again``: its boards lost once more after they were back, within the round.
- ``false_losses``: boards the fault did not take that were lost meanwhile, with
  examples (a served bus held by the machine for half a second is one: ``serve_held``).
- ``unfinished``: boards a round should have lost and rejoined that were not lost, or
  not rejoined, by the deadline (``for`` + :data:`DEADLINE_S`), with what the PC says.

Over all kinds: ``rejoin_p50_s``, ``rejoin_p99_s`` of every board rejoined;
``lateness_p99_rejoin_ms``: how late the loop's cycles (every other board's CI maps and
MCA Alive) went out while boards were being brought back (from their return, or their
loss if that came later, to the last one's ``rejoined`` event),
``lateness_p99_quiet_ms`` the same in the gaps with no fault at all (from 20 ms after
every board was back to the next fault), in the same run, and ``lateness_ratio``; a
cycle's lateness is the loop's own figure (``stats.late``, as ``benchmarks/runtime.py``
reports it) plus a period for every cycle the loop skipped before it (``stats.missed``:
it came that much later than due); ``missed_rejoin_pct``, ``missed_quiet_pct``: the
share of cycles skipped in each; ``longest_gap_rejoin_ms``, ``longest_gap_quiet_ms``:
the longest time between two cycles in each (no MCA Alive meanwhile: 50 ms stops the
boards). A quiet window in which a board was lost all the same is left out.
``other_watchdog_stops``: boards outside a fault whose watchdog stopped them meanwhile.
Also ``seconds`` (the whole run), ``load_average_start`` and ``_end`` (the machine's),
``run_time`` (compiled or pure Python, and why), ``serve_held``: how often ``fleet
serve`` said this machine kept it from running in real time (its standard error; a bus
silent for half a second that way is lost as if it were, see ``QUIET_MIN_S`` in
:mod:`ucom_tools.ops.remote.watch`), ``not_posed``: the joint sensors that did not follow
their target at the start (the platform's wheels).

Targets (``targets_met``, MET or NOT MET in the text, exit 1 when one is not), for every
kind: detection p99 <= 5 ms (the rule itself waits 5 ms of silence for a 1 ms map:
``beyond_rule_p99_ms`` says what the loop adds), rejoin p99 <= 1 s, every board lost and
rejoined, no other board lost and none lost again, no joint jump of more than 50 counts
(the soak's); over all: ``lateness_ratio`` <= 1.2 and no other board stopped by its
watchdog. Over socketcand a whole bus gone silent (``cable``, ``estop``) is noticed
after the loop's quiet time (half a second) until the served fleet reports its bus's
state. ``--json`` prints the figures as one JSON object. ``--kinds`` picks kinds,
``--processes`` is passed to ``fleet serve``. About 100 s on 2 cores with the defaults.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from runtime import percentile, served_armar3  # noqa: E402

from ucom_tools import compiled  # noqa: E402
from ucom_tools.config.attrtree.match import program_of  # noqa: E402
from ucom_tools.edgelists.model import Seed  # noqa: E402
from ucom_tools.ops.edges import EdgeRef  # noqa: E402
from ucom_tools.ops.realtime import frozen_heap  # noqa: E402
from ucom_tools.ops.remote import RemotePart  # noqa: E402
from ucom_tools.ops.remote.faults import BoardFault, lost_after  # noqa: E402
from ucom_tools.signals import stop_signals  # noqa: E402
from ucom_tools.transport.fault_request import TIMEOUT_S, request_fault  # noqa: E402
from ucom_tools.wire import mca  # noqa: E402
from ucom_tools.wire.codes import ErrorCode  # noqa: E402

KINDS: Final[dict[str, tuple[str, float]]] = {
    "power-off": ("CAN0/3", 0.1),
    "reset": ("CAN0/3", 0.0),
    "bus-off": ("CAN0/3", 0.1),
    "cable": ("CAN0", 0.1),
    "estop": ("robot", 0.1),
}
"""Each kind: its target (``ucom fleet fault``'s) and how long it lasts (``for``).  The
board-level ones hit a board of a bus of 1 ms maps (each board's fastest SO map comes
every 1 ms on ARMAR-III); bus-off and cable last longer than the boards' 50 ms watchdog:
they come back latched, and are rejoined as a reset board is."""
DEADLINE_S: Final = 6.0
"""How long after a fault's end every board it took must have been lost and rejoined."""
QUIET_AFTER_S: Final = 0.02
"""The quiet windows (lateness without a rejoin) begin this long after a rejoin."""
HOLD_COUNTS: Final = 20
"""A joint has reached its pose when its sensor is this close to its target (raw)."""
JUMP_COUNTS: Final = 50
"""A rejoined joint may be this far (raw counts) from where it was lost (the soak's)."""
POSE_S: Final = 3.0
"""How long the joints may take to reach their pose at the start."""


@dataclass
class Round:
    """One fault injected: when, what it should take, what came of it."""

    kind: str
    sent: float
    """time.monotonic() when the request went out."""
    ends: float
    """The fault's end (its return), on time.monotonic()."""
    expect: set[tuple[str, int]]
    answered_in: float = 0.0
    lost: dict[tuple[str, int], BoardFault] = field(default_factory=dict)
    detect: dict[tuple[str, int], float] = field(default_factory=dict)
    """Seconds from its last frame to its loss."""
    lost_at: float = 0.0
    """time.monotonic() of the last loss among the boards it took."""
    rejoined: dict[tuple[str, int], tuple[float, BoardFault]] = field(default_factory=dict)
    """time.monotonic() of its rejoined event, and the event."""
    before: dict[tuple[str, int], list[tuple[EdgeRef, int | None]]] = field(
        default_factory=dict)
    """Its joint sensors' raw values when it was lost."""
    others: list[BoardFault] = field(default_factory=list)
    """Boards the fault did not take that were lost meanwhile (false losses)."""
    again: int = 0
    """Losses of its boards after they were back (within the round)."""
    settled: float | None = None
    """time.monotonic() when every board was back (None: not by the deadline)."""
    stopped: set[tuple[str, int]] = field(default_factory=set)
    """Boards the fault did not take whose watchdog stopped them meanwhile."""
    jumps: list[int] = field(default_factory=list)
    """Each joint sensor's distance from its value at the loss, after the gap."""

    @property
    def finished(self) -> bool:
        return all(k in self.rejoined for k in self.expect)

    def rejoining(self) -> tuple[float, float] | None:
        """When its boards were being brought back: from their return (or their loss,
        if that came later) to the last one's rejoined event."""
        if not self.rejoined:
            return None
        return max(self.ends, self.lost_at), max(t for t, _ in self.rejoined.values())


class Recorder:
    """What the loop tells: every cycle's lateness (``each``), every fault event
    (``fault_hooks``: a few lookups, on the loop's thread, only when a board is lost or
    rejoined)."""

    def __init__(self, part: RemotePart,
                 joints: dict[tuple[str, int], list[tuple[EdgeRef, EdgeRef]]]) -> None:
        self.part = part
        self.joints = joints
        self.at: list[float] = []
        self.late: list[float] = []
        self.round: Round | None = None
        self.false_at: list[float] = []
        """time.monotonic() of every false loss (no quiet window has one)."""
        self._missed = part.stats.missed
        self._period = part.period_s
        self.maps = {(bus, n): [m.number for m in x.plan.maps_of(n)]
                     for bus, x in part.exchanges.items() for n in x.configured}
        self.limit = {(bus, n): lost_after(min(m.interval_us for m in x.plan.maps_of(n)) / 1e6)
                      for bus, x in part.exchanges.items() for n in x.configured
                      if x.plan.maps_of(n)}
        part.fault_hooks.append(self.fault)

    def each(self, part: RemotePart) -> None:
        """After every cycle: when it ended, and how late it went out (with a period for
        every cycle the loop skipped before it)."""
        missed = part.stats.missed
        self.at.append(time.monotonic())
        self.late.append(part.stats.late[-1] + (missed - self._missed) * self._period)
        self._missed = missed

    def fault(self, f: BoardFault) -> None:
        now = time.time()
        r = self.round
        if r is None:
            return
        key = (f.bus, f.board)
        if key not in r.expect:
            if f.event == "lost":
                r.others.append(f)
                self.false_at.append(time.monotonic())
        elif f.event == "lost" and key in r.lost:
            r.again += 1  # lost again after it was back (its first loss is measured)
        elif f.event == "lost":
            image = self.part.exchanges[f.bus].mca.image
            stamps = [image.stamps[m] for m in self.maps[key] if m in image.stamps]
            if stamps:
                r.detect[key] = now - max(stamps)
            r.lost[key] = f
            r.lost_at = max(r.lost_at, time.monotonic())
            r.before[key] = [(so, self.part.raw(so)) for _, so in self.joints.get(key, [])]
        else:
            r.rejoined[key] = (time.monotonic(), f)


def held_joints(part: RemotePart) -> dict[tuple[str, int], list[tuple[EdgeRef, EdgeRef]]]:
    """Per board, its cyclic CI targets that a rejoin seeds from a joint sensor, with that
    sensor (``program.seeds``: the joints that must hold where they stand)."""
    out: dict[tuple[str, int], list[tuple[EdgeRef, EdgeRef]]] = {}
    for bus, x in part.exchanges.items():
        for n in x.configured:
            program = program_of(part.trees.board(bus, x.bus.boards[n - 1].position))
            if program is None:
                continue
            refs = [r for r in part.names if r.bus == bus and r.board == n]
            so = {r.generic: r for r in refs if r.kind is mca.Kind.SO}
            pairs = []
            for r in refs:
                if r.kind is mca.Kind.CI and part.cyclic(r):
                    seed = program.seed_of(r.generic)
                    if seed.seed is Seed.SENSOR and seed.sensor in so:
                        pairs.append((r, so[seed.sensor]))
            if pairs:
                out[(bus, n)] = pairs
    return out


def pose(part: RemotePart, rec: Recorder,
         joints: dict[tuple[str, int], list[tuple[EdgeRef, EdgeRef]]]) -> list[str]:
    """Every held joint moved off its rest position (a few hundred counts, each its own)
    and waited for until it stands there (:data:`POSE_S` at most); those that did not
    come (the platform's wheels, in velocity control) get their target back.  Returns
    their names."""
    targets: list[tuple[EdgeRef, EdgeRef, int, int | None]] = []
    for j, (ci, so) in enumerate(p for pairs in joints.values() for p in pairs):
        raw = min(max(150 + 40 * (j % 8), ci.spec.minimum), ci.spec.maximum)
        targets.append((ci, so, raw, part.raw(ci)))
        part.set(ci, ci.value(raw))

    def there(so: EdgeRef, raw: int) -> bool:
        value = part.raw(so)
        return value is not None and abs(value - raw) <= HOLD_COUNTS

    deadline = time.monotonic() + POSE_S
    while time.monotonic() < deadline and not all(there(so, raw)
                                                 for _, so, raw, _ in targets):
        part.run(0.05, rec.each)
    missing = []
    for ci, so, raw, was in targets:
        if not there(so, raw):
            missing.append(part.names.name_of(so))
            if was is not None:
                part.set(ci, ci.value(was))
    return missing


def inject(part: RemotePart, rec: Recorder, port: int, kind: str, gap: float) -> Round:
    """One fault of ``kind``: requested, waited for (every board it takes lost and
    rejoined, with a deadline), then ``gap`` seconds of the undisturbed exchange."""
    target, seconds = KINDS[kind]
    if kind == "estop":
        expect = {(b, n) for b, x in part.exchanges.items() for n in x.configured}
    elif "/" in target:
        bus, board = target.split("/")
        expect = {(bus, int(board))}
    else:
        expect = {(target, n) for n in part.exchanges[target].configured}
    settle = time.monotonic() + DEADLINE_S  # a board lost meanwhile (a false loss) is
    while part.lost and time.monotonic() < settle:  # back first
        part.run(0.01, rec.each)
    sent = time.monotonic()
    r = Round(kind, sent, sent + seconds, expect)
    rec.round = r
    events = len(part.events)
    answer: list[str | BaseException] = []

    def ask() -> None:  # on a thread of its own: the loop goes on meanwhile (its boards'
        try:  # watchdogs wait for nobody)
            answer.append(request_fault("127.0.0.1", port, target, kind, seconds))
        except BaseException as err:
            answer.append(err)

    asking = threading.Thread(target=ask, name="fault request", daemon=True)
    asking.start()
    while not answer and time.monotonic() < sent + TIMEOUT_S + 1.0:
        part.run(0.001, rec.each)
    asking.join(1.0)
    if not answer or isinstance(answer[0], BaseException):
        raise SystemExit(f"fleet serve did not take the fault {kind} on {target}: "
                         + (str(answer[0]) if answer else "no answer"))
    r.answered_in = time.monotonic() - sent
    deadline = r.ends + DEADLINE_S
    while time.monotonic() < deadline and not (r.finished and not part.lost):
        part.run(0.01, rec.each)
    if r.finished and not part.lost:
        r.settled = time.monotonic()
    end = time.monotonic() + gap
    while time.monotonic() < end:
        part.run(0.01, rec.each)
    for key, before in r.before.items():  # it holds where it stands
        if key in r.rejoined:
            for so, raw in before:
                now = part.raw(so)
                if raw is not None and now is not None:
                    r.jumps.append(abs(now - raw))
    r.stopped = {(e.bus, e.board) for e in part.events[events:]
                 if e.code is ErrorCode.WATCHDOG and (e.bus, e.board) not in expect}
    return r


def in_windows(at: list[float], late: list[float],
               windows: list[tuple[float, float]]) -> list[float]:
    """The lateness of the cycles that ended within one of ``windows`` (sorted)."""
    out: list[float] = []
    k = 0
    for begin, end in sorted(windows):
        while k < len(at) and at[k] < begin:
            k += 1
        j = k
        while j < len(at) and at[j] <= end:
            out.append(late[j])
            j += 1
    return out


def longest_gap(at: list[float], windows: list[tuple[float, float]]) -> float:
    """The longest time between the ends of two cycles within one of ``windows``."""
    out = 0.0
    k = 0
    for begin, end in sorted(windows):
        while k < len(at) and at[k] < begin:
            k += 1
        j = k + 1
        while j < len(at) and at[j] <= end:
            out = max(out, at[j] - at[j - 1])
            j += 1
    return out


def skipped_pct(late: list[float], period: float) -> float:
    """The share of the cycles due that the loop skipped, of cycles whose lateness
    (skipped periods included) is ``late``."""
    skipped = sum(int(x // period) for x in late)
    return round(100 * skipped / max(1, skipped + len(late)), 3)


def kind_figures(rounds: list[Round], part: RemotePart, rec: Recorder,
                 p99_quiet: float) -> dict[str, Any]:
    detect = [d for r in rounds for d in r.detect.values()]
    beyond = [d - rec.limit[k] for r in rounds for k, d in r.detect.items()]
    rejoin = [t - r.ends for r in rounds for t, _ in r.rejoined.values()]
    configure = [f.time - f.answered for r in rounds for _, f in r.rejoined.values()
                 if f.answered is not None]
    seen = Counter(f.seen.split(":")[0] for r in rounds for f in r.lost.values())
    jumps = [j for r in rounds for j in r.jumps]
    unfinished = []
    for r in rounds:
        for key in sorted(r.expect):
            if key not in r.lost:
                unfinished.append(f"{key[0]}/{key[1]} not lost")
            elif key not in r.rejoined:
                lost = part.lost.get(key)
                unfinished.append(f"{key[0]}/{key[1]} not rejoined"
                                  + (f" ({lost.status})" if lost is not None else ""))
    windows = [w for r in rounds if (w := r.rejoining())]
    late = in_windows(rec.at, rec.late, windows)
    return {
        "rounds": len(rounds),
        "detect_p50_ms": round(percentile(detect, 50) * 1e3, 2),
        "detect_p99_ms": round(percentile(detect, 99) * 1e3, 2),
        "detect_max_ms": round(max(detect, default=0.0) * 1e3, 2),
        "beyond_rule_p99_ms": round(percentile(beyond, 99) * 1e3, 2),
        "detections": len(detect),
        "seen": dict(seen),
        "rejoin_p50_s": round(percentile(rejoin, 50), 3),
        "rejoin_p99_s": round(percentile(rejoin, 99), 3),
        "rejoin_max_s": round(max(rejoin, default=0.0), 3),
        "rejoins": len(rejoin),
        "configure_p50_s": round(percentile(configure, 50), 3),
        "configure_p99_s": round(percentile(configure, 99), 3),
        "request_ms_max": round(max((r.answered_in for r in rounds), default=0.0) * 1e3, 1),
        "joint_jump_max": max(jumps, default=0),
        "lateness_p99_rejoin_ms": round(percentile(late, 99) * 1e3, 3),
        "missed_rejoin_pct": skipped_pct(late, part.period_s),
        "lateness_ratio": round(percentile(late, 99) / p99_quiet, 2) if p99_quiet > 0
        else 0.0,
        "longest_gap_ms": round(longest_gap(rec.at, windows) * 1e3, 1),
        "lost_again": sum(r.again for r in rounds),
        "false_losses": len([f for r in rounds for f in r.others]),
        "false_loss_examples": sorted({f.describe() for r in rounds
                                       for f in r.others})[:5],
        "unfinished": unfinished[:10],
        "unfinished_count": len(unfinished),
    }


def run(port: int, kinds: list[str], repeat: int, gap: float) -> dict[str, Any]:
    with RemotePart.open("armar3", interface="socketcand", host="127.0.0.1", port=port,
                         rate_hz=1000.0, on_fault="hold", rejoin=True) as part, \
            frozen_heap():  # as ucom remote run does
        joints = held_joints(part)
        rec = Recorder(part, joints)
        unposed = pose(part, rec, joints)
        part.run(gap, rec.each)
        quiet_from: float | None = time.monotonic()
        rounds: list[Round] = []
        for _ in range(repeat):  # the kinds in turns: a busy stretch of the machine
            for kind in kinds:  # slows each alike
                rounds.append(inject(part, rec, port, kind, gap))
        rec.round = None
        rejoining = [w for r in rounds if (w := r.rejoining())]
        quiet: list[tuple[float, float]] = []  # no fault anywhere: from the last
        for r in rounds:  # rejoin (and a little) to the next fault
            if quiet_from is not None:
                quiet.append((quiet_from, r.sent))
            quiet_from = None if r.settled is None else r.settled + QUIET_AFTER_S
        if quiet_from is not None:
            quiet.append((quiet_from, time.monotonic()))
        quiet = [(a, b) for a, b in quiet if not any(a <= t <= b for t in rec.false_at)]
        late_rejoin = in_windows(rec.at, rec.late, rejoining)
        late_quiet = in_windows(rec.at, rec.late, quiet)
        p99_quiet = percentile(late_quiet, 99)
        per_kind = {k: kind_figures([r for r in rounds if r.kind == k], part, rec,
                                    p99_quiet) for k in kinds}

        rejoins = [t - r.ends for r in rounds for t, _ in r.rejoined.values()]
        p99_rejoin = percentile(late_rejoin, 99)
        return {"kinds": per_kind, "not_posed": unposed,
                "rejoin_p50_s": round(percentile(rejoins, 50), 3),
                "rejoin_p99_s": round(percentile(rejoins, 99), 3),
                "lateness_p99_rejoin_ms": round(p99_rejoin * 1e3, 3),
                "lateness_p99_quiet_ms": round(p99_quiet * 1e3, 3),
                "lateness_ratio": round(p99_rejoin / p99_quiet, 2) if p99_quiet > 0
                else 0.0,
                "lateness_cycles_rejoin": len(late_rejoin),
                "lateness_cycles_quiet": len(late_quiet),
                "longest_gap_rejoin_ms": round(longest_gap(rec.at, rejoining) * 1e3, 1),
                "longest_gap_quiet_ms": round(longest_gap(rec.at, quiet) * 1e3, 1),
                "missed_rejoin_pct": skipped_pct(late_rejoin, part.period_s),
                "missed_quiet_pct": skipped_pct(late_quiet, part.period_s),
                "other_watchdog_stops": sum(len(r.stopped) for r in rounds),
                "loop_scheduling": part.scheduled_as}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=20,
                    help="faults of each kind (default 20), the kinds in turns")
    ap.add_argument("--kinds", default=",".join(KINDS),
                    help=f"the fault kinds (default: all, {','.join(KINDS)})")
    ap.add_argument("--gap", type=float, default=0.15,
                    help="seconds of the undisturbed exchange after each fault (default "
                         "0.15)")
    ap.add_argument("--processes", default="auto",
                    help="fleet serve --processes (default: auto, one per bus)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    kinds = [k.strip() for k in args.kinds.split(",") if k.strip()]
    unknown = [k for k in kinds if k not in KINDS]
    if unknown or not kinds or args.repeat < 1:
        ap.error(f"--kinds: one or more of {', '.join(KINDS)}; --repeat: 1 or more"
                 + (f" (unknown: {', '.join(unknown)})" if unknown else ""))
    began = time.monotonic()
    figures: dict[str, Any] = {"cores": os.cpu_count(), "repeat": args.repeat,
                               "load_average_start": round(os.getloadavg()[0], 2),
                               "run_time": compiled.status().reason}
    with served_armar3(args.processes) as (serve, port):
        figures.update(run(port, kinds, args.repeat, args.gap))
    assert serve.stderr is not None  # it ended: what it said about its own pace
    held = [line.split(": ", 1)[-1].strip() for line in serve.stderr.read().splitlines()
            if "kept from running" in line or "behind the wall clock" in line]
    figures["serve_held"] = len(held)
    figures["serve_held_examples"] = held[:3]
    figures["seconds"] = round(time.monotonic() - began, 1)
    figures["load_average_end"] = round(os.getloadavg()[0], 2)
    targets = targets_of(figures)
    figures["targets_met"] = targets
    if args.json:
        print(json.dumps(figures, indent=2))
    else:
        say(args, figures, targets, held)
    return 0 if all(targets.values()) else 1  # make bench names the benchmark


def targets_of(figures: dict[str, Any]) -> dict[str, bool]:
    targets: dict[str, bool] = {}
    for kind, f in figures["kinds"].items():
        targets[f"{kind}: detection p99 <= 5 ms"] = f["detect_p99_ms"] <= 5.0 \
            and f["detections"] > 0
        targets[f"{kind}: rejoin p99 <= 1 s"] = f["rejoin_p99_s"] <= 1.0 and f["rejoins"] > 0
        targets[f"{kind}: every board lost and rejoined"] = f["unfinished_count"] == 0
        targets[f"{kind}: no other board lost, none lost again"] = \
            f["false_losses"] == 0 and f["lost_again"] == 0
        targets[f"{kind}: no joint jump > {JUMP_COUNTS} counts"] = \
            f["joint_jump_max"] <= JUMP_COUNTS
    targets["lateness p99 during rejoins <= 1.2x without"] = \
        0 < figures["lateness_ratio"] <= 1.2
    targets["no other board stopped by its watchdog"] = figures["other_watchdog_stops"] == 0
    return targets


def say(args: argparse.Namespace, figures: dict[str, Any], targets: dict[str, bool],
        held: list[str]) -> None:
    print(f"Faults on ARMAR-III over socketcand (fleet serve in another process), PC at 1 kHz"
          f" with --on-fault hold --rejoin, {args.repeat} of each kind, "
          f"{figures['seconds']} s, load average {figures['load_average_start']} -> "
          f"{figures['load_average_end']} on {figures['cores']} cores, run time "
          f"{figures['run_time']}:")
    for kind, f in figures["kinds"].items():
        target, seconds = KINDS[kind]
        print(f"  {kind:<9} {target} for {seconds:g} s: detection p50 {f['detect_p50_ms']} "
              f"ms, p99 {f['detect_p99_ms']} ms (beyond the silence rule p99 "
              f"{f['beyond_rule_p99_ms']} ms; {f['detections']} boards; seen: "
              + ", ".join(f"{s} {n}" for s, n in f["seen"].items()) + ")")
        print(f"            rejoin p50 {f['rejoin_p50_s']} s, p99 {f['rejoin_p99_s']} s "
              f"after the return (REJOIN answered to rejoined p50 {f['configure_p50_s']} s, "
              f"p99 {f['configure_p99_s']} s), joint jump max {f['joint_jump_max']} counts")
        print(f"            the loop's lateness p99 {f['lateness_p99_rejoin_ms']} ms while "
              f"it was brought back ({f['lateness_ratio']}x without), "
              f"{f['missed_rejoin_pct']} % of the cycles skipped, the longest gap "
              f"{f['longest_gap_ms']} ms")
        if f["lost_again"]:
            print(f"            lost once more after they were back: {f['lost_again']}")
        for line in f["false_loss_examples"]:
            print(f"            lost, not touched by the fault: {line}")
        for line in f["unfinished"]:
            print(f"            unfinished: {line}")
    print(f"  lateness  p99 {figures['lateness_p99_rejoin_ms']} ms during rejoins "
          f"({figures['lateness_cycles_rejoin']} cycles, {figures['missed_rejoin_pct']} % "
          f"skipped), {figures['lateness_p99_quiet_ms']} ms without "
          f"({figures['lateness_cycles_quiet']} cycles, {figures['missed_quiet_pct']} % "
          f"skipped): {figures['lateness_ratio']}x; the longest gap between two cycles "
          f"{figures['longest_gap_rejoin_ms']} ms during rejoins, "
          f"{figures['longest_gap_quiet_ms']} ms without")
    if held:
        print(f"  fleet serve was held by the machine {len(held)} times (its stderr), e.g. "
              f"{held[0]}")
    if figures["not_posed"]:
        print("  (not moved off their rest position, for want of following their target: "
              + ", ".join(figures["not_posed"]) + ")")
    for name, ok in targets.items():
        print(f"  target {name}: {'MET' if ok else 'NOT MET'}")


if __name__ == "__main__":
    with stop_signals():  # SIGTERM and SIGHUP as Ctrl-C: a served fleet is stopped too
        sys.exit(main())
