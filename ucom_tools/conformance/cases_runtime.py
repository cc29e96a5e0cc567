"""Conformance cases of the run time (``man/ucom-protocol.7``, RUN TIME): a board runs the
suite's run-time program (armar3.fl.S) from external RAM - its flash is not touched, the
reset before the next case ends it - and is checked over MCA Ready, DumpIO Descr,
parameters, Dump CI, SO maps and their period, the watchdog and Report 3."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from itertools import pairwise

import can

from ucom_tools.conformance.bench import Bench
from ucom_tools.conformance.case import case
from ucom_tools.edgelists import by_name
from ucom_tools.edgelists.model import EdgeKind
from ucom_tools.errors import BoardError, UcomTimeoutError
from ucom_tools.protocol.mca import BoardEdges
from ucom_tools.protocol.periodic import Periodic
from ucom_tools.wire import mca
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import ErrorCode
from ucom_tools.wire.ids import ALL, Function, seq

PROGRAM = "armar3 cascaded PID"
"""The run-time program the suite loads (its edges are known: ucom_tools.edgelists)."""
PERIOD_TOLERANCE = 0.02
"""SO frames may come this share of their period early or late (p99), beyond one frame
time of arbitration."""


def _running(b: Bench) -> tuple[int, mca.McaReady, BoardEdges]:
    n = b.boards()[0]
    ready = b.runtime_program(n)
    try:
        edges = b.mca.describe(seq(n), (ready.ci, ready.so, ready.par))
    except (BoardError, UcomTimeoutError) as err:
        b.expect(False, "descriptions of the edges MCA Ready counts",
                 f"{ready.ci} CI, {ready.so} SO, {ready.par} PAR edges described", str(err))
        raise
    return n, ready, edges


@contextmanager
def _alive(b: Bench, interval: float = 0.010) -> Iterator[Periodic]:
    """MCA Alive every ``interval`` while the block runs (sent by whoever waits)."""
    arb, data = mca.encode(mca.Alive(), ALL)
    frame = can.Message(arbitration_id=arb, data=data, is_extended_id=False)
    task = b.link.dispatcher.every(interval, lambda: [frame], "conformance Alive")
    try:
        yield task
    finally:
        b.link.dispatcher.cancel(task)


@case("mca.ready", "run time", "RUN TIME, Start sequence; RUN TIME, Messages (MCA Ready)",
      writes="the run-time program into external RAM (gone after reset)")
def mca_ready(b: Bench) -> None:
    """After Start the program announces itself STOPPED; its edge counts are its edges."""
    n, ready, edges = _running(b)
    b.expect(ready.state is mca.RunState.STOPPED, "state after Start", "STOPPED",
             ready.state.name)
    counts = (len(edges.ci), len(edges.so), len(edges.par))
    b.expect((ready.ci, ready.so, ready.par) == counts, "MCA Ready's CI/SO/PAR counts",
             counts, (ready.ci, ready.so, ready.par))
    query = b.mca.query(seq(n))
    b.expect(query.answers == Function.MCA_START and query.echo[0] == mca.StartOp.QUERY,
             "MCA Ready answering MCA Start QUERY", "answers 21, echo 00",
             f"answers {query.answers}, echo {query.echo.hex()}")


@case("mca.descr", "run time", "RUN TIME, Values (descriptions)",
      writes="the run-time program into external RAM (gone after reset)")
def mca_descr(b: Bench) -> None:
    """DumpIO Descr describes every edge whole: names, widths, ranges, units."""
    _, _, edges = _running(b)
    spec = by_name(PROGRAM)
    assert spec is not None
    for kind in mca.Kind:
        want = [(e.name, e.width, e.signed, e.exponent, e.minimum, e.maximum, e.unit)
                for e in spec.of(EdgeKind(kind))]
        got = [(r.name, r.width, r.signed, r.exponent, r.minimum, r.maximum, r.unit)
               for r in edges.of(kind)]
        if got != want:
            diff = next(i for i, (a, c) in enumerate(zip(want, got, strict=False)) if a != c) \
                if len(got) == len(want) else min(len(got), len(want))
            b.expect(False, f"{kind.name} edge {diff}",
                     want[diff] if diff < len(want) else "no edge",
                     got[diff] if diff < len(got) else "no edge")


@case("mca.digest", "run time",
      "RUN TIME, Messages (22 MCA DumpIO Descr Request DLC 1, 23 the digest)",
      writes="the run-time program into external RAM (gone after reset)")
def mca_digest(b: Bench) -> None:
    """The description's digest is the CRC-32 of the records DumpIO Descr describes."""
    n, _, edges = _running(b)
    want = edges.digest()
    got = b.mca.digest(seq(n))
    refusal = [e.describe() for a, e in b.mca.errors if a == seq(n)
               and e.function == Function.MCA_DUMPIO_DESCR_REQUEST]
    b.expect(got == want, "the digest (DumpIO Descr Request DLC 1)", f"0x{want:08X}",
             f"0x{got:08X}" if got is not None else (refusal[-1] if refusal else "no answer"))


