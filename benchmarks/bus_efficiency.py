#!/usr/bin/env python3
"""Bus efficiency of programming on the bus model: image payload bits per wire bit for a
64 KiB image into 1 and into 31 boards of one 1 Mbit/s bus, every frame counted from
ProgEnable to the last Program Finished (stuff bits included), against Tab. B.2's limit
for 8-byte frames (64 of 111 bits = 577 kbit/s).

Targets (man/ucom-protocol.7): >= 90 % of the limit for 1 board, >= 85 % for 31.
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from ucom_tools.config.topology import parse  # noqa: E402
from ucom_tools.image.formats import load_image  # noqa: E402
from ucom_tools.protocol.bootloader import BootloaderClient  # noqa: E402
from ucom_tools.protocol.link import Link  # noqa: E402
from ucom_tools.protocol.programmer import Programmer  # noqa: E402
from ucom_tools.virtual.canbus import VirtualUcomBus  # noqa: E402
from ucom_tools.virtual.fleet import Fleet  # noqa: E402
from ucom_tools.wire.canbits import payload_rate  # noqa: E402
from ucom_tools.wire.codes import StatusOp  # noqa: E402
from ucom_tools.wire.ids import ALL, seq  # noqa: E402

LIMIT = payload_rate(8) / 1e6  # 0.5766 payload bits per wire bit
TARGETS = {1: 0.90, 31: 0.85}


def chain(n: int) -> Fleet:
    text = 'name = "bench"\n[[bus]]\nname = "CAN0"\nbitrate = 1000000\n'
    text += "".join(f'[[bus.board]]\nplacement = "slot {i + 1}"\nboard = "3M"\n' for i in range(n))
    return Fleet(parse(text, f"<{n} boards>"))


def measure(n: int, image) -> tuple[float, int, int, float]:
    fleet = chain(n)
    bus = VirtualUcomBus("CAN0", fleet=fleet)
    try:
        link = Link(bus)
        client = BootloaderClient(link)
        init = client.init_chain()
        stats = bus.sim.stats
        bits0, frames0, t0 = stats.bits, stats.frames, bus.sim.now
        client.set_status(ALL, StatusOp.PROG_ENABLE, 1)
        result = Programmer(link).transfer(image.plan(), [seq(k) for k in init.numbers])
        assert result.all_verified
        wire = stats.bits - bits0
        useful = image.plan().size_words * 16  # the image's bits, not the protocol's
        return useful / wire, stats.frames - frames0, wire, (bus.sim.now - t0) / 1e6
    finally:
        bus.shutdown()


def main() -> int:
    image = load_image(ROOT / "firmware_images" / "bench64k.fl.S")
    print(f"limit (Tab. B.2, 8-byte frames at 1 Mbit/s): {LIMIT * 1000:.0f} kbit/s = "
          f"{LIMIT:.4f} payload bits per wire bit")
    ok = True
    for n, target in TARGETS.items():
        eff, frames, wire, virt = measure(n, image)
        share = eff / LIMIT
        met = share >= target
        ok &= met
        print(f"{n:2d} board(s): {frames} frames, {wire} wire bits, {eff:.4f} payload/wire = "
              f"{eff * 1000:.0f} kbit/s = {share * 100:.1f} % of the limit (target "
              f">= {target * 100:.0f} %): {'MET' if met else 'NOT MET'}; virtual time "
              f"{virt:.2f} s incl. flash erase")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
