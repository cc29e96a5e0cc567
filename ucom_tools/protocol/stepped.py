"""A request/answer conversation beside a loop that must never wait for it.

The clients of this package (:class:`~ucom_tools.protocol.bootloader.BootloaderClient`,
:class:`~ucom_tools.protocol.mca.McaClient`) send a request and block in
:meth:`Dispatcher.wait <ucom_tools.protocol.dispatch.Dispatcher.wait>` for its answer.
The run time's loop cannot block, and it is the one reader of its buses.  A
:class:`Stepped` conversation runs such client code unchanged on a worker thread whose
waits are *stepped by the loop*: a coroutine made of two threads, never both running.

- The loop calls :meth:`Stepped.step` once per cycle, after its cycle's sends and the
  drain of its buses.  If the worker waits for something that is now there (a frame in
  its subscription's queue, its deadline passed, its bus failed) the loop hands it
  control and blocks until the worker blocks on its next wait, or ends; otherwise the
  step costs a look at one queue and one clock.
- The worker's waits (:meth:`Stepped.wait`, installed by
  :func:`~ucom_tools.protocol.dispatch.stepped_by`) never read the bus: they take what
  the loop's drain delivered into the subscription's queue, or hand control back.
- Deadlines count on the bus clock as before: in virtual time the loop's pump drives it,
  so a conversation is as deterministic as the loop.  A request costs the loop one cycle
  per answer it waits for; the worker's own computation happens between the loop's
  cycles, where the loop would sleep.

The other way, a generator for each conversation, would have meant a second copy of
every client request (the acknowledged writes, descriptions, read-backs, the bootloader's
Start with its retries); this one reuses them as they are.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import can

from ucom_tools.protocol.dispatch import Dispatcher, Subscription, stepped_by


class Cancelled(BaseException):
    """Raised in the worker at its next wait when the conversation is cancelled (not an
    Exception: no ``except Exception`` of the conversation takes it)."""


class Stepped:
    """``work()`` run on a worker thread whose waits the loop steps (see the module
    docstring).  :attr:`done` once it ended: :attr:`result`, or :attr:`error` (an
    exception it raised; None when it was cancelled)."""

    def __init__(self, work: Callable[[], Any], name: str) -> None:
        self._work = work
        self.name = name
        self.done = False
        self.result: Any = None
        self.error: BaseException | None = None
        self.cancelled = False
        self.steps = 0
        """How often the loop handed the worker control."""
        self._go = threading.Lock()
        """Held while the worker may not run; the loop releases it to hand over."""
        self._back = threading.Lock()
        """Held while the loop may not run; the worker releases it when it waits or ends."""
        self._go.acquire()
        self._back.acquire()
        self._ready: Callable[[], bool] | None = None
        """What the worker waits for (None: it runs at the next step)."""
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ the loop's side
    def step(self) -> bool:
        """Hand the worker control if what it waits for is there; until it waits again or
        ends.  False when it was not run."""
        if self.done:
            return False
        ready = self._ready
        if ready is not None and not ready():
            return False
        self._hand_over()
        return True

    def cancel(self) -> None:
        """End the conversation: the worker gets :class:`Cancelled` at its wait (its
        ``finally`` blocks run, on the caller's thread's time)."""
        self.cancelled = True
        if self._thread is None:
            self.done = True
            return
        if not self.done:
            self._hand_over()

    def _hand_over(self) -> None:
        self.steps += 1
        self._ready = None
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
            self._thread.start()
        self._go.release()
        pending: BaseException | None = None
        while True:  # a Ctrl-C meanwhile waits for the worker to stop: never two running
            try:
                self._back.acquire()
                break
            except KeyboardInterrupt as err:
                pending = err
        if pending is not None:
            raise pending

    # ------------------------------------------------------------------ the worker's side
    def _run(self) -> None:
        self._go.acquire()
        stepped_by(self)
        try:
            if self.cancelled:
                raise Cancelled
            self.result = self._work()
        except Cancelled:
            pass
        except BaseException as err:  # handed to the loop's side, which decides
            self.error = err
        finally:
            stepped_by(None)
            self.done = True
            self._back.release()

    def _park(self, ready: Callable[[], bool]) -> None:
        """Hand control back to the loop until ``ready()`` (the loop looks every cycle)."""
        self._ready = ready
        self._back.release()
        self._go.acquire()
        if self.cancelled:
            raise Cancelled

    def wait(self, dispatcher: Dispatcher, sub: Subscription, deadline: float,
             ) -> can.Message | None:
        """:meth:`Dispatcher.wait` in the worker: the next frame the loop delivered for
        ``sub``, or None at ``deadline``; the bus's failure raised."""
        clock = dispatcher.clock
        queue = sub.queue

        def ready() -> bool:
            return bool(queue) or dispatcher.failure is not None or clock() >= deadline

        while True:
            got = dispatcher.take(sub)
            if got is not None:
                return got
            if dispatcher.failure is not None:
                raise dispatcher.failure
            if clock() >= deadline:
                return None
            self._park(ready)

    def sleep(self, clock: Callable[[], float], until: float) -> None:
        """Wait in the worker until ``until`` on ``clock`` (a pace between questions)."""
        while clock() < until:
            self._park(lambda: clock() >= until)

