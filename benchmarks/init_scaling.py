#!/usr/bin/env python3
"""`init` of up to 31 boards on one bus: no per-board timeout, so the time grows
linearly with the number of boards, plus the final wait that ends the chain (T_init,
asked 1 + retries times, so a lost frame cannot cut the chain short).

Prints, per chain length, the virtual bus time of the whole enumeration (the time a real
1 Mbit/s bus would take), its part up to the last Init Ack, and the wall time on the
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


class AckClock:
    """A listener on the simulated bus: when did the last Init Ack end?"""

    def __init__(self) -> None:
        self.last = 0.0

    def on_frame(self, arbitration_id: int, data: bytes, t_end: float) -> None:
        if arbitration_id >> 6 == 3:
            self.last = t_end


def run(n: int) -> tuple[float, float, float]:
    text = 'name = "bench"\n[[bus]]\nname = "CAN0"\nbitrate = 1000000\n'
    text += "".join(f'[[bus.board]]\nplacement = "slot {i + 1}"\nboard = "3M"\n' for i in range(n))
    bus = VirtualUcomBus("CAN0", fleet=Fleet(parse(text, "<init>")))
    acks = AckClock()
    bus.sim.attach(acks)
    try:
        client = BootloaderClient(Link(bus))
        t0v, t0 = bus.sim.now, time.perf_counter()
        result = client.init_chain()
        wall = time.perf_counter() - t0
        assert [a.seq_id for a in result.acks] == list(range(1, n + 1))
        return (bus.sim.now - t0v) / 1e3, (acks.last - t0v) / 1e3, wall * 1e3
    finally:
        bus.shutdown()


def main() -> int:
    asks = 1 + DEFAULT.retries
    rows = []
    tails = []
    print(f"{'boards':>6} {'virtual ms':>11} {'to the last Init Ack':>21} {'final wait':>11} "
          f"{'wall ms':>8}")
    for n in (1, 2, 4, 8, 16, 24, 31):
        virt, steps, wall = run(n)
        rows.append((n, steps))
        if n < 31:  # a chain of 31 is complete: there is no seq ID 32 to look for
            tails.append(virt - steps)
        print(f"{n:>6} {virt:>11.2f} {steps:>21.2f} {virt - steps:>11.2f} {wall:>8.2f}")
    (n1, y1), (n2, y2) = rows[0], rows[-1]
    slope = (y2 - y1) / (n2 - n1)
    worst = max(abs(y - (y1 + slope * (n - n1))) for n, y in rows)
    final = max(tails)
    print(f"slope {slope:.3f} ms per board; final wait {final:.1f} ms per bus (T_init "
          f"{DEFAULT.init_step * 1e3:.0f} ms asked {asks} times); largest deviation from "
          f"linear {worst:.3f} ms")
    linear = worst < 0.05 * (y2 - y1) and slope < DEFAULT.init_step * 1e3
    print("no per-board timeout, linear growth:", "MET" if linear else "NOT MET")
    return 0 if linear else 1


if __name__ == "__main__":
    sys.exit(main())
