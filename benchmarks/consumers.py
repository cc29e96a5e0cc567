#!/usr/bin/env python3
"""Nothing beside the loop can stop it: ``ucom remote run`` with its live view, ``--zenoh``
and ``--record`` at once, over ``ucom fleet serve armar3``, on a machine that two
CPU-bound processes keep busy, against the same runs without view, share and record.

ARMAR-III (11 boards, 4 buses, armar3.fl.S flashed) is served by ``ucom fleet serve``
(the robot's boards: a session of its own); ``--hogs`` processes (default 2, ``python -c
'while True: pass'``, each in a session of its own, as another user's jobs) keep the
machine's cores busy for the whole benchmark.  Every run is started in a session of its
own too, as from a terminal: Linux shares the processors between sessions first
(autogroups), then between a session's processes.  Each of ``--runs`` rounds (default 20)
runs the user's command twice, one after the other (so that both see the same machine):

- *with*: ``ucom remote run armar3 -i socketcand ... --zenoh tcp/127.0.0.1:PORT --record
  DIR/run.blf`` on a pseudo-terminal (200 x 60), so that it opens its live view, which
  renders at its own refresh rate; ``--seconds`` (default 10) after its first screen
  this process reads the robot's values over Zenoh (``RobotClient.read``, what ``ucom
  browse --get`` does) and types ``q``;
- *without*: ``ucom remote run armar3 -i socketcand ... --for SECONDS --json``.

Both set the same targets at the start (four joints move for a second or two).
Figures: ``runs``; ``watchdog_stops``: runs in which a board's watchdog stopped its motors
(the loop was away for 50 ms), with view etc. and without; ``exceptions``: runs that
ended in a traceback, an error or an unexpected exit code; ``p99_ms_with`` and
``p99_ms_without``: the median over the runs of each run's lateness p99 (how long after
its deadline a cycle sent its frames, as the run's summary prints it), ``ratio`` of the
two; ``worst_p99_ms_with``/``_without``; ``missed_with``/``missed_without``: cycles the
loop skipped, summed over the runs; ``renders_per_s``: how often the live view wrote to
its terminal (median of the runs: its refresh rate, 10 a second); ``recorded_rows``:
value rows in the values file (median); ``zenoh_reads``: runs whose Zenoh read answered
with a value; ``load_average``: the machine's, at the end.

Targets (``targets_met``; MET or NOT MET in the text, exit 1 when one is not): 0 watchdog
stops and 0 exceptions in the runs with view, share and record; ``ratio`` <= 1.5; every
run's view rendered (at least 5 screens a second), recorded and answered over Zenoh.
``--json`` prints the figures as one JSON object.  Not run by ``make test``: ``make bench``
runs it (20 x 2 runs of 10 s: about 10 minutes).
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import fcntl
import json
import os
import pty
import re
import select
import signal
import statistics
import struct
import subprocess
import sys
import tempfile
import termios
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks.network import free_port  # noqa: E402
from benchmarks.runtime import IMAGE  # noqa: E402
from ucom_tools import compiled  # noqa: E402
from ucom_tools.signals import stop_signals  # noqa: E402

SETS = ("Right Eye Target=1000", "Left Eye Target=-1000", "Neck Yaw Target=-2000",
        "Right Elbow Target=1500")
"""Set at the start of every run, with and without: joints that move, values that change."""
COLUMNS, ROWS = 200, 60
"""The pseudo-terminal's size: every board's box on the screen."""
VIEW_UP = b"Hz  missed"
"""In the live view's first line (``... cycles  1000 Hz  missed 0  lateness ...``)."""
START_S = 60.0
"""How long a run may take to start (claim, check, configure the boards)."""
END_S = 60.0
"""How long a run may take to stop the boards and print its summary."""
QUIET_S = 0.03
"""A pause this long in the view's output ends one screen's writes (renders_per_s)."""
_ANSI = re.compile(rb"\x1b\[[0-9;?<>=]*[ -/]*[@-~]|\x1b[()][0-9A-Za-z]|\x1b[=>78]|\r")
_P99 = re.compile(r"lateness p50 ([0-9.]+) ms, p99 ([0-9.]+) ms")
_MISSED = re.compile(r"([0-9]+) cycles at [0-9]+ Hz \([a-z ]+\), ([0-9]+) missed")


