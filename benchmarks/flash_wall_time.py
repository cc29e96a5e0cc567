#!/usr/bin/env python3
"""Wall time of `flash` of a 64 KiB image into all 11 ARMAR-III boards on the in-process
virtual fleet, against a baseline measured in the same run: the canopen library's SDO
download of the same 64 KiB into one canopen LocalNode on python-can's virtual bus.

Target: ours at least 4x faster for 11 boards than the baseline for one.
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

import canopen
from canopen.objectdictionary import DOMAIN, ObjectDictionary, ODVariable

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from ucom_tools.image.formats import load_image  # noqa: E402
from ucom_tools.ops.flash import flash  # noqa: E402
from ucom_tools.ops.flash_types import FlashRequest  # noqa: E402
from ucom_tools.ops.robot import ConnectSpec, open_robot  # noqa: E402

IMAGE = ROOT / "firmware_images" / "bench64k.fl.S"
RUNS = 3


def baseline_sdo(data: bytes) -> float:
    od = ObjectDictionary()
    var = ODVariable("image", 0x2000, 0)
    var.data_type = DOMAIN
    var.access_type = "rw"
    od.add_object(var)
    channel = f"bench-{time.monotonic_ns()}"
    server_net, client_net = canopen.Network(), canopen.Network()
    server_net.connect(interface="virtual", channel=channel)
    client_net.connect(interface="virtual", channel=channel)
    try:
        local = server_net.create_node(1, od)
        remote = canopen.RemoteNode(1, od)
        client_net.add_node(remote)
        t0 = time.perf_counter()
        remote.sdo.download(0x2000, 0, data)
        elapsed = time.perf_counter() - t0
        assert bytes(local.sdo.upload(0x2000, 0)) == data
        return elapsed
    finally:
        client_net.disconnect()
        server_net.disconnect()


def ours(image) -> tuple[float, int]:
    robot = open_robot(ConnectSpec(virtual="armar3"))
    try:
        for h in robot.buses.values():
            h.client.reset()
        t0 = time.perf_counter()
        result = flash(robot, FlashRequest(image))
        elapsed = time.perf_counter() - t0
        assert result.all_verified, [b.detail for b in result.failed]
        return elapsed, len(result.boards)
    finally:
        robot.close()


def main() -> int:
    image = load_image(IMAGE)
    data = b"".join(w.to_bytes(2, "little") for _, w in sorted(image.words.items()))
    assert len(data) == 64 * 1024
    base = [baseline_sdo(data) for _ in range(RUNS)]
    mine = [ours(image) for _ in range(RUNS)]
    b, o = statistics.median(base), statistics.median(t for t, _ in mine)
    boards = mine[0][1]
    print(f"image: {IMAGE.name}, {len(data)} bytes")
    print(f"baseline  canopen SDO download, 1 LocalNode, python-can virtual bus: "
          f"median {b:.3f} s  (runs: {', '.join(f'{x:.3f}' for x in base)})")
    print(f"ucom      flash into {boards} ARMAR-III boards on 4 virtual buses (incl. init, "
          f"verify, read-back): median {o:.3f} s  (runs: {', '.join(f'{t:.3f}' for t, _ in mine)})")
    ratio = b / o
    print(f"ratio     baseline(1 node) / ucom({boards} boards) = {ratio:.1f}x  (target >= 4x): "
          f"{'MET' if ratio >= 4 else 'NOT MET'}")
    return 0 if ratio >= 4 else 1


if __name__ == "__main__":
    sys.exit(main())
