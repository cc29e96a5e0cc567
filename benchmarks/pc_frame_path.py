#!/usr/bin/env python3
"""The PC side's frame path over socketcand, without a fleet: CPU per frame and per cycle.

``benchmarks/runtime.py`` measures the PC side's CPU on a busy machine against a served
fleet whose own pace sets the frame rate, so its figures move with everything else that
runs.  This one takes the served fleet out: one real :class:`SocketcandBus` on a real
TCP connection to a scripted server in this process, with the subscribers a running
:class:`~ucom_tools.ops.remote.RemotePart` has on a bus (the bootloader link, the MCA
client's answers and process image, the loop's board-error watch) and, with ``--tap``,
the SO-age tap of ``runtime.py``.  Every cycle is one bus's cycle of ARMAR-III at 1 kHz:
the server writes 4 SO maps (3 of 8 bytes, one of 4); the PC holds the bus, sends 2 CI
maps (8 and 6 bytes) and every 10th cycle MCA Alive, releases it (one write) and drains
what came (:meth:`~ucom_tools.protocol.dispatch.Dispatcher.drain`).  Only the PC's part is
timed, in CPU time of this thread (``time.thread_time``), so other processes move the
figures less than runtime.py's (but still: caches, the kernel); the best of ``--runs``
runs is reported.

Figures: ``us_per_frame`` (CPU per frame received or sent, the socket system calls
included), ``us_per_cycle``, ``frames_per_cycle``, and ``all_us_per_frame`` (every run:
the spread says how noisy the machine was); ``plain_data_us_per_frame``, the receiving
parse alone: the cycles' chunks, as the server wrote them, fed to an
:class:`~ucom_tools.wire.socketcand.ElementSplitter` and taken by its ``plain_data``
after each run (the best of the runs; the client above reads through it too).
No target (``make bench`` passes it): it compares versions of the frame path, run from
each worktree.  ``--json`` prints the figures as one JSON object.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import socket
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from ucom_tools.protocol.link import Link  # noqa: E402
from ucom_tools.protocol.mca import McaClient  # noqa: E402
from ucom_tools.transport.socketcand import SocketcandBus  # noqa: E402
from ucom_tools.wire import mca  # noqa: E402
from ucom_tools.wire.ids import ALL, Function  # noqa: E402
from ucom_tools.wire.socketcand import ElementSplitter  # noqa: E402

SO_MAPS = ((0x3A1, 8), (0x3A2, 8), (0x3A3, 8), (0x3A4, 4))
"""SO maps a bus of ARMAR-III receives every cycle: identifier, data bytes."""
CI_MAPS = ((0x361, 8), (0x362, 6))
"""CI maps the PC sends every cycle."""
ALIVE_EVERY = 10
"""MCA Alive every this many cycles (its interval is a few ms)."""


def _greet(listener: socket.socket, out: list[socket.socket]) -> None:
    """The server's side of the handshake (``< hi >``, open, rawmode, echoes); the
    connection is left in ``out`` for the benchmark's loop."""
    conn, _ = listener.accept()
    conn.settimeout(5)
    conn.sendall(b"< hi >")
    heard = b""
    for answer in (b"< ok >", b"< ok >"):
        while b">" not in heard:
            heard += conn.recv(4096)
        heard = heard.split(b">", 1)[1]
        conn.sendall(answer)
    for _ in range(3):
        while b"echo" not in heard:
            heard += conn.recv(4096)
        heard = heard.split(b">", 1)[1]
        conn.sendall(b"< echo >")
    out.append(conn)


@contextlib.contextmanager
def connected() -> Iterator[tuple[SocketcandBus, socket.socket]]:
    """A SocketcandBus on CAN0 and the server's end of its connection."""
    listener = socket.create_server(("127.0.0.1", 0))
    conns: list[socket.socket] = []
    greeter = threading.Thread(target=_greet, args=(listener, conns), daemon=True)
    greeter.start()
    bus = SocketcandBus("CAN0", "127.0.0.1", listener.getsockname()[1])
    greeter.join(5)
    listener.close()
    try:
        yield bus, conns[0]
    finally:
        bus.shutdown()
        conns[0].close()