def ucom(*args: str) -> list[str]:
    return [sys.executable, "-m", "ucom_tools", *args]


@contextlib.contextmanager
def served_armar3(*serve_args: str) -> Iterator[int]:
    """ARMAR-III with armar3.fl.S flashed, served by ``ucom fleet serve`` (a process per
    bus; ``serve_args`` added, e.g. ``--extra-bus CO0``) in a session of its own: the fleet
    stands for the robot's boards, which have processors of their own; it must not share
    its session's processor time with this process.  Its port; stopped afterwards
    (SIGINT, then killed)."""
    with tempfile.TemporaryDirectory() as tmp:
        state = Path(tmp) / "state"
        flash = subprocess.run(ucom("flash", str(IMAGE), "--virtual", "armar3", "--state",
                                    str(state)), capture_output=True, text=True)
        if flash.returncode:
            raise SystemExit(f"flash failed: {flash.stderr}")
        proc = subprocess.Popen(ucom("fleet", "serve", "armar3", "--state", str(state),
                                     "--port", "0", *serve_args), text=True,
                                stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, start_new_session=True)
        try:
            assert proc.stdout is not None
            line = proc.stdout.readline()
            if not line.startswith("listening on"):
                raise SystemExit(f"fleet serve did not start: {line}"
                                 + (proc.stderr.read() if proc.stderr else ""))
            yield int(line.rsplit(":", 1)[1])
        finally:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


@contextlib.contextmanager
def hogs(n: int) -> Iterator[list[subprocess.Popen[bytes]]]:
    """``n`` CPU-bound processes for the block's length, each in a session of its own (as
    another user's jobs are: Linux shares the processors between sessions first, then
    between a session's processes)."""
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"],
                              start_new_session=True) for _ in range(n)]
    try:
        yield procs
    finally:
        for p in procs:
            p.kill()
        for p in procs:
            p.wait()


class Terminal:
    """A pseudo-terminal of :data:`COLUMNS` x :data:`ROWS` whose output is read (and
    kept, with the time of each read) by a thread of its own, as a terminal emulator
    does: the program on it never waits for its reader."""

    def __init__(self) -> None:
        self.master, self.slave = pty.openpty()
        fcntl.ioctl(self.slave, termios.TIOCSWINSZ, struct.pack("HHHH", ROWS, COLUMNS, 0, 0))
        self.data = bytearray()
        self.reads: list[tuple[float, int]] = []
        """(time, bytes) of every read."""
        self.up = threading.Event()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        while True:
            try:
                ready, _, _ = select.select([self.master], [], [], 1.0)
                if not ready:
                    continue
                chunk = os.read(self.master, 65536)
            except OSError:  # EIO: the program and every holder of the slave are gone
                return
            if not chunk:
                return
            self.reads.append((time.monotonic(), len(chunk)))
            self.data += chunk
            if not self.up.is_set() and VIEW_UP in self.data:
                self.up.set()

    def type(self, text: str) -> None:
        os.write(self.master, text.encode())

    def text(self) -> str:
        return _ANSI.sub(b"", bytes(self.data)).decode("utf-8", "replace")

    def renders(self, start: float, end: float) -> int:
        """Bursts of output between ``start`` and ``end`` (screens written)."""
        n, last = 0, -1.0
        for t, _ in self.reads:
            if start <= t <= end:
                if t - last > QUIET_S:
                    n += 1
                last = t
        return n

    def close(self) -> None:
        with contextlib.suppress(OSError):
            os.close(self.slave)
        self._thread.join(5)
        with contextlib.suppress(OSError):
            os.close(self.master)


REALTIME: list[str] = []
"""``--realtime`` where the benchmark was asked to."""


def connection(port: int) -> list[str]:
    """The robot, and ``--on-fault hold``: a served fleet that a busy machine holds up
    for more than 5 ms makes its boards silent that long, which the loop counts as lost
    (``ucom-protocol(7)``, Faults); under the default policy that would end the run."""
    return ["armar3", "-i", "socketcand", "--host", "127.0.0.1", "--port", str(port),
            "--on-fault", "hold", *REALTIME]


def sets() -> list[str]:
    return [a for s in SETS for a in ("--set", s)]


