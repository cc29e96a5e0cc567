#!/usr/bin/env python3
"""Soak: ARMAR-III at 1 kHz for 30 min, 1 % frame loss, a fault a minute, hold and rejoin.

Issue 34, part 6: over half an hour on a lossy link, every fault detected, every board
back, no joint jump, no leak.

The whole ARMAR-III fleet (11 boards, 4 buses, armar3.fl.S flashed) runs in ``ucom
fleet serve --loss 0.01`` (1 % of the frames lost each way between the PC and every bus)
in another process.  This process is the PC: ``RemotePart`` over socketcand with
``on_fault="hold", rejoin=True`` (what ``ucom remote run --on-fault hold --rejoin``
runs), every joint's target following a slow sine of its own (set every 10 ms), for
``--minutes`` (default 30).  Every ``--every`` seconds (default 60) of the loop's own
time a fault is injected into the served fleet (``ucom fleet fault``'s request, from a
thread of its own so that the loop never waits for it), rotating through the kinds
power-off, reset, bus-off (a board: the boards in turn, the buses interleaved), cable (a
bus: the buses in turn) and estop (the robot), each lasting 1, 2 or 1.5 s in turn.

Why in this process, not ``ucom remote run ... --json`` as a subprocess: the loop's
fault hooks run on its own thread at the moment of the detection, so each lost event
is timed there (against the board's last frame on the same time base, and against the
request that injected the fault), and each joint sensor's value is taken at the loss
and watched, cycle by cycle, after the rejoin; the run's ``--json`` gives the events
only at the end, the joints' values only through a recording.  RSS, threads and file
descriptors are those of the loop's own process.  What the soak adds to it is small and
bounded: the lateness as a histogram (fixed size, not a sample per cycle), a record per
fault and per event.  What it does not soak: the live view, ``--record`` and
``--zenoh`` of ``ucom remote run`` (``benchmarks/consumers.py`` measures them beside the
loop).

Figures (``--json``: one object with these keys):

- ``faults_injected``: each fault (``at_s`` of the run, ``kind``, ``target``, ``for_s``,
  the fleet's answer, the ``boards`` it hit, how many were ``detected`` and
  ``rejoined``); ``undetected``: boards a fault hit that the PC never named lost;
  ``spurious``: lost events of boards no fault hit (the 1 % loss or a stall taken for a
  fault);
- ``detect_ms``: p50/p99/max from the board's last frame (its time stamp, on its bus's
  time base) to the lost event, over every detected board, and ``detect_ms_by_kind``;
  ``detect_from_injection_ms``: the same from the moment the request was sent;
- ``rejoin_ms``: p50/p99/max from the board's return (its first answer to Init Request
  REJOIN; for a board whose SO maps came again, which ran on, the fault's end) to its
  rejoined event; ``back_ms``: from the fault's end to the rejoined event (a power-off's
  includes the board's boot); ``rejoined_how``: by a rejoin, or its maps came again;
  ``never_rejoined``: boards lost at a fault and not back before the next one or the
  end, named;
- ``joint_jump_max_counts``: over every joint sensor ("... Joint Sensor", absolute) of
  every board rejoined after an injected fault, the largest difference between its value
  at the loss (the last the PC had) and any value in the :data:`HOLD_S` after its rejoin
  (its targets untouched meanwhile); ``jumps``: the joints over :data:`JUMP_COUNTS`;
  ``jumps_after_spurious``: the same after losses no fault caused (a board that ran on
  while its frames were held up moved meanwhile: no jump of the rejoin's);
  ``target_gap_max_counts``: the largest distance between a lost joint's old target and
  its sensor at the loss (how far a rejoin that sent the old target would have moved
  it: what the check can catch); ``stopped_after_rejoin``: boards whose watchdog stopped
  them, or that refused their CI maps as stopped, within 2 x :data:`HOLD_S` of their
  rejoin;
- ``rss_mb_start`` (:data:`RSS_AFTER_S` after the warm-up, or a third of a shorter run),
  ``rss_mb_end``, ``rss_growth_mb``, ``rss_mb_curve`` (every :data:`RSS_EVERY_S`; the
  loop's own lateness record, 100 000 samples, fills in its first 100 s: some 3 MB);
  ``threads_start``/``threads_end`` and ``fds_start``/``fds_end`` (/proc/self/task and
  /proc/self/fd, after the warm-up and at the end, every board back and no rejoin under
  way);
- ``lateness_ms``: p50/p99/max of every cycle of the run (how long after its deadline it
  sent); ``missed``: cycles the loop skipped; ``watchdog_stops``: Errors WATCHDOG of the
  whole run, ``watchdog_stops_outside_faults`` of them from boards no fault had hit in
  the :data:`STRAY_S` before (the loop or the served fleet fell behind); ``stalls``: when
  the loop was away for more than :data:`STALL_S` (two cycles that far apart), with the
  rejoins under way then; ``load_average_start``/``_end``: the machine's;
  ``serve_log_lines``, ``serve_log_tail``: what ``fleet serve`` logged (its faults, and
  the pauses a busy machine forced on it).

Targets (``targets_met``, MET or NOT MET in the text; exit 1 when one is not): every
injected fault detected on every board it hit; every board rejoined, none left lost;
no joint jump (within :data:`JUMP_COUNTS` counts); no board stopped after its rejoin;
RSS growth <= 5 MB; no more threads or file descriptors at the end than at the start;
no watchdog stop outside the faults.  Not run by ``make bench`` or ``make test``:
``make soak`` runs it for 30 minutes.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import queue
import subprocess
import sys
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks.lib.soak_analysis import (  # noqa: E402
    HOLD_S,
    JUMP_COUNTS,
    Injected,
    Seen,
    analyse,
)
from benchmarks.runtime import served_armar3  # noqa: E402
from ucom_tools import compiled  # noqa: E402
from ucom_tools.errors import UcomError  # noqa: E402
from ucom_tools.ops.edges import EdgeRef  # noqa: E402
from ucom_tools.ops.realtime import frozen_heap  # noqa: E402
from ucom_tools.ops.remote import RemotePart  # noqa: E402
from ucom_tools.ops.remote.faults import BoardFault, LostBoardWrite  # noqa: E402
from ucom_tools.signals import stop_signals  # noqa: E402
from ucom_tools.transport.fault_request import request_fault  # noqa: E402

KINDS = ("power-off", "reset", "bus-off", "cable", "estop")
"""The fault kinds, in the order they rotate."""
DURATIONS_S = (1.0, 2.0, 1.5)
"""How long each fault lasts, in turn."""
LOSS = "0.01"
"""``fleet serve --loss``: the share of frames lost each way."""
WARM_UP_S = 2.0
"""The loop runs this long before anything is measured."""
RSS_AFTER_S = 60.0
"""The RSS at the start is taken this long after the warm-up (the first minute)."""
RSS_EVERY_S = 30.0
"""``rss_mb_curve``: the RSS every this often (from the end of the warm-up)."""
SETTLE_S = 10.0
"""No fault is injected later than this before the end (time to come back)."""
END_WAIT_S = 20.0
"""At the end, how long the loop runs on (at most) until every board is back."""
AMPLITUDE = 300
"""Of each joint's sine (raw counts, around where it stood at the start)."""
STALL_S = 0.02
"""Two cycles further apart than this: the loop was away (listed in ``stalls``)."""
BIN_S = 1e-5
"""The lateness histogram's bin (10 us; up to 0.1 s, longer in the last bin)."""
BINS = 10_000


