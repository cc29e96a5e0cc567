"""The CANopen master of ``benchmarks/gateway.py``, one per CANopen bus in a process of its
own (``gateway.py --master SPEC``): python-can's own socketcand client, no ucom-tools
code on the master's side but the bit counting of ``ucom_tools.wire.canbits``; what it
does and measures is in ``benchmarks/gateway.py``'s docstring."""

from __future__ import annotations

import bisect
import itertools
import json
import logging
import math
import struct
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any

import can

from ucom_tools.wire.canbits import frame_bits, unstuffed_bits, worst_frame_bits

SDO_EVERY_S = 0.02
SDO_TIMEOUT_S = 0.05
STEP_S = 2.0
"""A state machine step's deadline (its statusword in TPDO1)."""
SINE_COUNTS, SINE_HZ = 100, 0.5
"""The joints' CSP set-points: a sine of this amplitude and frequency about where each
stood."""
ENABLE_STEPS = ((0x06, 0x21), (0x07, 0x23), (0x0F, 0x27))
"""Controlword, and the statusword (& 0x6F) that answers it: ready to switch on,
switched on, operation enabled."""


@dataclass(frozen=True)
class MasterSpec:
    """What one master drives (JSON on its command line)."""

    host: str
    port: int
    channel: str
    nodes: list[int]
    so: list[int]
    """Per node, the SO object its SDO uploads read besides 0x6064."""
    rate: float
    seconds: float
    start_s: float


class MasterError(Exception):
    """The master could not set its joints up (why, for the report)."""