@case("mca.par-write", "run time", "RUN TIME, Values; RUN TIME, Bad input",
      writes="the run-time program into external RAM (gone after reset)")
def mca_par_write(b: Bench) -> None:
    """PAR writes are acknowledged and read back; a value out of range is refused whole."""
    n, _, edges = _running(b)
    par = edges.par
    index = next(i for i, r in enumerate(par) if r.name == "Max PWM")
    b.mca.write(seq(n), mca.Kind.PAR, index, [12345], par)
    got = b.mca.dump(seq(n), mca.Kind.PAR, index, 1, par)
    b.expect(got == [12345], "Max PWM read back", [12345], got)
    refused = None
    try:
        b.mca.write(seq(n), mca.Kind.PAR, index, [par[index].maximum + 1], par)
    except BoardError as err:
        refused = str(err)
    b.expect(refused is not None and "range" in refused,
             f"Max PWM = {par[index].maximum + 1} (over its maximum)",
             "Error OUT_OF_RANGE", refused or "acknowledged")
    got = b.mca.dump(seq(n), mca.Kind.PAR, index, 1, par)
    b.expect(got == [12345], "Max PWM after the refused write", [12345], got)


@case("mca.dump", "run time", "RUN TIME, Messages (MCA Dump CI / DSP CI)",
      writes="the run-time program into external RAM (gone after reset)")
def mca_dump(b: Bench) -> None:
    """Dump CI answers every value under its own index."""
    n, _, edges = _running(b)
    par = edges.par
    gains = [i for i, r in enumerate(par) if r.width == 4][:6]
    values = [1000 * (k + 1) + 7 for k in range(len(gains))]
    for i, v in zip(gains, values, strict=True):
        b.mca.write(seq(n), mca.Kind.PAR, i, [v], par)
    got = b.mca.dump(seq(n), mca.Kind.PAR, gains[0], len(gains), par)
    want = [values[gains.index(i)] if i in gains else None
            for i in range(gains[0], gains[0] + len(gains))]
    b.expect(got == want, f"PAR {gains[0]}..{gains[0] + len(gains) - 1} read back", want, got)


@case("mca.so-period", "run time", "RUN TIME, Process data (SO maps); RUN TIME, Bus budget",
      writes="the run-time program into external RAM (gone after reset)")
