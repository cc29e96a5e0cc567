"""What ``ucom remote`` says: the mapping check's table, the exchange's plan, and at the
end of a run its summary (what the joints did, the loop's figures), the boards' events,
faults and the network's writes, as text or as ``--json``'s fields."""

from __future__ import annotations

from decimal import Decimal
from typing import TYPE_CHECKING, Any

from rich.markup import escape

from ucom_tools.cli.output import json_number, stderr, stdout
from ucom_tools.cli.tables import FitTable, shown_path
from ucom_tools.ops.remote import RemotePart
from ucom_tools.ops.remote.faults import STOP, BoardFault
from ucom_tools.ops.remote.feed import LoopFeed
from ucom_tools.ops.remote.report import BoardEvent, CheckReport, LoopStats, Summary, WriteEvent
from ucom_tools.wire import mca
from ucom_tools.wire.codes import ErrorCode

if TYPE_CHECKING:
    from ucom_tools.config.topology import BoardKey

WARN_LOAD = 0.70
"""A planned bus load above this is warned of at the start."""


def _rate(s: LoopStats) -> float:
    """Cycles a second over the run (0 for a run that never started)."""
    return 0.0 if s.ended_clock is None else s.rate(s.ended_clock)


def check_json(report: CheckReport) -> list[dict[str, Any]]:
    return [{"bus": b.bus, "board": b.board, "where": b.where, "prefix": b.prefix,
             "tree": b.tree_file, "program": b.program, "ok": b.ok, "error": b.error or None,
             "differences": [{"line": d.line, "message": d.message}
                             for d in b.differences]} for b in report.boards]


def print_check(report: CheckReport) -> None:
    if report.boards and all(b.no_program for b in report.boards):
        return  # the error says it in one line
    t = FitTable("boards against their trees")
    for col, drop in (("board", 0), ("prefix", 0), ("tree", 2), ("edges CI/SO/PAR", 1),
                      ("result", 0)):
        t.add_column(col, drop=drop)
    for b in report.boards:
        summary = b.summary().removeprefix(f"{b.where}: ")
        result = ("[green]matches[/]" if b.ok else "[red]no program[/]" if b.no_program
                  else f"[red]{escape(summary)}[/]")
        t.add_row(escape(b.where), escape(b.prefix), escape(shown_path(b.tree_file)),
                  b.program or "-", result)
    stdout().print(t)
    for b in report.boards:
        if b.differences:
            tree = shown_path(b.tree_file)
            stdout().print(f"[bold]{escape(b.where)}[/] ({escape(tree)}):")
            for d in b.differences:
                where = f"{tree}:{d.line}: " if d.line else ""
                stdout().print(f"  {escape(where)}{escape(d.message)}", soft_wrap=True)


def plan_notes(part: RemotePart) -> None:
    for name, x in part.exchanges.items():
        p = x.plan
        line = (f"{name}: the exchange needs {p.nominal:.1%} of the bus "
                f"({p.worst:.1%} with the most stuff bits), {len(p.so_maps)} SO and "
                f"{len(p.ci_maps)} CI maps")
        if p.nominal > WARN_LOAD:
            stderr().print(f"[yellow]ucom: {escape(line)}: over {WARN_LOAD:.0%}, frames may "
                           "be late[/]", soft_wrap=True)
        else:
            stderr().print(f"[dim]{escape(line)}[/]", soft_wrap=True)


def _value_text(v: object) -> str:
    if isinstance(v, Decimal):
        return format(v, "f")
    return str(v)


def stats_json(part: RemotePart, loads: dict[str, float]) -> dict[str, Any]:
    s = part.stats
    return {"cycles": s.cycles, "rate_hz": round(_rate(s), 1),
            "missed": s.missed, "longest_gap_ms": round(s.longest_gap_s * 1e3, 3),
            "jitter_ms": {
                "p50": round(s.percentile(50) * 1e3, 3),
                "p99": round(s.percentile(99) * 1e3, 3),
                "max": round(max(s.late, default=0.0) * 1e3, 3)},
            "bus_load": {n: round(v, 4) for n, v in loads.items()},
            "planned_load": {n: {"nominal": round(x.plan.nominal, 4),
                                 "worst": round(x.plan.worst, 4)}
                             for n, x in part.exchanges.items()},
            "virtual_time": part.virtual,
            "realtime": part.scheduled_as}


