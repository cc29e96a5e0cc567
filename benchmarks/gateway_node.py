#!/usr/bin/env python3
"""What the gateway's CANopen node runtime (``ucom_tools.gateway.node``) costs per node
and SYNC, against canopen's ``LocalNode`` TPDO path in the same run, and how long a
master waits for an SDO answer while SYNCs run.

``--nodes`` nodes (default 9, one UCoM bus's joints) on python-can's virtual bus, each
from ``tests/data/gateway_node.eds`` with its two TPDOs of transmission type 1 (0x6041 +
0x6061, 0x6064 + 0x606C), all OPERATIONAL; a master (canopen's ``Network``) on another
end of the channel sends ``--syncs`` SYNCs at ``--rate`` Hz.  On every SYNC the
application refreshes the four mapped values of every node:

- runtime: in ``on_sync`` with ``NodeRuntime.set``; the runtime builds the TPDO frames
  from the stored bytes and sends them;
- baseline: canopen's way on ``LocalNode``: a SYNC subscriber sets the values through
  ``node.tpdo[n][name].raw`` and calls ``transmit()`` for each TPDO.

Figures: ``cpu_us_per_node_sync`` (the handling thread's CPU time spent on SYNCs, per
node and SYNC; the runtime's also with its whole thread, idle turns included:
``thread_cpu_us_per_node_sync``) and ``speedup``; ``virtual_bus_send_us``, what python-can's
virtual bus itself costs a frame (measured beside: it deep-copies every frame for every
receiver), and both paths without it (``..._without_bus``, ``speedup_without_bus``);
then SDO upload round trips of 0x6064 (rotating over the nodes, ``--uploads`` each)
idle and while SYNC runs at 100 Hz and 250 Hz: ``sdo_p50_ms`` / ``sdo_p99_ms`` each, and
``tpdos_per_sync`` (every node's two TPDOs came, or the runtime fell behind).

Targets (``targets_met``; MET or NOT MET in the text, exit 1 when one is not): the
runtime at most a third of the baseline's CPU per node and SYNC without the virtual
bus's own sending (with it, the bus's 2 frames a node dominate both; measured here:
24.9 against 48.2 us, 10.0 against 33.3 us without, 7.5 us a frame); every SYNC's TPDOs
sent at 250 Hz; SDO p99 at 250 Hz under 10 ms (ros2_canopen's default SDO timeout is
20 ms).  ``--json`` prints the figures as one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import can
import canopen

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks.runtime import percentile  # noqa: E402
from ucom_tools.gateway.codes import NmtCommand  # noqa: E402
from ucom_tools.gateway.node import NodeCallbacks, NodeRuntime  # noqa: E402

EDS = str(ROOT / "tests" / "data" / "gateway_node.eds")
MAPPED = ((1, "Statusword", 0x6041), (1, "Modes of operation display", 0x6061),
          (2, "Position actual value", 0x6064), (2, "Velocity actual value", 0x606C))


class Counter(can.Listener):
    """Counts the TPDO frames the master receives."""

    def __init__(self) -> None:
        self.tpdos = 0

    def on_message_received(self, msg: can.Message) -> None:
        if 0x181 <= msg.arbitration_id <= 0x2FF:
            self.tpdos += 1


def values(k: int, node: int) -> tuple[int, int, int, int]:
    return (0x0237, 1, k * 10 + node, -k)


def wait_until(pred: Any, timeout: float) -> bool:
    """``pred()`` true within ``timeout`` (checked every millisecond)."""
    deadline = time.monotonic() + timeout
    tick = threading.Event()
    while not pred():
        if time.monotonic() > deadline:
            return False
        tick.wait(0.001)
    return True


def master(channel: str) -> tuple[can.BusABC, canopen.Network, Counter]:
    bus = can.Bus(interface="virtual", channel=channel)
    net = canopen.Network(bus)
    net.NOTIFIER_CYCLE = 0.05
    counter = Counter()
    net.listeners.append(counter)
    net.connect()
    return bus, net, counter


def run_syncs(net: canopen.Network, syncs: int, rate: float, done: Any) -> float:
    """``syncs`` SYNCs at ``rate``; the seconds it took until ``done()``."""
    start = time.monotonic()
    net.sync.start(1.0 / rate)
    try:
        wait_until(done, syncs / rate * 3 + 5)
    finally:
        net.sync.stop()
    return time.monotonic() - start


def bench_runtime(nodes: int, syncs: int, rate: float) -> dict[str, Any]:
    channel = f"bench-gw-{uuid.uuid4().hex}"
    _, net, counter = master(channel)
    node_bus = can.Bus(interface="virtual", channel=channel)
    ids = list(range(1, nodes + 1))
    state = {"k": 0}
    runtime: NodeRuntime

    def on_sync(counter_value: int | None) -> None:
        k = state["k"] = state["k"] + 1
        for node in slaves:
            for (_, _, index), value in zip(MAPPED, values(k, node.id), strict=True):
                node.set(index, 0, value)

    runtime = NodeRuntime(node_bus, {i: canopen.import_od(EDS, i) for i in ids},
                          NodeCallbacks(on_sync=on_sync))
    slaves = [runtime.node(i) for i in ids]
    try:
        runtime.start()
        net.nmt.send_command(NmtCommand.START)
        wait_until(lambda: all(runtime.state(i) == 5 for i in ids), 5)
        before = runtime.stats()
        seconds = run_syncs(net, syncs, rate, lambda: runtime.stats().syncs - before.syncs
                            >= syncs)
        after = runtime.stats()
        # the thread's CPU so far: read from outside through its clock
        thread = runtime._thread
        assert thread is not None and thread.ident is not None
        thread_cpu = time.clock_gettime(time.pthread_getcpuclockid(thread.ident))
        done = after.syncs - before.syncs
        return {"syncs": done, "seconds": round(seconds, 2),
                "cpu_us_per_node_sync": round((after.sync_cpu_s - before.sync_cpu_s)
                                              / done / nodes * 1e6, 2),
                "thread_cpu_us_per_node_sync": round(thread_cpu / done / nodes * 1e6, 2),
                "tpdos_per_sync": round(counter.tpdos / done, 2)}
    finally:
        runtime.close()
        net.disconnect()
        node_bus.shutdown()


def bench_baseline(nodes: int, syncs: int, rate: float) -> dict[str, Any]:
    channel = f"bench-gw-{uuid.uuid4().hex}"
    _, net, counter = master(channel)
    node_net = canopen.Network(can.Bus(interface="virtual", channel=channel))
    node_net.NOTIFIER_CYCLE = 0.05
    node_net.connect()
    locals_ = []
    for i in range(1, nodes + 1):
        local = canopen.LocalNode(i, canopen.import_od(EDS, i))
        node_net.add_node(local)
        local.tpdo.read(from_od=True)
        locals_.append(local)
    cpu = [0.0, 0]

    def on_sync(can_id: int, data: bytearray, timestamp: float) -> None:
        start = time.thread_time()
        cpu[1] += 1
        k = cpu[1]
        for local in locals_:
            for (pdo, name, _), value in zip(MAPPED, values(k, local.id), strict=True):
                local.tpdo[pdo][name].raw = value
            local.tpdo[1].transmit()
            local.tpdo[2].transmit()
        cpu[0] += time.thread_time() - start

    node_net.subscribe(0x80, on_sync)
    try:
        seconds = run_syncs(net, syncs, rate, lambda: cpu[1] >= syncs)
        done = cpu[1]
        return {"syncs": done, "seconds": round(seconds, 2),
                "cpu_us_per_node_sync": round(cpu[0] / done / nodes * 1e6, 2),
                "tpdos_per_sync": round(counter.tpdos / done, 2)}
    finally:
        node_net.disconnect()
        net.disconnect()


def bus_send_us(frames: int = 20000) -> float:
    """CPU per frame of python-can's virtual bus itself (a message built and sent to one
    receiver, as every TPDO above is)."""
    channel = f"bench-gw-{uuid.uuid4().hex}"
    sender, receiver = (can.Bus(interface="virtual", channel=channel) for _ in range(2))
    try:
        start = time.thread_time()
        for k in range(frames):
            sender.send(can.Message(arbitration_id=0x181, data=k.to_bytes(6, "little"),
                                    is_extended_id=False, check=False))
        return (time.thread_time() - start) / frames * 1e6
    finally:
        sender.shutdown()
        receiver.shutdown()


def bench_sdo(nodes: int, uploads: int, rates: tuple[float, ...]) -> dict[str, Any]:
    channel = f"bench-gw-{uuid.uuid4().hex}"
    _, net, _counter = master(channel)
    node_bus = can.Bus(interface="virtual", channel=channel)
    ids = list(range(1, nodes + 1))
    remotes = [net.add_node(i, canopen.import_od(EDS, i)) for i in ids]
    runtime = NodeRuntime(node_bus, {i: canopen.import_od(EDS, i) for i in ids},
                          NodeCallbacks(on_sync=lambda c: [runtime.set(i, 0x6064, 0, i)
                                                           for i in ids]))
    out: dict[str, Any] = {}
    try:
        runtime.start()
        net.nmt.send_command(NmtCommand.START)
        wait_until(lambda: all(runtime.state(i) == 5 for i in ids), 5)
        for rate in (0.0, *rates):
            if rate:
                net.sync.start(1.0 / rate)
            times = []
            try:
                for k in range(uploads * nodes):
                    remote = remotes[k % nodes]
                    start = time.perf_counter()
                    remote.sdo.upload(0x6064, 0)
                    times.append(time.perf_counter() - start)
            finally:
                if rate:
                    net.sync.stop()
            key = f"{int(rate)}hz" if rate else "idle"
            out[f"sdo_p50_ms_{key}"] = round(percentile(times, 50) * 1e3, 3)
            out[f"sdo_p99_ms_{key}"] = round(percentile(times, 99) * 1e3, 3)
            out[f"sdo_max_ms_{key}"] = round(max(times) * 1e3, 3)
    finally:
        runtime.close()
        net.disconnect()
        node_bus.shutdown()
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--nodes", type=int, default=9)
    ap.add_argument("--syncs", type=int, default=2000)
    ap.add_argument("--rate", type=float, default=250.0, help="SYNC rate of the CPU runs")
    ap.add_argument("--uploads", type=int, default=100, help="SDO uploads per node")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    runtime = bench_runtime(args.nodes, args.syncs, args.rate)
    baseline = bench_baseline(args.nodes, args.syncs, args.rate)
    send_us = bus_send_us()
    for figures_of in (runtime, baseline):  # the bus's own cost of 2 frames taken out
        figures_of["cpu_us_per_node_sync_without_bus"] = round(
            figures_of["cpu_us_per_node_sync"] - 2 * send_us, 2)
    sdo = bench_sdo(args.nodes, args.uploads, (100.0, 250.0))
    figures: dict[str, Any] = {
        "nodes": args.nodes, "syncs": args.syncs, "rate_hz": args.rate,
        "runtime": runtime, "baseline": baseline,
        "virtual_bus_send_us": round(send_us, 2),
        "speedup": round(baseline["cpu_us_per_node_sync"]
                         / runtime["cpu_us_per_node_sync"], 1),
        "speedup_without_bus": round(baseline["cpu_us_per_node_sync_without_bus"]
                                     / runtime["cpu_us_per_node_sync_without_bus"], 1),
        **sdo, "load_average": round(os.getloadavg()[0], 2),
    }
    targets = {
        "runtime <= 1/3 of the LocalNode TPDO path without the virtual bus's sending":
            runtime["cpu_us_per_node_sync_without_bus"] * 3
            <= baseline["cpu_us_per_node_sync_without_bus"],
        "every SYNC's TPDOs sent": runtime["tpdos_per_sync"] >= 2 * args.nodes - 0.01,
        "SDO p99 at 250 Hz SYNC < 10 ms": sdo["sdo_p99_ms_250hz"] < 10,
    }
    figures["targets_met"] = {k: bool(v) for k, v in targets.items()}
    code = 0 if all(targets.values()) else 1
    if args.json:
        print(json.dumps(figures, indent=2))
        return code
    print(f"{args.nodes} CANopen nodes x 2 TPDOs (type 1), {runtime['syncs']} SYNCs at "
          f"{args.rate:g} Hz on python-can's virtual bus, 4 values refreshed per node and "
          "SYNC:")
    print(f"  runtime:  {runtime['cpu_us_per_node_sync']} us CPU per node and SYNC "
          f"({runtime['thread_cpu_us_per_node_sync']} us with its whole thread, idle turns "
          f"included); {runtime['tpdos_per_sync']} TPDOs per SYNC")
    print(f"  baseline: {baseline['cpu_us_per_node_sync']} us (LocalNode's TPDO path, "
          f"values set through tpdo[n][name].raw, transmit()); {baseline['tpdos_per_sync']}"
          f" TPDOs per SYNC; the runtime is {figures['speedup']}x cheaper")
    print(f"  python-can's virtual bus itself: {figures['virtual_bus_send_us']} us a frame "
          f"(a deep copy per receiver); without it {runtime['cpu_us_per_node_sync_without_bus']}"
          f" us against {baseline['cpu_us_per_node_sync_without_bus']} us: "
          f"{figures['speedup_without_bus']}x")
    for key in ("idle", "100hz", "250hz"):
        print(f"  SDO upload round trip {key.replace('hz', ' Hz SYNC')}: p50 "
              f"{sdo[f'sdo_p50_ms_{key}']} ms, p99 {sdo[f'sdo_p99_ms_{key}']} ms, max "
              f"{sdo[f'sdo_max_ms_{key}']} ms")
    print(f"  load average {figures['load_average']}")
    for name, ok in targets.items():
        print(f"  target {name}: {'MET' if ok else 'NOT MET'}")
    return code


if __name__ == "__main__":
    sys.exit(main())
