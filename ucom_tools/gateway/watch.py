"""The master watch of a bus of gateway nodes: is the CANopen master still there?

Two ways, as the nodes' dictionaries say:

- heartbeat consumer (0x1016 of any node: each entry ``node ID << 16 | time in ms``):
  a producer counts from its first heartbeat (or boot-up) on; one silent for longer than
  its time (the shortest any node gives) is lost;
- with no consumer configured, a SYNC timeout: 3 x the communication cycle period 0x1006
  (microseconds; the shortest any node gives) where set, else 3 x the SYNC period
  measured (the mean of the last 8 intervals), at least 50 ms and at most 100 ms;
  nothing before the first SYNC, 100 ms between the first SYNC and the second.  The
  floor: a master's SYNC that reaches the gateway through a network socket (socketcand)
  on a busy host arrives in bursts, late by tens of milliseconds now and then (measured
  with canopen's SYNC producer beside ARMAR-III's served fleet on two cores: gaps of 31
  ms at a 10 ms SYNC), which a timeout of 3 periods took for a master gone; a master
  that wants a tighter watch sets 0x1006 or a heartbeat consumer.

A bus that fails (reading it raises) counts as the master gone until a frame comes in
again.  ``lost(reason)`` is called once when the master goes, ``back(reason)`` once when it
returns (a heartbeat of every lost producer, or a SYNC); :meth:`MasterWatch.check` runs on
every turn of the runtime's loop, so the call comes within the timeout plus one cycle.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable

SYNC_TIMEOUT_CAP = 0.100
SYNC_TIMEOUT_FLOOR = 0.050
SYNC_PERIODS = 3
MEASURED = 8


class MasterWatch:
    """Times the master's heartbeats or SYNCs (all times ``time.monotonic``)."""

    def __init__(self, lost: Callable[[str], None], back: Callable[[str], None]) -> None:
        self._lost_cb = lost
        self._back_cb = back
        self.consumers: dict[int, float] = {}  # producer node ID -> timeout (s)
        self.cycle_period = 0.0  # 0x1006 (s); 0: not set
        self._seen: dict[int, float] = {}  # producer -> its last heartbeat
        self._missing: set[int] = set()  # producers lost
        self._last_sync: float | None = None
        self._intervals: deque[float] = deque(maxlen=MEASURED)
        self._sync_lost = False
        self._bus_down = False
        self.lost = False

    def configure(self, consumers: dict[int, float], cycle_period: float) -> None:
        """New configuration (0x1016/0x1006 written, a reset): timing starts afresh; a
        master already lost stays lost until it is back."""
        self.consumers = dict(consumers)
        self.cycle_period = cycle_period
        self._seen = {p: t for p, t in self._seen.items() if p in self.consumers}
        self._missing &= set(self.consumers)
        if not self.consumers and self._missing:
            self._missing.clear()
        self._update()

    @property
    def producers(self) -> tuple[int, ...]:
        """The node IDs whose heartbeats are consumed."""
        return tuple(self.consumers)

    def heartbeat(self, producer: int, now: float) -> None:
        """A heartbeat (or boot-up) of ``producer`` arrived."""
        if producer not in self.consumers:
            return
        self._seen[producer] = now
        if producer in self._missing:
            self._missing.discard(producer)
            self._update(f"heartbeat of node {producer} again")

    def sync(self, now: float) -> None:
        """A SYNC arrived."""
        last = self._last_sync
        if self._sync_lost:
            self._sync_lost = False
            self._intervals.clear()
            self._last_sync = now
            self._update("SYNC again")
            return
        if last is not None:
            self._intervals.append(now - last)
        self._last_sync = now

    def sync_timeout(self) -> float:
        """The SYNC timeout in force (seconds)."""
        if self.cycle_period > 0:
            return SYNC_PERIODS * self.cycle_period
        if not self._intervals:
            return SYNC_TIMEOUT_CAP
        period = sum(self._intervals) / len(self._intervals)
        return min(max(SYNC_PERIODS * period, SYNC_TIMEOUT_FLOOR), SYNC_TIMEOUT_CAP)

    def check(self, now: float) -> float:
        """Note a master gone by ``now``; the time of the next deadline (inf: none)."""
        if self.consumers:
            deadline = float("inf")
            for producer, timeout in self.consumers.items():
                seen = self._seen.get(producer)
                if seen is None or producer in self._missing:
                    continue
                if now - seen > timeout:
                    self._missing.add(producer)
                    self._update(f"heartbeat of node {producer} missing for "
                                 f"{(now - seen) * 1e3:.0f} ms (0x1016: "
                                 f"{timeout * 1e3:.0f} ms)")
                else:
                    deadline = min(deadline, seen + timeout)
            return deadline
        last = self._last_sync
        if last is None or self._sync_lost:
            return float("inf")
        timeout = self.sync_timeout()
        if now - last > timeout:
            self._sync_lost = True
            self._update(f"no SYNC for {(now - last) * 1e3:.0f} ms (timeout "
                         f"{timeout * 1e3:.1f} ms)")
            return float("inf")
        return last + timeout

    def bus_failed(self, reason: str) -> None:
        """The bus itself failed (reading it raised): the master is out of reach."""
        if not self._bus_down:
            self._bus_down = True
            self._update(reason)

    def bus_ok(self) -> None:
        """A frame came in again after a failure of the bus."""
        if self._bus_down:
            self._bus_down = False
            self._update("CAN bus back")

    def _update(self, reason: str = "") -> None:
        lost = self._bus_down or bool(self._missing) or (
            not self.consumers and self._sync_lost)
        if lost == self.lost:
            return
        self.lost = lost
        if lost:
            self._lost_cb(reason)
        else:
            self._back_cb(reason or "master watch reconfigured")
