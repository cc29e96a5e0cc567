#!/usr/bin/env python3
"""What sharing a running robot on Zenoh costs the 1 kHz loop, and how fast its values
reach another process (``ucom remote run --zenoh``, ``ucom-network(7)``).

ARMAR-III's CAN0 (3 boards) is served by ``ucom fleet serve`` in another process; this
process runs the PC's ``RemotePart`` on it over socketcand at 1 kHz, twice in the same
run: without sharing (the baseline) and shared on a loopback endpoint at
``--publish-rate`` (default 100 Hz) while a subscriber in a third process follows
``Right Eye Joint Sensor``.  Figures:

- ``missed_pct`` / ``jitter_p99_ms`` of the loop without and with sharing, and their
  ratio (target: lateness p99 with sharing <= 1.1x without);
- ``latency_p50_ms`` / ``latency_p99_ms``: from the board's time stamp of a value (the
  SO frame's end on the bus, on this machine's clock) to its arrival in the subscriber;
- ``cpu_pct`` of this process both ways, and ``share_cpu_us_per_value``: the extra CPU
  of sharing per value published.

``--json`` prints the figures as one JSON object.  Not measured here yet: a set-point
from ``ucom browse --set`` to its CI frame, and the latency at the loop's own rate.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks.runtime import percentile, served_armar3  # noqa: E402
from ucom_tools.ops.remote import RemotePart  # noqa: E402

SIGNAL = "Right Eye Joint Sensor"
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


def loop(port: int, seconds: float, zenoh: str | None, publish_hz: float) -> dict[str, Any]:
    """The 1 kHz loop on CAN0 for ``seconds``, shared on ``zenoh`` when given (with a
    subscriber process following SIGNAL)."""
    kwargs: dict[str, Any] = {"zenoh": zenoh, "publish_hz": publish_hz} if zenoh else {}
    child = None
    lines: list[str] = []
    ready = threading.Event()

    def read(stream: Any) -> None:
        for line in stream:
            if line.startswith("ready"):
                ready.set()
            elif line[:1].isdigit():
                lines.append(line)

    with RemotePart.open("armar3", interface="socketcand", host="127.0.0.1", port=port,
                         channels=("CAN0",), rate_hz=1000.0, **kwargs) as part:
        if zenoh:
            child = subprocess.Popen([sys.executable, "-c", SUBSCRIBER, zenoh, SIGNAL],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     text=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
            threading.Thread(target=read, args=(child.stdout,), daemon=True).start()
            deadline = time.monotonic() + 30
            while not ready.is_set() and time.monotonic() < deadline:
                part.cycle()  # the loop goes on (the watchdogs) while it connects
            if not ready.is_set():
                child.kill()
                raise SystemExit("the subscriber did not connect")
        part.stats.late.clear()
        lines.clear()
        cycles0, missed0 = part.stats.cycles, part.stats.missed
        cpu, wall = time.process_time(), time.perf_counter()
        end = wall + seconds
        while time.perf_counter() < end:
            part.cycle()
        wall = time.perf_counter() - wall
        cpu = time.process_time() - cpu
        s = part.stats
        cycles, missed = s.cycles - cycles0, s.missed - missed0
        late = list(s.late)
        values = len(part.names)
        got = list(lines)
    if child is not None:
        assert child.stdin is not None
        child.stdin.close()
        try:
            child.wait(timeout=10)
        except subprocess.TimeoutExpired:
            child.kill()
    lines = got
    lat = [float(x) for x in lines]
    return {"missed_pct": round(100 * missed / max(1, cycles + missed), 3),
            "jitter_p99_ms": round(percentile(late, 99) * 1e3, 3),
            "cpu_pct": round(100 * cpu / wall, 1), "cpu_s": cpu, "wall_s": wall,
            "values": values, "latency": lat}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--publish-rate", type=float, default=100.0)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    with served_armar3("1") as (_proc, port):
        plain = loop(port, args.seconds, None, args.publish_rate)
        shared = loop(port, args.seconds, f"tcp/127.0.0.1:{free_port()}", args.publish_rate)
    lat = shared.pop("latency")
    plain.pop("latency")
    published = shared["values"] * args.publish_rate * shared["wall_s"]
    extra = shared["cpu_s"] / shared["wall_s"] - plain["cpu_s"] / plain["wall_s"]
    figures: dict[str, Any] = {
        "publish_rate_hz": args.publish_rate,
        "missed_pct": plain["missed_pct"], "shared_missed_pct": shared["missed_pct"],
        "jitter_p99_ms": plain["jitter_p99_ms"],
        "shared_jitter_p99_ms": shared["jitter_p99_ms"],
        "jitter_ratio": round(shared["jitter_p99_ms"] / max(plain["jitter_p99_ms"], 1e-3), 2),
        "cpu_pct": plain["cpu_pct"], "shared_cpu_pct": shared["cpu_pct"],
        "share_cpu_us_per_value": round(1e6 * extra * shared["wall_s"] / max(published, 1),
                                        3),
        "samples": len(lat),
        "latency_p50_ms": round(percentile(lat, 50) * 1e3, 3),
        "latency_p99_ms": round(percentile(lat, 99) * 1e3, 3),
    }
    targets = {"lateness p99 with sharing <= 1.1x without":
               figures["shared_jitter_p99_ms"] <= 1.1 * max(figures["jitter_p99_ms"], 0.01)}
    figures["targets_met"] = {k: bool(v) for k, v in targets.items()}
    if args.json:
        print(json.dumps(figures, indent=2))
        return
    print(f"ARMAR-III CAN0 at 1 kHz over socketcand, {args.seconds:g} s each, values shared "
          f"on Zenoh at {args.publish_rate:g} Hz:")
    print(f"  loop      without sharing: {figures['missed_pct']} % missed, p99 "
          f"{figures['jitter_p99_ms']} ms, CPU {figures['cpu_pct']} %")
    print(f"            shared:          {figures['shared_missed_pct']} % missed, p99 "
          f"{figures['shared_jitter_p99_ms']} ms, CPU {figures['shared_cpu_pct']} % "
          f"({figures['share_cpu_us_per_value']} us per value published)")
    print(f"  latency   board time stamp to a subscriber in another process: p50 "
          f"{figures['latency_p50_ms']} ms, p99 {figures['latency_p99_ms']} ms "
          f"({figures['samples']} samples of {SIGNAL!r})")
    for name, ok in targets.items():
        print(f"  target {name}: {'MET' if ok else 'NOT MET'}")


if __name__ == "__main__":
    main()
