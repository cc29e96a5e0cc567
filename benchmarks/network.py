#!/usr/bin/env python3
"""What sharing a running robot on Zenoh costs the 1 kHz loop, and how fast its values
reach another process (``ucom remote run --zenoh``, ``ucom-network(7)``).

ARMAR-III's CAN0 (3 boards) is served by ``ucom fleet serve`` in another process; this
process runs the PC's ``RemotePart`` on it over socketcand at 1 kHz, three times in the
same run: without sharing (the baseline), shared on a loopback endpoint at
``--publish-rate`` (default 100 Hz), and shared at the loop's rate (1000 Hz), each time
with a subscriber following ``Right Eye Joint Sensor`` on another host: in a network
namespace joined to this one by a veth pair, the robot listening on its end (as root
with ip(8); else, or with ``--loopback``, in another process on loopback:
``subscriber`` says which).  Figures:

- ``missed_pct`` / ``jitter_p99_ms`` of the loop without and with sharing (at
  ``--publish-rate``), and their ratio; ``loop_rate_missed_pct`` /
  ``loop_rate_jitter_p99_ms`` with values shared at 1000 Hz;
- ``latency_p50_ms`` / ``latency_p99_ms``: from the board's time stamp of a value (the
  SO frame's end on the bus, on this machine's clock) to its arrival in the subscriber,
  at ``--publish-rate``; ``loop_rate_latency_p50_ms`` / ``loop_rate_latency_p99_ms`` the
  same at 1000 Hz;
- ``setpoint_p50_ms`` / ``setpoint_p99_ms``: a set-point written from another process
  (``RobotClient.write``, what ``ucom browse --set`` does; ``--setpoints`` of them, each
  value new) to its CI frame on the bus: from the write's start to the time stamp of the
  first CI map frame that carries the value, seen by another client of the served bus;
- ``cpu_pct`` of this process both ways, and ``share_cpu_us_per_value``: the extra CPU
  of sharing per value of the robot's edges at the publishing rate;
- ``watchdog_stops`` of each run (boards that stopped: then the served fleet or the loop
  fell behind, and the latencies say so rather than the network) and ``load_average``.

Targets (``targets_met``, MET or NOT MET in the text): lateness p99 and missed share
with sharing <= 1.1x without (within 0.01 ms / 0.1 point: the noise of a 5 s run),
latency p99 at 100 Hz under 20 ms and at the loop rate under 10 ms, set-point p99 under
20 ms.  ``--json`` prints the figures as one JSON object.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks.runtime import percentile, served_armar3  # noqa: E402
from ucom_tools.net.share import open_shared  # noqa: E402
from ucom_tools.ops.remote import RemotePart  # noqa: E402
from ucom_tools.signals import stop_signals  # noqa: E402
from ucom_tools.wire import mca  # noqa: E402
from ucom_tools.wire.ids import Function  # noqa: E402

SIGNAL = "Right Eye Joint Sensor"
TARGET = "Right Eye Target"
WRITER = """
import sys, time
from ucom_tools.net.client import RobotClient
client = RobotClient.connect(sys.argv[1], timeout=10)
print("ready", flush=True)
sys.stdin.readline()  # the bus listener is ready
for k in range(int(sys.argv[2])):
    value = 200 + k % 2 * 100 + k  # a new value every time
    start = time.time()
    client.write(sys.argv[3], value)
    print(f"{value} {start:.6f}", flush=True)
client.close()
"""
CI_LISTENER = """
import sys, time
from ucom_tools.transport.socketcand import SocketcandBus
from ucom_tools.wire.mca import mask
port, ident, offset = (int(x) for x in sys.argv[1:4])
signed = sys.argv[4] == "1"
bus = SocketcandBus("CAN0", "127.0.0.1", port)
print("ready", flush=True)
last = None
while True:
    msg = bus.recv(0.5)
    if msg is None or msg.arbitration_id != ident:
        continue
    data = mask(bytes(msg.data))
    value = int.from_bytes(data[offset:offset + 2], "big", signed=signed)
    if value != last:
        last = value
        print(f"{value} {msg.timestamp:.6f}", flush=True)
"""
SUBSCRIBER = """
import sys, time
from ucom_tools.net.client import RobotClient
client = RobotClient.connect(sys.argv[1], timeout=10)
print("ready", flush=True)
def on_value(t, name, value):
    print(f"{time.time() - t:.6f}", flush=True)