def end_of(proc: subprocess.Popen[Any], timeout: float) -> int:
    try:
        return proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        return -9


def run_with(port: int, seconds: float, tmp: Path) -> dict[str, Any]:
    """The command with its live view, --zenoh and --record, on a pseudo-terminal."""
    from ucom_tools.net.client import RobotClient

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    log = tmp / "run.blf"
    term = Terminal()
    proc = subprocess.Popen(ucom("remote", "run", *connection(port), "--zenoh", endpoint,
                                 "--record", str(log), *sets()),
                            stdin=term.slave, stdout=term.slave, stderr=term.slave,
                            start_new_session=True, env={**os.environ, "TERM": "xterm"})
    zenoh_ok = False
    code: int
    try:
        started = term.up.wait(START_S) and proc.poll() is None
        t0 = time.monotonic()
        if started:
            deadline = t0 + seconds
            while proc.poll() is None and time.monotonic() < deadline:
                time.sleep(0.05)  # the benchmark's own pace: nothing here waits on this
            if proc.poll() is None:
                with contextlib.suppress(Exception), RobotClient.connect(
                        endpoint, timeout=5) as client:
                    zenoh_ok = bool(client.read(["Right Eye Joint Sensor"], timeout=5))
            t1 = time.monotonic()
            if proc.poll() is None:
                term.type("q\r")
        else:
            t1 = t0
        code = end_of(proc, END_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        term.close()
    text = term.text()
    rows = 0
    values = Path(str(log) + ".values.csv")
    if values.exists():
        with values.open(newline="") as f:
            rows = max(0, sum(1 for _ in csv.reader(f)) - 1)
    out = figures_of_text(text, code)
    out.update({"started": started, "zenoh": zenoh_ok, "rows": rows,
                "renders_per_s": round(term.renders(t0, t1) / max(1e-9, t1 - t0), 1)
                if started else 0.0})
    with contextlib.suppress(OSError):
        log.unlink()
        values.unlink()
    return out


def figures_of_text(text: str, code: int) -> dict[str, Any]:
    """What a run's summary (text, on its terminal) and exit code say."""
    p99 = _P99.findall(text)
    missed = _MISSED.findall(text)
    stopped = "its watchdog stopped every motor" in text
    lost = len(re.findall(r" lost at \d", text))
    failed = "Traceback" in text or code not in (0, 1) or (
        code == 1 and not stopped and not lost)
    return {"p99_ms": float(p99[-1][1]) if p99 else None,
            "missed": int(missed[-1][1]) if missed else None,
            "stopped": stopped, "exception": bool(failed), "exit": code, "lost": lost,
            "tail": "" if not failed and not stopped else text[-1500:]}


def run_without(port: int, seconds: float) -> dict[str, Any]:
    """The same command for ``seconds`` without view, share or record (--json)."""
    proc = subprocess.run(ucom("remote", "run", *connection(port), "--for", str(seconds),
                               "--json", *sets()), start_new_session=True,  # as the other
                          capture_output=True, text=True, timeout=START_S + seconds + END_S)
    try:
        doc = json.loads(proc.stdout)
    except ValueError:
        return {"p99_ms": None, "missed": None, "stopped": False, "exception": True,
                "exit": proc.returncode, "lost": 0,
                "tail": (proc.stdout + proc.stderr)[-1500:]}
    stopped = any(e.get("stopped_motors") for e in doc.get("events", []))
    lost = sum(f.get("event") == "lost" for f in doc.get("faults", []))
    run = doc.get("run", {})
    return {"p99_ms": run.get("jitter_ms", {}).get("p99"), "missed": run.get("missed"),
            "stopped": stopped, "exception": proc.returncode not in (0, 1)
            or (proc.returncode == 1 and not stopped and not lost), "exit": proc.returncode,
            "lost": lost, "tail": "" if proc.returncode == 0 else proc.stderr[-1500:]}


# ---------------------------------------------------------------------- what the loop pays
def costs(cycles: int = 3000) -> dict[str, float]:
    """In process, ARMAR-III in virtual time: what the hand-over and the feed to the
    consumers' process cost the loop's thread (its each_cycle hooks timed one by one)."""
    from tests.runtime_rig import programmed, robot_of
    from ucom_tools.config.attrtree.robot import bind
    from ucom_tools.ops.remote import RemotePart
    from ucom_tools.ops.remote.feed import LoopFeed
    from ucom_tools.ops.remote.publish import LoopHandover

    fleet = programmed("armar3")
    robot = robot_of(fleet)
    part = RemotePart(robot, bind(robot.topology))
    out: dict[str, float] = {}
    try:
        part.start()
        handover = LoopHandover.of(part, 100.0)
        part.run(1.5)  # nobody reads: its lease runs out
        t = time.perf_counter()
        for _ in range(100_000):
            handover.on_cycle()
        out["handover_idle_ns"] = round((time.perf_counter() - t) / 100_000 * 1e9)
        t = time.perf_counter()
        for _ in range(1000):
            handover.publish()
        out["snapshot_us"] = round((time.perf_counter() - t) / 1000 * 1e6, 1)
        # the feed: frames of every bus, value changes, snapshots at 100 Hz, into a pipe
        # a thread drains (as the consumers' process does)
        r, w = os.pipe()
        back_r, back_w = os.pipe()
        drained = threading.Thread(target=lambda: [None for _ in iter(
            lambda: os.read(r, 1 << 16), b"")], daemon=True)
        drained.start()
        feed = LoopFeed(part, w, back_r, frames=True, rate_hz=100.0, wait=False)
        feed.attach_frames()
        feed.attach()
        feed.send_image()
        spent = [0.0]

        def timed(hook: Any) -> Any:
            def call() -> None:
                t0 = time.perf_counter()
                hook()
                spent[0] += time.perf_counter() - t0
            return call
        part.each_cycle[:] = [timed(h) for h in part.each_cycle]
        for _ in range(cycles):
            part.cycle()
        frames = sum(h.link.dispatcher.received + h.link.dispatcher.sent
                     for h in part.robot.buses.values())
        out["feed_us_per_cycle"] = round(spent[0] / cycles * 1e6, 1)
        out["frames_per_cycle"] = round(frames / max(1, part.stats.cycles), 1)
        out["lost"] = feed.lost
        for fd in (w, back_r, back_w):
            os.close(fd)
    finally:
        part.close()
        robot.close()
    return out


# ---------------------------------------------------------------------- the decision
_LOOP = """
import sys, time
sys.path.insert(0, sys.argv[1])
from ucom_tools.ops.realtime import RealtimeScheduling, ShortSlice, precise_sleep
realtime, seconds, mode = sys.argv[2] == "1", float(sys.argv[3]), sys.argv[4]

def work(stop):  # a consumer: 30 % of a core of Python work, in 3 ms stretches
    while not stop.is_set():
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < 0.003:
            sum(i * i for i in range(200))
        time.sleep(0.007)

if __name__ == "__main__":
    import multiprocessing, threading
    stop = threading.Event() if mode == "thread" else multiprocessing.Event()
    worker = (threading.Thread(target=work, args=(stop,), daemon=True) if mode == "thread"
              else multiprocessing.Process(target=work, args=(stop,), daemon=True)
              if mode == "process" else None)
    if worker is not None:
        worker.start()
    sys.setswitchinterval(1e-4)  # as the loop of ucom remote run
    rt = RealtimeScheduling()
    if realtime:
        rt.enter()
    if not rt.active:
        ShortSlice().enter()
    precise_sleep()
    period = 1e-3
    deadline = time.monotonic() + period
    end = deadline + seconds
    late, last, gap = [], time.monotonic(), 0.0
    while deadline < end:
        now = time.monotonic()
        if deadline - now > 1e-4:
            time.sleep(deadline - now - 1e-4)
        while time.monotonic() < deadline:
            pass
        now = time.monotonic()
        behind = now - deadline
        if behind >= period:
            deadline += (behind // period) * period
            behind %= period
        late.append(behind)
        gap, last = max(gap, now - last), now
        sum(i for i in range(100))  # a cycle's own work
        deadline += period
    stop.set()
    late.sort()
    print(late[int(0.99 * len(late))] * 1e3, gap * 1e3, rt.active)
"""


def decision(rounds: int, seconds: float) -> dict[str, Any]:
    """A 1 kHz Python loop beside a consumer doing 30 % of a core of Python work: none, in
    a thread of the loop's process, in a process of its own; under SCHED_FIFO where
    permitted (``--realtime``), and at normal priority: lateness p99 (median of the
    rounds) and the longest gap between two cycles (the worst)."""
    out: dict[str, Any] = {}
    for realtime in (True, False):
        for mode in ("none", "thread", "process"):
            p99s, gaps, active = [], [], False
            for _ in range(rounds):
                got = subprocess.run([sys.executable, "-c", _LOOP, str(ROOT),
                                      "1" if realtime else "0", str(seconds), mode],
                                     capture_output=True, text=True, timeout=seconds + 60)
                p99, gap, rt = got.stdout.split()
                p99s.append(float(p99))
                gaps.append(float(gap))
                active = rt == "True"
            if realtime and not active:
                break  # SCHED_FIFO is not permitted here
            key = f"{'fifo' if realtime else 'normal'}_{mode}"
            out[f"{key}_p99_ms"] = round(statistics.median(p99s), 3)
            out[f"{key}_gap_ms"] = round(max(gaps), 1)
    return out


def median(values: list[float]) -> float | None:
    return round(statistics.median(values), 3) if values else None


def arguments() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--hogs", type=int, default=2,
                    help="CPU-bound processes beside the runs (default 2)")
    ap.add_argument("--realtime", action="store_true",
                    help="both runs with --realtime (the loop under SCHED_FIFO)")
    ap.add_argument("--decision-rounds", type=int, default=3,
                    help="rounds of the thread-or-process measurement (0: none)")
    ap.add_argument("--skip-costs", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--json", action="store_true")
    return ap.parse_args()


def say_run(k: int, w: dict[str, Any], o: dict[str, Any]) -> None:
    print(f"  run {k + 1:2}: with p99 {w['p99_ms']} ms"
          f"{' WATCHDOG' if w['stopped'] else ''}"
          f"{' LOST ' + str(w['lost']) if w['lost'] else ''}"
          f"{' EXCEPTION' if w['exception'] else ''}, {w['renders_per_s']} "
          f"screens/s, {w['rows']} rows, zenoh {'ok' if w['zenoh'] else 'NO'}"
          f"; without p99 {o['p99_ms']} ms{' WATCHDOG' if o['stopped'] else ''}"
          f"{' LOST ' + str(o['lost']) if o['lost'] else ''}"
          f"{' EXCEPTION' if o['exception'] else ''}", flush=True)


def figures_of(args: argparse.Namespace, with_runs: list[dict[str, Any]],
               without_runs: list[dict[str, Any]], costs_: dict[str, Any],
               decision_: dict[str, Any], load: float) -> dict[str, Any]:
    p_with = [r["p99_ms"] for r in with_runs if r["p99_ms"] is not None]
    p_without = [r["p99_ms"] for r in without_runs if r["p99_ms"] is not None]
    m_with, m_without = median(p_with), median(p_without)
    return {
        "runs": args.runs, "seconds": args.seconds, "hogs": args.hogs,
        "realtime": args.realtime,
        "run_time": compiled.status().reason,
        "watchdog_stops": sum(r["stopped"] for r in with_runs),
        "watchdog_stops_without": sum(r["stopped"] for r in without_runs),
        "exceptions": sum(r["exception"] for r in with_runs),
        "exceptions_without": sum(r["exception"] for r in without_runs),
        "p99_ms_with": m_with, "p99_ms_without": m_without,
        "ratio": round(m_with / m_without, 2) if m_with is not None and m_without else None,
        "worst_p99_ms_with": max(p_with, default=None),
        "worst_p99_ms_without": max(p_without, default=None),
        "missed_with": sum(r["missed"] or 0 for r in with_runs),
        "missed_without": sum(r["missed"] or 0 for r in without_runs),
        "boards_lost_with": sum(r["lost"] for r in with_runs),
        "boards_lost_without": sum(r["lost"] for r in without_runs),
        "renders_per_s": median([r["renders_per_s"] for r in with_runs]),
        "recorded_rows": median([r["rows"] for r in with_runs]),
        "zenoh_reads": sum(r["zenoh"] for r in with_runs),
        "load_average": round(load, 2),
        "costs": costs_, "decision": decision_,
        "failures": [r["tail"] for r in with_runs + without_runs if r["tail"]][:3],
    }


def targets_of(figures: dict[str, Any], with_runs: list[dict[str, Any]]) -> dict[str, bool]:
    return {
        "0 watchdog stops with view, share and record": figures["watchdog_stops"] == 0,
        "0 exceptions": figures["exceptions"] == 0,
        "lateness p99 <= 1.5x without": figures["ratio"] is not None
        and figures["ratio"] <= 1.5,
        "every view rendered (>= 5 screens/s), recorded, shared": all(
            r["started"] and r["renders_per_s"] >= 5 and r["rows"] > 0 and r["zenoh"]
            for r in with_runs),
    }


def say(args: argparse.Namespace, figures: dict[str, Any], targets: dict[str, bool]) -> None:
    print(f"ARMAR-III over fleet serve, {args.runs} runs of {args.seconds:g} s with live "
          f"view + --zenoh + --record and without, {args.hogs} CPU-bound processes beside, "
          f"run time {figures['run_time']}:")
    print(f"  lateness p99 (median of the runs) {figures['p99_ms_with']} ms with, "
          f"{figures['p99_ms_without']} ms without: "
          f"{figures['ratio']}x (worst {figures['worst_p99_ms_with']} / "
          f"{figures['worst_p99_ms_without']} ms); missed {figures['missed_with']} / "
          f"{figures['missed_without']} cycles")
    print(f"  watchdog stops {figures['watchdog_stops']} with, "
          f"{figures['watchdog_stops_without']} without; exceptions {figures['exceptions']}"
          f" with, {figures['exceptions_without']} without; boards lost (the served fleet "
          f"held up) {figures['boards_lost_with']} with, {figures['boards_lost_without']} "
          "without")
    print(f"  live view {figures['renders_per_s']} screens/s, {figures['recorded_rows']} "
          f"value rows recorded, Zenoh answered in {figures['zenoh_reads']} of "
          f"{args.runs} runs; load average {figures['load_average']}")
    c = figures["costs"]
    if c:
        print(f"  the loop pays: {c['handover_idle_ns']} ns a cycle for a hand-over nobody "
              f"reads, {c['snapshot_us']} us a snapshot; the feed to the consumers' process "
              f"{c['feed_us_per_cycle']} us a cycle ({c['frames_per_cycle']} frames a cycle, "
              "100 snapshots a second)")
    d = figures["decision"]
    for prio in ("fifo", "normal"):
        if f"{prio}_none_p99_ms" in d:
            print(f"  a 1 kHz loop ({'SCHED_FIFO' if prio == 'fifo' else 'normal'}) "
                  "beside 30 % of a core of Python work: "
                  + ", ".join(f"{m} p99 {d[f'{prio}_{m}_p99_ms']} ms (gap "
                              f"{d[f'{prio}_{m}_gap_ms']} ms)"
                              for m in ("none", "thread", "process")))
    for tail in figures["failures"]:
        print("  --- a failed run's end:\n" + tail)
    for name, ok in targets.items():
        print(f"  target {name}: {'MET' if ok else 'NOT MET'}")


def main() -> int:
    args = arguments()
    if args.realtime:
        REALTIME.append("--realtime")
    with_runs: list[dict[str, Any]] = []
    without_runs: list[dict[str, Any]] = []
    figures_costs = {} if args.skip_costs else costs()
    with tempfile.TemporaryDirectory() as tmp, served_armar3() as port, hogs(args.hogs):
        figures_decision = decision(args.decision_rounds, 3.0) if args.decision_rounds \
            else {}
        for k in range(args.runs):
            with_runs.append(run_with(port, args.seconds, Path(tmp)))
            without_runs.append(run_without(port, args.seconds))
            if not args.json:
                say_run(k, with_runs[-1], without_runs[-1])
        load = os.getloadavg()[0]
    figures = figures_of(args, with_runs, without_runs, figures_costs, figures_decision, load)
    targets = targets_of(figures, with_runs)
    figures["targets_met"] = {k: bool(v) for k, v in targets.items()}
    if args.json:
        print(json.dumps(figures, indent=2))
    else:
        say(args, figures, targets)
    return 0 if all(targets.values()) else 1


if __name__ == "__main__":
    with stop_signals():  # SIGTERM and SIGHUP as Ctrl-C: the fleet and the hogs stopped too
        sys.exit(main())
