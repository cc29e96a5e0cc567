"""Real-time pacing of a simulated bus: virtual microseconds follow the wall clock.

Used when the fleet is served to other processes (``ucom fleet serve``) or when a user
asks for pacing; in-process tools otherwise drive the bus in virtual time.

The clock thread runs every node's ``on_frame`` and every scheduled callback.  One that
raises is logged with its traceback (logger ``ucom.bus``) and the bus goes on.  What
failed is not retried: a callback is gone, a frame misses the nodes after the failing
one.
"""

from __future__ import annotations

import logging
import threading
import time

from ucom_tools.virtual.simbus import SimBus

log = logging.getLogger("ucom.bus")


class RealtimeDriver:
    """A thread that advances one bus to the wall clock and sleeps until its next event."""

    def __init__(self, sim: SimBus, t0: float) -> None:
        self.sim = sim
        self.t0 = t0
        self._stop = False
        self._thread = threading.Thread(target=self._run, name=f"ucom-bus-{sim.name}",
                                        daemon=True)

    def now_us(self) -> float:
        return (time.monotonic() - self.t0) * 1e6

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        with self.sim.changed:
            self._stop = True
            self.sim.changed.notify_all()
        self._thread.join(timeout=2)

    def _run(self) -> None:
        sim = self.sim
        with sim.changed:
            while not self._stop:
                now = self.now_us()
                self._advance(now)
                nxt = sim.next_event_time()
                wait = 0.5 if nxt is None else min(0.5, max(0.0, (nxt - now) / 1e6))
                if wait > 0:
                    sim.changed.wait(timeout=wait)

    def _advance(self, now: float) -> None:
        """Run the bus up to ``now`` (hold ``sim.lock``); a node or callback that raises
        is logged and skipped, never the end of the bus."""
        sim = self.sim
        sent = sim.stats.frames
        try:
            sim.run_until(now)
        except Exception:
            log.exception("bus %s: a node or scheduled callback failed at %.1f us; "
                          "the bus goes on", sim.name, sim.now)
        if sim.stats.frames != sent:
            sim.changed.notify_all()  # senders waiting for room in their TX queue