def mca_so_period(b: Bench) -> None:
    """An SO map comes every period cycles (p99 error within 2 % plus a frame time)."""
    n, _, _ = _running(b)
    period = 5
    b.mca.admin(seq(n), mca.AdminData.so_map(1, period, [0, 1]))
    with _alive(b):
        b.mca.start(seq(n))
        b.frames.clear()
        b.mca.pump(b.clock() + 0.5)
    b.mca.start(seq(n), mca.StartOp.STOP)
    arb = mca.MapFrame(Function.MCA_SENSOR_OUTPUT, 1, b"\0\0").arbitration_id()
    times = [f.timestamp for f in b.frames if f.arbitration_id == arb and f.is_rx]
    b.expect(len(times) >= 50, "SO map 1 frames in 0.5 s", ">= 50 (every 5 ms)", len(times))
    cycle = 0.001  # LoopTime default of the run-time program
    want = period * cycle
    errors = sorted(abs((t1 - t0) - want) for t0, t1 in pairwise(times))
    p99 = errors[min(len(errors) - 1, int(0.99 * len(errors)))]
    limit = PERIOD_TOLERANCE * want + b.link.wire_time(1)
    b.expect(p99 <= limit, "SO period error, p99", f"<= {limit * 1e6:.0f} us",
             f"{p99 * 1e6:.0f} us (mean interval "
             f"{(times[-1] - times[0]) / (len(times) - 1) * 1e3:.3f} ms)")


@case("mca.watchdog", "run time", "RUN TIME, Watchdog",
      writes="the run-time program into external RAM (gone after reset)")
def mca_watchdog(b: Bench) -> None:
    """Without MCA Alive a running board latches within its watchdog time plus a cycle,
    says so, refuses CI, and only MCA Start releases it."""
    n, _, edges = _running(b)
    alive_ms = 50
    b.mca.admin(seq(n), mca.AdminData.alive(alive_ms))
    with _alive(b):
        b.mca.start(seq(n))
        b.mca.pump(b.clock() + 0.1)
        last_alive = b.clock()
    errors: list[tuple[float, m.Error]] = []
    deadline = last_alive + (alive_ms + 1) / 1000 + b.allowed(b.timeouts.reply)
    while b.clock() < deadline + 0.1 and not errors:
        b.mca.pump(b.clock() + 0.001)
        errors += [(b.clock(), e) for a, e in b.mca.errors
                   if a == seq(n) and e.code is ErrorCode.WATCHDOG]
        b.mca.errors.clear()
        for f in list(b.frames):
            if f.arbitration_id >> 6 == Function.ERROR and f.is_rx and \
                    f.arbitration_id & 0x1F == n and f.data and f.data[0] == ErrorCode.WATCHDOG:
                errors.append((f.timestamp, m.Error(ErrorCode.WATCHDOG, 26)))
                break
    b.expect(bool(errors), "Error WATCHDOG after the last MCA Alive",
             f"within {alive_ms} ms + a cycle", "none")
    state = b.mca.query(seq(n)).state
    b.expect(state is mca.RunState.LATCHED, "state after the watchdog", "LATCHED", state.name)
    ci = edges.ci
    target = next(i for i, r in enumerate(ci) if r.name == "MotorA Target")
    refused = None
    try:
        b.mca.write(seq(n), mca.Kind.CI, target, [123], ci)
    except BoardError as err:
        refused = str(err)
    b.expect(refused is not None and "watchdog" in refused, "CI while latched",
             "Error LATCHED", refused or "taken")
    with _alive(b):
        state = b.mca.start(seq(n)).state
    b.expect(state is mca.RunState.RUNNING, "MCA Start after the latch", "RUNNING",
             state.name)
    b.mca.start(seq(n), mca.StartOp.STOP)


@case("mca.report", "run time", "RUN TIME, Loop, load and LEDs (Report 3)",
      writes="the run-time program into external RAM (gone after reset)")
def mca_report(b: Bench) -> None:
    """Report 3 gives the run state, the cycle time and a load under 100 %."""
    n, _, _ = _running(b)
    status = b.mca.app_status(seq(n))
    b.expect(status.state is mca.RunState.STOPPED and status.cycle_us == 1000,
             "Report 3 of a stopped program at 1 ms", "STOPPED, 1000 us",
             f"{status.state.name}, {status.cycle_us} us")
    b.expect(0 < status.load_permille < 1000, "load", "0..1000 per mille",
             status.load_permille)
