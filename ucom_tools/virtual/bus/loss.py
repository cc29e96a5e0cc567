"""Lost frames, reproducibly: the two ways ucom-tools loses frames on purpose.

- :class:`LossyBus` wraps any ``can.BusABC`` (python-can level, for tests and benchmarks)
  and drops frames in both directions, at random with a seeded generator (``loss``) or
  where a predicate says so (``drop``), so that the real host code runs over a bus that
  loses frames.  A frame dropped on the way out is reported as sent (the host cannot
  tell, as on a real bus where a frame is lost to a receiver); one dropped on the way in
  is never seen.
- :class:`FrameLoss` is ``ucom fleet serve --loss``: frames lost at random between one
  socketcand client and its bus, each client with its own seeded generator
  (:class:`~ucom_tools.virtual.serve.connection.Connection` asks it for every frame).

(Neither is a lost frame a mutant board's *defect*, a documented deviation from the
protocol, :mod:`ucom_tools.virtual.board.mutants`, nor an injected *fault*,
:mod:`ucom_tools.virtual.injected`.)
"""

from __future__ import annotations

import random
import time
from collections.abc import Callable
from typing import Any

import can

Direction = str  # "tx" (host -> bus) or "rx" (bus -> host)
DropRule = Callable[[Direction, can.Message], bool]


class LossyBus(can.BusABC):
    """``inner`` with frames lost: a share ``loss`` at random (seeded), and every frame for
    which ``drop(direction, message)`` is true."""

    def __init__(self, inner: can.BusABC, *, loss: float = 0.0, seed: int = 0,
                 drop: DropRule | None = None, **kwargs: Any) -> None:
        if not 0.0 <= loss < 1.0:
            raise ValueError(f"loss must be in [0, 1), got {loss}")
        self.inner = inner
        self.loss = loss
        self.rng = random.Random(seed)
        self.drop = drop
        self.dropped = {"tx": 0, "rx": 0}
        self.channel_info = f"{getattr(inner, 'channel_info', 'bus')} (losing {loss:.1%})"
        clock = getattr(inner, "clock", None)
        self._clock: Callable[[], float] = clock if callable(clock) else time.monotonic
        super().__init__(channel=str(getattr(inner, "channel", "") or ""), **kwargs)

    def clock(self) -> float:
        """The inner bus's time base (virtual time on the in-process fleet)."""
        return self._clock()

    def stamp(self) -> float:
        """Timestamps of sent frames on the inner bus's base of received ones."""
        stamp = getattr(self.inner, "stamp", None)
        return stamp() if callable(stamp) else time.time()

    def _lost(self, direction: Direction, msg: can.Message) -> bool:
        if self.drop is not None and self.drop(direction, msg):
            lost = True
        else:
            lost = self.loss > 0.0 and self.rng.random() < self.loss
        if lost:
            self.dropped[direction] += 1
        return lost

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if not self._lost("tx", msg):
            self.inner.send(msg, timeout)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """The next frame not lost; ``timeout`` counts on the inner bus's clock (python-can's
        own loop would count wall time, which virtual time does not spend)."""
        msg, _ = self._recv_internal(timeout)
        return msg

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        deadline = None if timeout is None else self._clock() + timeout
        while True:
            remaining = None if deadline is None else max(0.0, deadline - self._clock())
            msg = self.inner.recv(remaining)
            if msg is None:
                return None, False
            if not self._lost("rx", msg):
                return msg, False
            if remaining == 0.0:
                return None, False

    def shutdown(self) -> None:
        if not self._is_shutdown:
            self.inner.shutdown()
        super().shutdown()


class FrameLoss:
    """``fleet serve --loss``: frames lost between one client and its bus, a share
    ``share`` each way, from a generator seeded per client: the serve's seed, the bus and
    the client's number on this process (the same run loses the same frames)."""

    def __init__(self, share: float, seed: str) -> None:
        self.share = share
        self._rng = random.Random(seed)
        self.counts = {"to": 0, "from": 0}
        """Frames lost on their way to the client and from it."""

    def lost(self, direction: str) -> bool:
        if self._rng.random() < self.share:
            self.counts[direction] += 1
            return True
        return False