def boards_json(part: RemotePart) -> list[dict[str, Any]]:
    out: list[dict[str, Any]] = []
    current: dict[str, Any] | None = None
    for ref in part.names:
        if current is None or (current["bus"], current["board"]) != (ref.bus, ref.board):
            current = {"bus": ref.bus, "board": ref.board, "where": ref.where,
                       "prefix": ref.prefix, "edges": []}
            out.append(current)
        raw = part.raw(ref)
        value = None if raw is None else ref.value(raw)
        current["edges"].append({"name": ref.unique, "kind": ref.kind.name,
                                 "value": json_number(value),
                                 "text": None if value is None else _value_text(value)})
    return out


def print_summary(part: RemotePart, summary: Summary, loads: dict[str, float]) -> None:
    changed = [(r, summary.traces[r]) for r in part.names
               if r.kind is mca.Kind.SO and r in summary.traces and summary.traces[r].changes]
    # flags and one-count jitter (Settled 0 -> 1, an encoder's last count) say little here
    moved = [(r, t) for r, t in changed if r.raw(t.high) - r.raw(t.low) > 1]
    t = FitTable("what the joints did (sensor values that moved)")
    for col, drop in (("board", 1), ("name", 0), ("first", 0), ("last", 0), ("range", 0),
                      ("unit", 0)):
        t.add_column(col, drop=drop)
    clipped = False
    for ref, tr in moved:
        low, high = _value_text(tr.low), _value_text(tr.high)
        # a value at the end of what its encoding can carry: the board clipped it (the
        # quantity went further, e.g. a velocity over 32767 counts/s)
        least, most = ref.spec.raw_limits()
        if ref.raw(tr.low) <= least:
            low, clipped = f"{low}*", True
        if ref.raw(tr.high) >= most:
            high, clipped = f"{high}*", True
        t.add_row(escape(ref.where), escape(ref.unique), _value_text(tr.first),
                  _value_text(tr.last), f"{low} .. {high}", escape(ref.spec.unit))
    if moved:
        stdout().print(t)
        if clipped:
            stdout().print("[dim]* the most the edge's encoding can carry: the value went "
                           "further and was clipped[/]")
    jitter = len(changed) - len(moved)
    if not moved:
        stdout().print("no sensor value moved" + (
            f" by more than one count: {jitter} changed by one count or a flag only "
            "(--json lists every value)" if jitter else ""), soft_wrap=True)
    elif jitter:
        stdout().print(f"[dim]{jitter} more changed by one count or a flag only (--json "
                       "lists every value)[/]")
    s = part.stats
    clock = "virtual time" if part.virtual else "wall clock"
    gap = (f" (the longest gap between two cycles {s.longest_gap_s * 1e3:.1f} ms)"
           if s.missed else "")
    stdout().print(
        f"{s.cycles} cycles at {_rate(s):.0f} Hz ({clock}), {s.missed} missed"
        f"{gap}, "
        f"lateness p50 {s.percentile(50) * 1e3:.3f} ms, p99 {s.percentile(99) * 1e3:.3f} "
        f"ms; bus load " + ", ".join(f"{n} {v:.1%}" for n, v in loads.items())
        + ("" if part.scheduling is None else f"; {part.scheduled_as}"))


def print_loop_away(part: RemotePart) -> None:
    """After watchdog stops: whether the PC's own loop was away that long (no MCA Alive
    sent), which points at this machine's load rather than the bus or the boards."""
    watchdog_ms = min((x.plan.alive_ms for x in part.exchanges.values()), default=0)
    gap_ms = part.stats.longest_gap_s * 1e3
    if part.virtual or not watchdog_ms or gap_ms < watchdog_ms:
        return
    hint = ("" if part.scheduling is not None and part.scheduling.used
            else "; --realtime runs it under SCHED_FIFO")
    stderr().print(f"[yellow]ucom: the PC's loop itself did not run for {gap_ms:.0f} ms at "
                   f"a time (the boards' watchdog: {watchdog_ms} ms): this machine kept it "
                   f"from its deadlines{hint}[/]", soft_wrap=True)