def subscribers(bus: SocketcandBus, tap: bool) -> Link:
    """The subscribers a running RemotePart has on a bus (see the module docstring)."""
    link = Link(bus, "CAN0", margin=0.01)
    McaClient(link)
    d = link.dispatcher
    d.subscribe(lambda msg: msg.arbitration_id >> 6 == Function.ERROR, "CAN0 board errors",
                on_frame=lambda msg: None)
    if tap:
        ages: list[float] = []

        def age(msg: can.Message) -> None:
            if msg.arbitration_id >> 6 == 14 and msg.is_rx:
                ages.append(time.time() - msg.timestamp)
                if len(ages) > 10_000:
                    ages.clear()
        d.taps.append(age)
    return link


def one_run(cycles: int, tap: bool) -> dict[str, float]:
    with connected() as (bus, server):
        link = subscribers(bus, tap)
        d = link.dispatcher
        alive = mca.encode(mca.Alive(), ALL)[0]
        payloads = [(ident, bytes(range(1, n + 1))) for ident, n in CI_MAPS]
        server.setblocking(False)
        cpu = 0.0
        frames0 = d.received + d.sent
        chunks = []
        for k in range(cycles):
            stamp = time.time()
            chunk = b"".join(b"< frame %03X %.6f %s >" % (
                ident, stamp + 1e-4 * i, bytes(n).hex().upper().encode())
                for i, (ident, n) in enumerate(SO_MAPS))
            server.sendall(chunk)
            chunks.append(chunk)
            t0 = time.thread_time()
            bus.hold()
            for ident, data in payloads:
                link.send_raw(ident, data)
            if k % ALIVE_EVERY == 0:
                link.send_raw(alive, b"")
            bus.release()
            d.drain()
            cpu += time.thread_time() - t0
            with contextlib.suppress(BlockingIOError):
                while server.recv(65536):
                    pass
        frames = d.received + d.sent - frames0
        if d.received < cycles * len(SO_MAPS) * 0.99:
            raise SystemExit(f"only {d.received} of {cycles * len(SO_MAPS)} frames came")
    return {"us_per_frame": round(1e6 * cpu / frames, 3),
            "us_per_cycle": round(1e6 * cpu / cycles, 2),
            "frames_per_cycle": round(frames / cycles, 2),
            "plain_data_us_per_frame": round(1e6 * parse_time(chunks), 3)}


def parse_time(chunks: list[bytes]) -> float:
    """CPU seconds per frame of the chunks fed to a splitter and taken by plain_data."""
    splitter = ElementSplitter()
    arrival = time.time()
    offset = math.inf
    taken = 0
    t0 = time.thread_time()
    for chunk in chunks:
        splitter.feed(chunk)
        frames, offset = splitter.plain_data(arrival, offset)
        taken += len(frames)
    cpu = time.thread_time() - t0
    if taken != len(chunks) * len(SO_MAPS):
        raise SystemExit(f"plain_data took {taken} of {len(chunks) * len(SO_MAPS)} frames")
    return cpu / taken


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=int, default=20_000)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--tap", action="store_true", help="with runtime.py's SO-age tap")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    runs = [one_run(args.cycles, args.tap) for _ in range(args.runs)]
    figures: dict[str, Any] = min(runs, key=lambda r: r["us_per_frame"])
    figures["plain_data_us_per_frame"] = min(r["plain_data_us_per_frame"] for r in runs)
    figures.update(cycles=args.cycles, runs=args.runs, tap=args.tap,
                   all_us_per_frame=[r["us_per_frame"] for r in runs])
    if args.json:
        print(json.dumps(figures, indent=2))
        return
    print(f"PC frame path over socketcand, one bus, {args.cycles} cycles x {args.runs} runs"
          f"{' with the SO-age tap' if args.tap else ''}:")
    print(f"  {figures['us_per_frame']} us of CPU per frame (best; all: "
          f"{figures['all_us_per_frame']}), {figures['us_per_cycle']} us per cycle of "
          f"{figures['frames_per_cycle']} frames")
    print(f"  {figures['plain_data_us_per_frame']} us of CPU per frame to feed the chunks to a "
          "splitter and take them with plain_data, alone")


if __name__ == "__main__":
    main()