class Master:
    """The CANopen master of one bus (see the module docstring): python-can's socketcand
    client, a thread receiving, a thread sending SYNCs and RPDOs, the main thread setting
    the joints up and asking SDO uploads.  Prints its figures as one JSON line once
    measured (or a line saying why not), then sends SYNCs on until its stdin ends."""

    def __init__(self, spec: MasterSpec) -> None:
        self.spec = spec
        self.ids = frozenset(spec.nodes)
        self.bus = can.Bus(interface="socketcand", host=spec.host, port=spec.port,
                           channel=spec.channel, tcp_tune=True)
        self.lock = threading.Lock()
        self.cond = threading.Condition()
        self.stop = threading.Event()
        self.alive: set[int] = set()
        self.status: dict[int, int] = {}
        self.position: dict[int, int] = {}
        self.answers: dict[int, tuple[float, bytes]] = {}
        self.targets: dict[int, int] | None = None
        """Node -> the centre of its sine, once RPDO2 goes out."""
        self.measuring = False
        self.frames: list[tuple[float, float, int, bytes]] = []
        """TPDOs while measuring: (arrival, time stamp, identifier, data)."""
        self.sent: list[tuple[int, bytes]] = []
        self.syncs: list[float] = []
        self.emcys = 0
        self.last_tpdo = 0.0

    def send(self, ident: int, data: bytes, *, pdo: bool = False) -> None:
        msg = can.Message(arbitration_id=ident, data=data, is_extended_id=False)
        with self.lock:
            self.bus.send(msg)
        if pdo and self.measuring:
            self.sent.append((ident, data))

    def receive(self) -> None:
        ids, cond = self.ids, self.cond
        while not self.stop.is_set():
            try:
                msg = self.bus.recv(0.1)
            except can.CanError:
                return
            if msg is None:
                continue
            now, ident = time.time(), msg.arbitration_id
            node, kind, data = ident & 0x7F, ident & 0x780, bytes(msg.data)
            if node not in ids:
                continue
            if kind in (0x180, 0x280):
                self.last_tpdo = now
                if self.measuring:
                    self.frames.append((now, msg.timestamp, ident, data))
                if kind == 0x280:
                    self.position[node] = int.from_bytes(data[:4], "little", signed=True)
                elif self.status.get(node) != int.from_bytes(data[:2], "little"):
                    with cond:
                        self.status[node] = int.from_bytes(data[:2], "little")
                        cond.notify_all()
            elif kind in (0x580, 0x700):
                with cond:
                    if kind == 0x580:
                        self.answers[node] = (now, data)
                    else:
                        self.alive.add(node)
                    cond.notify_all()
            elif kind == 0x080 and self.measuring:
                self.emcys += 1

    def cyclic(self) -> None:
        """SYNC every period; RPDO2 of every node half a period later."""
        period = 1.0 / self.spec.rate
        start = time.monotonic()
        due = start + period
        while not self.stop.is_set():
            time.sleep(max(0.0, due - time.monotonic()))  # the master's own pace
            sent = time.time()
            self.send(0x080, b"", pdo=True)
            if self.measuring:
                self.syncs.append(sent)
            targets = self.targets
            if targets is not None:
                time.sleep(max(0.0, due + period / 2 - time.monotonic()))
                phase = math.sin(2 * math.pi * SINE_HZ * (time.monotonic() - start))
                for node, centre in targets.items():
                    value = centre + round(SINE_COUNTS * phase)
                    self.send(0x300 + node, struct.pack("<ii", value, 0), pdo=True)
            due += period
            if time.monotonic() - due > period:  # held up: on from now
                due = time.monotonic() + period

    def wait(self, pred: Any, timeout: float) -> bool:
        with self.cond:
            return bool(self.cond.wait_for(pred, timeout))

    def sdo(self, node: int, request: bytes, timeout: float = SDO_TIMEOUT_S
            ) -> tuple[float, bytes] | None:
        """An expedited SDO request; (round trip to the answer's arrival, the answer)."""
        with self.cond:
            self.answers.pop(node, None)
        start = time.time()
        self.send(0x600 + node, request)
        if not self.wait(lambda: node in self.answers
                         and self.answers[node][1][1:4] == request[1:4], timeout):
            return None
        with self.cond:
            arrival, data = self.answers.pop(node)
        return arrival - start, data

    def write(self, node: int, index: int, value: int, size: int) -> None:
        command = {1: 0x2F, 2: 0x2B, 4: 0x23}[size]
        got = self.sdo(node, bytes((command, index & 0xFF, index >> 8, 0))
                       + value.to_bytes(size, "little", signed=value < 0).ljust(4, b"\0"),
                       1.0)
        if got is None or got[1][0] != 0x60:
            raise MasterError(f"node {node}: SDO write of 0x{index:04X} = {value}: "
                              + ("no answer" if got is None else f"answer {got[1].hex()}"))

    def enable(self, node: int) -> bool:
        """Fault reset where the node is in FAULT, then the state machine's steps."""
        if self.status.get(node, 0) & 0x08:
            self.write(node, 0x6040, 0x80, 2)
            if not self.wait(lambda: not self.status.get(node, 0) & 0x08, STEP_S):
                return False
        for controlword, answer in ENABLE_STEPS:
            self.write(node, 0x6040, controlword, 2)
            if not self.wait(lambda a=answer: self.status.get(node, 0) & 0x6F == a, STEP_S):
                return False
        return True

    def set_up(self) -> int:
        """NMT start, SYNC, CSP, the state machine: how many joints are enabled."""
        nodes = self.spec.nodes
        if not self.wait(lambda: self.alive >= self.ids, self.spec.start_s):
            raise MasterError(f"no heartbeat within {self.spec.start_s:g} s from "
                              f"{sorted(self.ids - self.alive)}")
        for node in nodes:
            self.send(0x000, bytes((0x01, node)))
        threading.Thread(target=self.cyclic, daemon=True).start()
        if not self.wait(lambda: self.ids <= self.status.keys()
                         and self.ids <= self.position.keys(), 5.0):
            raise MasterError("no TPDOs after NMT start and SYNC")
        for node in nodes:
            self.write(node, 0x6060, 8, 1)  # cyclic synchronous position
        self.targets = {node: self.position[node] for node in nodes}
        return sum(self.enable(node) for node in nodes)

    def measure(self) -> dict[str, Any]:
        """``seconds`` of SYNCs and RPDOs with an SDO upload every :data:`SDO_EVERY_S`."""
        nodes, so = self.spec.nodes, self.spec.so
        rtts: list[float] = []
        timeouts = k = 0
        self.measuring = True
        due = time.monotonic()
        end = due + self.spec.seconds
        while time.monotonic() < end and time.time() - self.last_tpdo < 0.5:
            node = nodes[k % len(nodes)]
            index = 0x6064 if (k // len(nodes)) % 2 == 0 else so[k % len(nodes)]
            got = self.sdo(node, bytes((0x40, index & 0xFF, index >> 8, 0, 0, 0, 0, 0)))
            if got is None or got[1][0] & 0xE0 != 0x40:
                timeouts += 1
            else:
                rtts.append(got[0])
            k += 1
            due += SDO_EVERY_S
            time.sleep(max(0.0, due - time.monotonic()))  # the master's own pace
        self.measuring = False
        return {**self.sync_figures(), "sdo_s": rtts, "sdo_timeouts": timeouts,
                "emcys": self.emcys, "bits_per_sync": self.bits_per_sync()}

    def sync_figures(self) -> dict[str, Any]:
        """Per SYNC (the last one's TPDOs may come after the window: left out), the time
        from its send to the last of its TPDOs, by time stamp and by arrival: the 2 a
        node-th TPDO after it, so that a SYNC whose TPDOs spill past the next SYNC counts
        its whole time (and one the nodes did not answer, the time until as many TPDOs
        came); ``complete``: the SYNCs whose every TPDO came before the next SYNC."""
        syncs, expected = self.syncs, 2 * len(self.spec.nodes)
        out: dict[str, Any] = {"syncs": max(0, len(syncs) - 1)}
        for key, column in (("sync_tpdo_s", 1), ("sync_tpdo_arrival_s", 0)):
            times: list[float] = sorted(float(f[column]) for f in self.frames)
            latencies: list[float] = []
            complete = 0
            for s0, s1 in itertools.pairwise(syncs):
                lo, hi = bisect.bisect_right(times, s0), bisect.bisect_right(times, s1)
                complete += hi - lo == expected
                if lo + expected <= len(times):
                    latencies.append(times[lo + expected - 1] - s0)
            out[key] = latencies
            if column == 1:
                out["complete"] = complete
        return out

    def bits_per_sync(self) -> dict[str, float]:
        """SYNC, RPDOs and TPDOs while measuring, per SYNC: frames and bits (counted with
        their stuff bits; nominal 47 + 8n; worst with every stuff bit a frame can need)."""
        frames = [(ident, data) for _, _, ident, data in self.frames] + self.sent
        n = max(1, len(self.syncs))
        return {"frames": round(len(frames) / n, 2),
                "counted": round(sum(frame_bits(i, d) for i, d in frames) / n, 1),
                "nominal": round(sum(unstuffed_bits(len(d)) for _, d in frames) / n, 1),
                "worst": round(sum(worst_frame_bits(len(d)) for _, d in frames) / n, 1)}

    def main(self) -> int:
        logging.getLogger("can").setLevel(logging.ERROR)  # its socketcand client's chatter
        sys.setswitchinterval(5e-4)  # the SYNC thread waits for no other thread long
        threading.Thread(target=self.receive, daemon=True).start()
        try:
            enabled = self.set_up()
            print(json.dumps({**self.measure(), "enabled": enabled}), flush=True)
            sys.stdin.read()  # SYNCs go on until the benchmark ends the gateway's run
        except MasterError as err:
            print(f"{self.spec.channel}: {err}", flush=True)
        finally:
            self.stop.set()
            self.bus.shutdown()
        return 0