def watchdog_stops(events: list[BoardEvent], faults: list[BoardFault],
                    ) -> list[BoardKey]:
    """The boards whose watchdog stopped them and that did not rejoin after it."""
    out = set()
    for e in events:
        if e.stopped_motors and not any(
                f.event == "rejoined" and (f.bus, f.board) == (e.bus, e.board)
                and f.time >= e.time for f in faults):
            out.add((e.bus, e.board))
    return sorted(out)


def fault_json(f: BoardFault) -> dict[str, Any]:
    return {"time": f.time, "bus": f.bus, "board": f.board, "where": f.where,
            "event": f.event, "seen": f.seen, "answered": f.answered}


def print_faults(part: RemotePart, still_lost: list[Any]) -> None:
    """Every board lost and rejoined, in order; under --on-fault stop what was done;
    the boards still lost at the end; each bus that failed (exit 4), as a bus error is
    shown elsewhere."""
    for why in part.failed_buses.values():
        stderr().print(f"[bold red]ucom: bus error:[/] {escape(why)}", soft_wrap=True)
    for f in part.faults:
        if f.event == "lost":
            stderr().print(f"[red]ucom: {escape(f.where)} lost at {f.time:.3f} s: "
                           f"{escape(f.seen)}[/]", soft_wrap=True)
        else:
            after = "" if f.answered is None else \
                f", {f.time - f.answered:.3f} s after it answered"
            stderr().print(f"[green]ucom: {escape(f.where)} rejoined at {f.time:.3f} s"
                           f"{after}: {escape(f.seen)}[/]", soft_wrap=True)
    if part.on_fault == STOP and part.faults:
        stderr().print(f"[red]ucom: --on-fault stop: every other board was stopped at "
                       f"{part.faults[0].time:.3f} s (MCA Start STOP on every bus); the run "
                       "ended[/]", soft_wrap=True)
    elif still_lost:
        for b in still_lost:
            stderr().print(f"[red]ucom: {escape(b.where)} still lost at the end (since "
                           f"{b.since:.3f} s): {escape(b.status)}[/]", soft_wrap=True)


def write_json(w: WriteEvent) -> dict[str, Any]:
    return {"time": w.time, "name": w.name or None, "value": w.value, "origin": w.origin,
            "result": w.result}


def print_writes(writes: list[WriteEvent]) -> None:
    """What the network set (a line per refused write, a count of the rest)."""
    done = sum(w.done for w in writes)
    if done:
        stderr().print(f"[dim]{done} value(s) set or stops asked from the network[/]")
    for w in writes:
        if not w.done:
            stderr().print(f"[yellow]ucom: refused from the network ({escape(w.origin)}) at "
                           f"{w.time:.3f} s: {escape(w.name)}={escape(w.value)}: "
                           f"{escape(w.result)}[/]", soft_wrap=True)


def event_json(e: BoardEvent) -> dict[str, Any]:
    return {"time": e.time, "bus": e.bus, "board": e.board, "where": e.where,
            "error": e.code.name, "text": e.text, "stopped_motors": e.stopped_motors}


def print_events(events: list[BoardEvent]) -> None:
    """What the boards reported while running, a line per board and kind (with a
    count), the watchdogs that stopped motors in red."""
    seen: dict[tuple[str, int, ErrorCode], tuple[BoardEvent, int]] = {}
    for e in events:
        first, n = seen.get((e.bus, e.board, e.code), (e, 0))
        seen[(e.bus, e.board, e.code)] = (first, n + 1)
    for first, n in seen.values():
        style = "red" if first.stopped_motors else "yellow"
        times = f" ({n} times)" if n > 1 else ""
        stderr().print(f"[{style}]ucom: {escape(first.where)} at {first.time:.3f} s: "
                       f"{escape(first.text)}{times}[/]", soft_wrap=True)


def extra_json(feed: LoopFeed | None, name: str) -> dict[str, Any] | None:
    """An extra consumer's figures, with the loop's count of its writes."""
    if feed is None:
        return None
    got = feed.stats.get(name)
    return {**(got or {}), "writes_applied": feed.drive.applied,
            "writes_refused": feed.drive.refused, "last_refused": feed.drive.reason or None}