def proc_counts() -> tuple[float, int, int]:
    """This process's RSS (MB), threads and open file descriptors, from /proc."""
    rss = 0.0
    with contextlib.suppress(OSError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                rss = int(line.split()[1]) / 1024
    try:
        threads = len(os.listdir("/proc/self/task"))
        fds = len(os.listdir("/proc/self/fd"))
    except OSError:
        threads = threading.active_count()
        fds = -1
    return rss, threads, fds


def schedule(part: RemotePart, minutes: float, every: float) -> list[Injected]:
    """The faults of the run, every ``every`` s from ``every`` on, none later than
    :data:`SETTLE_S` before the end: the kinds in turn; board faults on the boards in
    turn (interleaved by bus), cables on the buses in turn."""
    by_bus: dict[str, list[int]] = {}
    for bus, x in part.exchanges.items():
        by_bus[bus] = sorted(x.configured)
    boards: list[tuple[str, int]] = []
    for k in range(max(len(v) for v in by_bus.values())):
        boards += [(bus, ns[k]) for bus, ns in by_bus.items() if k < len(ns)]
    buses = list(by_bus)
    every_board = [(bus, n) for bus, ns in by_bus.items() for n in ns]
    out: list[Injected] = []
    b = c = 0
    k = 0
    while (k + 1) * every + DURATIONS_S[k % len(DURATIONS_S)] + SETTLE_S <= minutes * 60:
        kind = KINDS[k % len(KINDS)]
        for_s = DURATIONS_S[k % len(DURATIONS_S)]
        if kind == "estop":
            out.append(Injected(kind, "robot", for_s, list(every_board)))
        elif kind == "cable":
            bus = buses[c % len(buses)]
            c += 1
            out.append(Injected(kind, bus, for_s, [(bus, n) for n in by_bus[bus]]))
        else:
            bus, n = boards[b % len(boards)]
            b += 1
            out.append(Injected(kind, f"{bus}/{n}", for_s, [(bus, n)]))
        k += 1
    return out


class Injector:
    """A thread that asks the served fleet for the faults handed to it (the loop hands
    them over without waiting), noting when each was sent and answered."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.todo: queue.Queue[Injected | None] = queue.Queue()
        self.thread = threading.Thread(target=self._run, name="soak-injector")
        self.thread.start()

    def _run(self) -> None:
        while (f := self.todo.get()) is not None:
            f.sent = time.monotonic()
            try:
                f.answer = request_fault("127.0.0.1", self.port, f.target, f.kind, f.for_s)
                f.ok = True
            except UcomError as err:
                f.answer = str(err)
            f.done = time.monotonic()

    def close(self) -> None:
        self.todo.put(None)
        self.thread.join(30)


class ServerLog:
    """``fleet serve``'s standard error, read by a thread of its own as it comes (a pipe
    nobody reads would fill and stop the fleet): the line count, the last lines."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        self.proc = proc
        self.count = 0
        self.lines: deque[str] = deque(maxlen=20)
        self.thread = threading.Thread(target=self._run, name="soak-serve-log", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.count += 1
            self.lines.append(line.rstrip())


class Soak:
    """The loop's side: the joints' sines, the fault schedule, the hooks' records, the
    lateness histogram, the joints after each rejoin."""

    def __init__(self, part: RemotePart, injector: Injector, faults: list[Injected],
                 every: float) -> None:
        self.part = part
        self.injector = injector
        self.faults = faults
        self.every = every
        self.seen: list[Seen] = []
        self.hist = [0] * (BINS + 1)
        """Cycles by lateness, :data:`BIN_S` a bin (p50 and p99: a bin's upper edge)."""
        self.late_max = 0.0
        self.sensors: dict[tuple[str, int], list[EdgeRef]] = {}
        """Each board's joint sensors."""
        self.joints: list[tuple[EdgeRef, EdgeRef, int]] = []
        """(target, sensor, raw centre) of every joint whose target is cyclic."""
        names = part.names
        for ref in names:
            name = names.name_of(ref)
            if ref.kind.name != "SO" or not name.endswith(" Joint Sensor"):
                continue
            self.sensors.setdefault((ref.bus, ref.board), []).append(ref)
            try:
                target = names.resolve(name[: -len("Joint Sensor")] + "Target")
            except UcomError:  # a sensor without a target: not moved
                continue
            if part.cyclic(target):
                self.joints.append((target, ref, part.raw(ref) or 0))
        self.held: dict[tuple[str, int], tuple[float, Seen]] = {}
        """Boards rejoined whose joints are watched: until when, their lost record."""
        self.last_loss: dict[tuple[str, int], Seen] = {}
        self.next_fault = 0
        self.start = 0.0
        self.previous = 0.0
        self.stalls: list[str] = []
        """The loop away for longer than :data:`STALL_S` (when, how long, what ran)."""
        self.stall_count = 0
        part.fault_hooks.append(self.on_fault)

    def on_fault(self, fault: BoardFault) -> None:
        """On the loop's thread, as the event happens (nothing here waits)."""
        now = time.monotonic()
        key = (fault.bus, fault.board)
        s = Seen(fault, now)
        if fault.event == "lost":
            x = self.part.exchanges[fault.bus]
            stamps = x.mca.image.stamps
            last = [stamps[m.number] for m in x.plan.maps_of(fault.board)
                    if m.number in stamps]
            if last:
                s.since_frame = self.part.robot.buses[fault.bus].link.dispatcher.stamp() \
                    - max(last)
            for ref in self.sensors.get(key, []):
                raw = self.part.raw(ref)
                if raw is not None:
                    s.sensors[ref] = raw
            for target, sensor, _ in self.joints:
                if (target.bus, target.board) == key:
                    raw = self.part.raw(target)
                    if raw is not None:
                        s.targets[sensor] = raw
            self.last_loss[key] = s
            self.held.pop(key, None)
        else:
            loss = self.last_loss.get(key)
            if loss is not None:
                self.held[key] = (now + HOLD_S, loss)
        self.seen.append(s)

    def each(self, k: int, now: float) -> None:
        """After every cycle: its lateness, the joints of boards just rejoined, every 10
        cycles the sines, the fault that is due (handed to the injector's thread)."""
        part = self.part
        late = part.stats.late[-1]
        self.hist[min(BINS, int(late / BIN_S))] += 1
        if late > self.late_max:
            self.late_max = late
        if self.previous and now - self.previous > STALL_S:
            self.stall_count += 1
            if len(self.stalls) < 30:
                self.stalls.append(f"{self.previous - self.start:.3f} s: "
                                   f"{(now - self.previous) * 1e3:.0f} ms, "
                                   f"{len(part.conversations.under_way)} rejoins under way, "
                                   f"{len(part.lost)} boards lost")
        self.previous = now
        if self.held:
            self._watch_held(now)
        if k % 10 == 0:
            t = now - self.start
            lost = part.lost
            for j, (target, _, centre) in enumerate(self.joints):
                key = (target.bus, target.board)
                if key in lost or key in self.held:
                    continue  # held where it stands (writes to a lost board are refused)
                raw = centre + round(AMPLITUDE * math.sin(2 * math.pi * (0.1 + 0.01 * j)
                                                          * t))
                with contextlib.suppress(LostBoardWrite):
                    part.set(target, target.value(raw))
        if self.next_fault < len(self.faults) and \
                now - self.start >= (self.next_fault + 1) * self.every:
            self.injector.todo.put(self.faults[self.next_fault])
            self.next_fault += 1

    def _watch_held(self, now: float) -> None:
        """The joint sensors of the boards rejoined in the last :data:`HOLD_S` against
        their values at the loss."""
        part = self.part
        lost = part.lost
        for key, (until, loss) in list(self.held.items()):
            if key in lost:
                continue
            for ref, before in loss.sensors.items():
                raw = part.raw(ref)
                if raw is None:
                    continue
                d = abs(raw - before)
                if d > loss.worst.get(ref, (-1, 0, 0.0))[0]:
                    loss.worst[ref] = (d, raw, round(now - (until - HOLD_S), 3))
            if now >= until:
                del self.held[key]

    def lateness(self) -> dict[str, float]:
        total = sum(self.hist)

        def at(p: float) -> float:
            want = min(total - 1, int(p / 100 * total))
            seen = 0
            for i, n in enumerate(self.hist):
                seen += n
                if seen > want:
                    return round((i + 1) * BIN_S * 1e3, 3)  # the bin's upper edge
            return 0.0
        return {"p50": at(50) if total else 0.0, "p99": at(99) if total else 0.0,
                "max": round(self.late_max * 1e3, 3)}


def run(port: int, minutes: float, every: float, realtime: bool) -> dict[str, Any]:
    injector = Injector(port)
    try:
        with RemotePart.open("armar3", interface="socketcand", host="127.0.0.1",
                             port=port, on_fault="hold", rejoin=True,
                             realtime=realtime) as part, frozen_heap():  # as remote run
            soak = Soak(part, injector, schedule(part, minutes, every), every)
            warm = time.monotonic() + WARM_UP_S
            while time.monotonic() < warm:
                part.cycle()
            _, threads0, fds0 = proc_counts()
            missed0 = part.stats.missed
            cycles0 = part.stats.cycles
            soak.start = now = time.monotonic()
            end = soak.start + minutes * 60
            rss_at = soak.start + min(RSS_AFTER_S, minutes * 60 / 3)
            rss0 = None
            curve: list[float] = []
            next_sample = soak.start
            load0 = os.getloadavg()[0]
            k = 0
            while now < end:
                part.cycle()
                now = time.monotonic()
                soak.each(k, now)
                k += 1
                if rss0 is None and now >= rss_at:
                    rss0 = proc_counts()[0]
                if now >= next_sample:
                    curve.append(round(proc_counts()[0], 1))
                    next_sample += RSS_EVERY_S
            # every board back, no rejoin or request under way (a deadline: the loop runs on)
            deadline = now + END_WAIT_S
            while now < deadline and (part.lost or part.conversations.under_way or soak.held or any(
                    f.sent and not f.done for f in soak.faults) or
                    not injector.todo.empty()):
                part.cycle()
                now = time.monotonic()
                soak.each(k, now)
                k += 1
            rss1, threads1, fds1 = proc_counts()
            cycles = part.stats.cycles - cycles0
            missed = part.stats.missed - missed0
            wall = now - soak.start
            out = analyse(soak, part.stats.started_clock, part.lost, list(part.events))
            out.update({"rss_mb_curve": curve, "load_average_start": round(load0, 2),
                        "load_average_end": round(os.getloadavg()[0], 2),
                        "stalls": soak.stalls, "stall_count": soak.stall_count,
                        "lateness_ms": soak.lateness(), "cycles": cycles,
                        "missed": missed, "rate_hz": round(cycles / wall, 1),
                        "realtime": part.scheduled_as, "joints_moved": len(soak.joints)})
    finally:
        injector.close()
    out.update({"rss_mb_start": round(rss0 or rss1, 1), "rss_mb_end": round(rss1, 1),
                "rss_growth_mb": round(rss1 - (rss0 or rss1), 1),
                "threads_start": threads0, "threads_end": threads1,
                "fds_start": fds0, "fds_end": fds1})
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=30.0)
    ap.add_argument("--every", type=float, default=60.0,
                    help="seconds between two faults (default 60)")
    ap.add_argument("--processes", default="auto",
                    help="fleet serve --processes (default: auto, one per bus)")
    ap.add_argument("--realtime", action="store_true",
                    help="the loop under SCHED_FIFO, as 'ucom remote run --realtime'")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    if args.minutes <= 0 or args.every <= 0:
        ap.error("--minutes and --every must be positive")
    if args.every + DURATIONS_S[0] + SETTLE_S > args.minutes * 60:
        ap.error(f"no fault fits: --minutes must be at least --every + "
                 f"{DURATIONS_S[0] + SETTLE_S:g} s")
    figures: dict[str, Any] = {"minutes": args.minutes, "every_s": args.every,
                               "loss": float(LOSS), "processes": args.processes,
                               "cores": os.cpu_count(), "run_time": compiled.status().reason}
    with served_armar3(args.processes, extra=("--loss", LOSS)) as (proc, port):
        said = ServerLog(proc)
        figures.update(run(port, args.minutes, args.every, args.realtime))
    said.thread.join(10)
    figures["serve_log_lines"] = said.count
    figures["serve_log_tail"] = list(said.lines)
    targets = {
        "every fault detected": not figures["undetected"]
        and all(r["ok"] for r in figures["faults_injected"]),
        "every board rejoined": not figures["never_rejoined"],
        f"no joint jump (<= {JUMP_COUNTS} counts)": not figures["jumps"],
        "no board stopped after its rejoin": not figures["stopped_after_rejoin"],
        "RSS growth <= 5 MB": figures["rss_growth_mb"] <= 5.0,
        "no thread leak": figures["threads_end"] <= figures["threads_start"],
        "no file descriptor leak": figures["fds_end"] <= figures["fds_start"],
        "no watchdog stop outside the faults": figures["watchdog_stops_outside_faults"]
        == 0,
    }
    figures["targets_met"] = {k: bool(v) for k, v in targets.items()}
    if args.json:
        print(json.dumps(figures, indent=2))
    else:
        say(args, figures, targets)
    return 0 if all(targets.values()) else 1