client.subscribe([sys.argv[2]], on_value)
sys.stdin.read()
client.close()
"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def ci_slot(part: RemotePart, name: str) -> tuple[int, int, bool]:
    """Where the CI ``name`` travels on its bus: the CI map frame's identifier, the value's
    byte offset in its (unmasked) data, signed or not."""
    ref = part.names.resolve(name)
    x = part.exchanges[ref.bus]
    for c in x.plan.ci_maps:
        used = [slot for slot in c.slots if slot is not None]
        if (ref.board, ref.index) in used:
            ident = mca.MapFrame(Function.MCA_CONTROLLER_INPUT, c.number, bytes(2))
            return ident.arbitration_id(), 2 * used.index((ref.board, ref.index)), \
                ref.spec.signed
    raise SystemExit(f"{name} is in no CI map")


def child(code: str, *args: str, where: tuple[str, ...] = ()) -> tuple[
        subprocess.Popen[str], list[str], threading.Event]:
    """A Python process running ``code`` (``where``: a prefix, ``ip netns exec NS``): its
    number lines, and an event set by "ready" (or by its end)."""
    proc = subprocess.Popen([*where, sys.executable, "-c", code, *args],
                            stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": str(ROOT)})
    lines: list[str] = []
    ready = threading.Event()

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            if line.startswith("ready"):
                ready.set()
            else:
                lines.append(line.strip())
        ready.set()
    threading.Thread(target=read, daemon=True).start()
    return proc, lines, ready


def end(proc: subprocess.Popen[str], cycle: Callable[[], object] | None = None) -> None:
    """Close ``proc``'s input and wait (10 s at most) for it to end, the loop cycling
    meanwhile where ``cycle`` is given (a loop that waited would let every board's
    watchdog stop it, and the run would end with its boards lost)."""
    if proc.stdin is not None:
        proc.stdin.close()
    deadline = time.monotonic() + 10
    while proc.poll() is None and time.monotonic() < deadline:
        if cycle is not None:
            cycle()
        else:
            time.sleep(0.01)
    if proc.poll() is None:
        proc.kill()
        proc.wait()


def loop(port: int, seconds: float, zenoh: str | None, publish_hz: float,
         setpoints: int = 0, where: tuple[str, ...] = ()) -> dict[str, Any]:
    """The 1 kHz loop on CAN0 for ``seconds``, shared on ``zenoh`` when given (with a
    subscriber process following SIGNAL); then, with ``setpoints``, that many writes of
    TARGET from another process, timed to their CI frames on the bus."""
    kwargs: dict[str, Any] = {"zenoh": zenoh, "publish_hz": publish_hz,
                              "allow_writes": setpoints > 0} if zenoh else {}
    sub = None
    lines: list[str] = []
    sets: list[str] = []
    frames: list[str] = []
    opener = open_shared if zenoh else RemotePart.open
    with opener("armar3", interface="socketcand", host="127.0.0.1", port=port,
                channels=("CAN0",), rate_hz=1000.0, **kwargs) as part:
        if zenoh:
            sub, lines, ready = child(SUBSCRIBER, zenoh, SIGNAL, where=where)
            deadline = time.monotonic() + 30
            while not ready.is_set() and time.monotonic() < deadline:
                part.cycle()  # the loop goes on (the watchdogs) while it connects
            if sub.poll() is not None or not ready.is_set():
                sub.kill()
                raise SystemExit("the subscriber did not connect")
        part.stats.late.clear()
        lines.clear()
        cycles0, missed0 = part.stats.cycles, part.stats.missed
        cpu, wall = time.process_time(), time.perf_counter()
        stop = wall + seconds
        while time.perf_counter() < stop:
            part.cycle()
        wall = time.perf_counter() - wall
        cpu = time.process_time() - cpu
        s = part.stats
        cycles, missed = s.cycles - cycles0, s.missed - missed0
        late = list(s.late)
        values = len(part.names)
        stops = sum(1 for e in part.events if e.stopped_motors)
        got = list(lines)
        if sub is not None:
            end(sub, part.cycle)
        if zenoh and setpoints:
            ident, offset, signed = ci_slot(part, TARGET)
            listener, frames, heard = child(CI_LISTENER, str(port), str(ident), str(offset),
                                            "1" if signed else "0")
            writer, sets, connected = child(WRITER, zenoh, str(setpoints), TARGET,
                                            where=where)
            deadline = time.monotonic() + 30
            while not (heard.is_set() and connected.is_set()) \
                    and time.monotonic() < deadline:
                part.cycle()
            assert writer.stdin is not None
            writer.stdin.write("go\n")
            writer.stdin.flush()
            deadline = time.monotonic() + 30 + setpoints * 2
            while writer.poll() is None and time.monotonic() < deadline:
                part.cycle()
            stop_at = time.monotonic() + 0.1  # the last frame's way to the listener
            while time.monotonic() < stop_at:
                part.cycle()
            end(writer, part.cycle)
            listener.kill()
            listener.wait()
    lat = [float(x) for x in got if x[:1].isdigit()]
    return {"missed_pct": round(100 * missed / max(1, cycles + missed), 3),
            "jitter_p99_ms": round(percentile(late, 99) * 1e3, 3),
            "cpu_pct": round(100 * cpu / wall, 1), "cpu_s": cpu, "wall_s": wall,
            "values": values, "latency": lat, "watchdog_stops": stops,
            **setpoint_times(sets, frames if zenoh and setpoints else [])}


def setpoint_times(sets: list[str], frames: list[str]) -> dict[str, Any]:
    """Each write's way to its frame: the writer's "VALUE START" lines against the bus
    listener's "VALUE STAMP" lines (the first frame that carried each value)."""
    first: dict[int, float] = {}
    for line in frames:
        value, stamp = line.split()
        first.setdefault(int(value), float(stamp))
    times, lost = [], 0
    for line in sets:
        value, start = line.split()
        if int(value) in first:
            times.append(first[int(value)] - float(start))
        else:
            lost += 1
    return {"setpoints": times, "setpoints_lost": lost}


@contextlib.contextmanager
def other_host(wanted: bool) -> Iterator[tuple[tuple[str, ...], str, str]]:
    """Where the subscriber and the writer run: a network namespace joined to this one by
    a veth pair (as root, with ip(8)), the robot listening on its end: (the ``ip netns
    exec`` prefix, the robot's address, what it is); else loopback, saying why."""
    ns = f"ucombench{os.getpid() % 100000}"
    here, there = f"ucb{os.getpid() % 100000}a", f"ucb{os.getpid() % 100000}b"
    net = f"10.250.{os.getpid() % 250}"

    def ip(*args: str) -> bool:
        return subprocess.run(["ip", *args], capture_output=True).returncode == 0
    why = ("--loopback" if not wanted else "not root" if os.geteuid() != 0
           else "no ip(8)" if shutil.which("ip") is None else None)
    made = why is None and ip("netns", "add", ns)
    try:
        if made and all([
                ip("link", "add", here, "type", "veth", "peer", "name", there, "netns", ns),
                ip("addr", "add", f"{net}.1/24", "dev", here), ip("link", "set", here, "up"),
                ip("-n", ns, "addr", "add", f"{net}.2/24", "dev", there),
                ip("-n", ns, "link", "set", there, "up"),
                ip("-n", ns, "link", "set", "lo", "up")]):
            yield ("ip", "netns", "exec", ns), f"{net}.1", \
                "in another network namespace (a veth pair)"
        else:
            yield (), "127.0.0.1", \
                f"in another process on loopback ({why or 'no network namespace here'})"
    finally:
        if made:
            ip("netns", "del", ns)
            ip("link", "del", here)


def ms(values: list[float], p: float) -> float | None:
    return round(percentile(values, p) * 1e3, 3) if values else None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--publish-rate", type=float, default=100.0)
    ap.add_argument("--setpoints", type=int, default=100)
    ap.add_argument("--loopback", action="store_true",
                    help="subscriber and writer on loopback, not in a network namespace")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    with served_armar3("1") as (_proc, port), other_host(not args.loopback) as (
            where, address, remote):
        plain = loop(port, args.seconds, None, args.publish_rate)
        shared = loop(port, args.seconds, f"tcp/{address}:{free_port()}", args.publish_rate,
                      setpoints=args.setpoints, where=where)
        fast = loop(port, args.seconds, f"tcp/{address}:{free_port()}", 1000.0, where=where)
    lat, fast_lat, sets = shared["latency"], fast["latency"], shared["setpoints"]
    published = shared["values"] * args.publish_rate * shared["wall_s"]
    extra = shared["cpu_s"] / shared["wall_s"] - plain["cpu_s"] / plain["wall_s"]
    figures: dict[str, Any] = {
        "publish_rate_hz": args.publish_rate, "subscriber": remote,
        "missed_pct": plain["missed_pct"], "shared_missed_pct": shared["missed_pct"],
        "jitter_p99_ms": plain["jitter_p99_ms"],
        "shared_jitter_p99_ms": shared["jitter_p99_ms"],
        "jitter_ratio": round(shared["jitter_p99_ms"] / max(plain["jitter_p99_ms"], 1e-3), 2),
        "cpu_pct": plain["cpu_pct"], "shared_cpu_pct": shared["cpu_pct"],
        "share_cpu_us_per_value": round(1e6 * extra * shared["wall_s"] / max(published, 1),
                                        3),
        "samples": len(lat),
        "latency_p50_ms": ms(lat, 50), "latency_p99_ms": ms(lat, 99),
        "loop_rate_missed_pct": fast["missed_pct"],
        "loop_rate_jitter_p99_ms": fast["jitter_p99_ms"],
        "loop_rate_cpu_pct": fast["cpu_pct"],
        "loop_rate_samples": len(fast_lat),
        "loop_rate_latency_p50_ms": ms(fast_lat, 50),
        "loop_rate_latency_p99_ms": ms(fast_lat, 99),
        "setpoints": len(sets), "setpoints_lost": shared["setpoints_lost"],
        "setpoint_p50_ms": ms(sets, 50), "setpoint_p99_ms": ms(sets, 99),
        "watchdog_stops": {"plain": plain["watchdog_stops"], "shared": shared["watchdog_stops"],
                           "loop_rate": fast["watchdog_stops"]},
        "load_average": round(os.getloadavg()[0], 2),
    }

    def under(key: str, limit: float) -> bool:
        return figures[key] is not None and figures[key] < limit
    targets = {
        "lateness p99 with sharing <= 1.1x without":
            figures["shared_jitter_p99_ms"] <= 1.1 * figures["jitter_p99_ms"] + 0.01,
        "missed with sharing <= 1.1x without":
            figures["shared_missed_pct"] <= 1.1 * figures["missed_pct"] + 0.1,
        f"latency p99 at {args.publish_rate:g} Hz < 20 ms": under("latency_p99_ms", 20),
        "latency p99 at the loop rate < 10 ms": under("loop_rate_latency_p99_ms", 10),
        "set-point p99 < 20 ms, none lost":
            under("setpoint_p99_ms", 20) and not figures["setpoints_lost"],
    }
    figures["targets_met"] = {k: bool(v) for k, v in targets.items()}
    if args.json:
        print(json.dumps(figures, indent=2))
    else:
        say(args, figures, targets, remote)


def say(args: argparse.Namespace, figures: dict[str, Any], targets: dict[str, bool],
        remote: str) -> None:
    print(f"ARMAR-III CAN0 at 1 kHz over socketcand, {args.seconds:g} s each, values shared "
          f"on Zenoh at {args.publish_rate:g} Hz and at 1000 Hz:")
    print(f"  loop      without sharing: {figures['missed_pct']} % missed, p99 "
          f"{figures['jitter_p99_ms']} ms, CPU {figures['cpu_pct']} %")
    print(f"            shared:          {figures['shared_missed_pct']} % missed, p99 "
          f"{figures['shared_jitter_p99_ms']} ms, CPU {figures['shared_cpu_pct']} % "
          f"({figures['share_cpu_us_per_value']} us per value published)")
    print(f"            shared, 1000 Hz: {figures['loop_rate_missed_pct']} % missed, p99 "
          f"{figures['loop_rate_jitter_p99_ms']} ms, CPU {figures['loop_rate_cpu_pct']} %")
    print(f"  latency   board time stamp to a subscriber {remote}: p50 "
          f"{figures['latency_p50_ms']} ms, p99 {figures['latency_p99_ms']} ms "
          f"({figures['samples']} samples of {SIGNAL!r}); at 1000 Hz p50 "
          f"{figures['loop_rate_latency_p50_ms']} ms, p99 "
          f"{figures['loop_rate_latency_p99_ms']} ms ({figures['loop_rate_samples']})")
    print(f"  set-point RobotClient.write ({remote}) to its CI frame on the bus: p50 "
          f"{figures['setpoint_p50_ms']} ms, p99 {figures['setpoint_p99_ms']} ms "
          f"({figures['setpoints']} of {TARGET!r}, {figures['setpoints_lost']} lost)")
    stops = figures["watchdog_stops"]
    if any(stops.values()):
        print(f"  boards    stopped by their watchdog: {stops} (the loop or the served fleet "
              "fell behind: the figures are not the network's)")
    print(f"  machine   load average {figures['load_average']} on {os.cpu_count()} cores")
    for name, ok in targets.items():
        print(f"  target {name}: {'MET' if ok else 'NOT MET'}")


if __name__ == "__main__":
    with stop_signals():  # SIGTERM and SIGHUP as Ctrl-C: a served fleet is stopped too
        main()
