#!/usr/bin/env python3
"""`init` of up to 31 boards on one bus: no per-board timeout, so the time grows
linearly with the number of boards, plus one final timeout that ends the chain.

Prints, per chain length, the virtual bus time of the whole enumeration (the time a real
1 Mbit/s bus would take), its part before the final timeout, and the wall time on the
in-process fleet; then the slope per board and the worst deviation from a straight line.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from ucom_tools.config.topology import parse  # noqa: E402
from ucom_tools.protocol.bootloader import BootloaderClient  # noqa: E402
from ucom_tools.protocol.link import Link  # noqa: E402
from ucom_tools.protocol.timeouts import DEFAULT  # noqa: E402
from ucom_tools.virtual.canbus import VirtualUcomBus  # noqa: E402
from ucom_tools.virtual.fleet import Fleet  # noqa: E402


def run(n: int) -> tuple[float, float, int]:
    text = 'name = "bench"\n[[bus]]\nname = "CAN0"\nbitrate = 1000000\n'
    text += '[[bus.board]]\nplacement = "x"\nboard = "3M"\n' * n
    bus = VirtualUcomBus("CAN0", fleet=Fleet(parse(text, "<init>")))
    try:
        client = BootloaderClient(Link(bus))
        t0v, t0 = bus.sim.now, time.perf_counter()
        result = client.init_chain()
        wall = time.perf_counter() - t0
        assert [a.seq_id for a in result.acks] == list(range(1, n + 1))
        return (bus.sim.now - t0v) / 1e3, wall * 1e3, len(result.acks)
    finally:
        bus.shutdown()


def main() -> int:
    final = DEFAULT.init_step * 1e3
    rows = []
    print(f"{'boards':>6} {'virtual ms':>11} {'without final timeout':>22} {'wall ms':>8}")
    for n in (1, 2, 4, 8, 16, 24, 31):
        virt, wall, _found = run(n)
        # a chain of 31 is complete without a timeout: there is no seq ID 32 to look for
        steps = virt - (final if n < 31 else 0.0)
        rows.append((n, steps))
        print(f"{n:>6} {virt:>11.2f} {steps:>22.2f} {wall:>8.2f}")
    (n1, y1), (n2, y2) = rows[0], rows[-1]
    slope = (y2 - y1) / (n2 - n1)
    worst = max(abs(y - (y1 + slope * (n - n1))) for n, y in rows)
    print(f"slope {slope:.3f} ms per board; one final timeout of {final:.0f} ms per bus; "
          f"largest deviation from linear {worst:.3f} ms")
    linear = worst < 0.05 * (y2 - y1) and slope < final
    print("no per-board timeout, linear growth:", "MET" if linear else "NOT MET")
    return 0 if linear else 1


if __name__ == "__main__":
    sys.exit(main())