def ms(s: dict[str, Any]) -> str:
    return (f"p50 {s['p50']} ms, p99 {s['p99']} ms, max {s['max']} ms (n {s['n']})"
            if s["n"] else "none")


def say(args: argparse.Namespace, f: dict[str, Any], targets: dict[str, bool]) -> None:
    print(f"ARMAR-III at 1 kHz over socketcand (fleet serve --loss {LOSS}), "
          f"{args.minutes:g} min, a fault every {args.every:g} s, --on-fault hold --rejoin, "
          f"loop scheduling {f['realtime']}, run time {f['run_time']}:")
    for r in f["faults_injected"]:
        print(f"  {r['at_s']:8.1f} s  {r['kind']:9} {r['target']:6} {r['for_s']:g} s: "
              f"{r['detected']}/{r['boards']} detected, {r['rejoined']}/{r['boards']} "
              f"rejoined{'' if r['ok'] else '  (REFUSED: ' + r['answer'] + ')'}")
    print(f"  faults      {f['faults']} injected, {f['boards_hit']} boards hit; "
          f"undetected {len(f['undetected'])}, lost without a fault "
          f"{f['spurious_count']}")
    print(f"  detection   after the last frame {ms(f['detect_ms'])}; after the request "
          f"{ms(f['detect_from_injection_ms'])}")
    for kind, s in f["detect_ms_by_kind"].items():
        print(f"    {kind:10}{ms(s)}")
    print(f"  rejoin      from the return {ms(f['rejoin_ms'])}; from the fault's end "
          f"{ms(f['back_ms'])}; by a rejoin {f['rejoined_how']['rejoin']}, maps again "
          f"{f['rejoined_how']['maps again']}")
    print(f"  joints      {f['joints_checked']} checked after their rejoin: largest change "
          f"{f['joint_jump_max_counts']} counts (old target to sensor at the loss up to "
          f"{f['target_gap_max_counts']})")
    print(f"  process     RSS {f['rss_mb_start']} -> {f['rss_mb_end']} MB "
          f"({f['rss_growth_mb']:+} MB), threads {f['threads_start']} -> "
          f"{f['threads_end']}, file descriptors {f['fds_start']} -> {f['fds_end']}; RSS "
          f"every {RSS_EVERY_S:g} s: {', '.join(map(str, f['rss_mb_curve']))}")
    lt = f["lateness_ms"]
    print(f"  loop        {f['rate_hz']} Hz, {f['cycles']} cycles, {f['missed']} missed; "
          f"lateness p50 {lt['p50']} ms, p99 {lt['p99']} ms, max {lt['max']} ms; "
          f"watchdog stops {f['watchdog_stops']} ({f['watchdog_stops_outside_faults']} "
          "outside the faults)")
    print(f"  stalls      {f['stall_count']} times the loop was away for more than "
          f"{STALL_S * 1e3:g} ms; fleet serve logged {f['serve_log_lines']} lines; load "
          f"average {f['load_average_start']} at the start, {f['load_average_end']} at the "
          f"end ({f['cores']} cores)")
    for what in ("undetected", "never_rejoined", "jumps", "jumps_after_spurious",
                 "stopped_after_rejoin",
                 "spurious", "watchdog_stops_outside", "stalls", "serve_log_tail"):
        for item in f[what]:
            print(f"  {what.replace('_', ' ')}: {item}")
    for name, ok in targets.items():
        print(f"  target {name}: {'MET' if ok else 'NOT MET'}")


if __name__ == "__main__":
    with stop_signals():  # SIGTERM and SIGHUP as Ctrl-C: the served fleet is stopped too
        sys.exit(main())
