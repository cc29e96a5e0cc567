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
  step costs a look at one queue and one clock.  On the wall clock the loop waits at
  most until shortly before its next deadline (``budget``): a worker whose budget is
  spent hands control back at its next wait although frames wait for it (it has taken
  one in this step at least), and one that computes longer than its budget between two
  waits runs on beside the loop, which hands it nothing more until it has come to its
  next wait.  (It never reads a bus; its frames go out as any other thread's; what it
  changes - the values the loop sends a board - it changes whole, one value at a time.)
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

Measured (ARMAR-III over ``fleet serve``, the PC at 1 kHz, compiled, a board's rejoin:
some 170 steps in 0.42 s): a step takes 0.2-0.3 ms of the loop's wall time (two thread
switches and the worker's part), p99 0.7-0.8 ms, and fewer than one step in twenty
outlasts the budget; the other boards' cycles were late by 0.075 ms at p99 while it
ran, 0.088 ms without (nine runs pooled).  Eleven at once (an emergency stop,
``benchmarks/faults.py``, 20 rounds): 0.21 ms at p99 against 0.085 ms without; before a
worker gave control back at its spent budget, and while others were handed control
beside one computing past its own, 2.25 ms (eleven threads taking turns at the GIL with
the loop).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import can

from ucom_tools.protocol.dispatch import Dispatcher, stepped_by
from ucom_tools.protocol.routing import Subscription


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
        self._free = False
        """The worker runs beside the loop: its last step outlasted the loop's budget."""
        self._thread: threading.Thread | None = None
        self._ends: float | None = None
        """When this step's budget is spent (``time.monotonic()``; None: no budget)."""
        self._took = False
        """The worker took a frame in this step (the next one waits for the next step once
        the budget is spent)."""

    # ------------------------------------------------------------------ the loop's side
    def step(self, budget: float | None = None) -> bool:
        """Hand the worker control if what it waits for is there; until it waits again or
        ends, or for ``budget`` seconds at most (then it runs on beside the caller, see
        the module docstring).  False when it was not run."""
        if self.busy():
            return False  # still computing
        if self.done:
            return False
        ready = self._ready
        if ready is not None and not ready():
            return False
        self._hand_over(budget)
        return True

    def busy(self) -> bool:
        """The worker computes beside the caller: its last step outlasted the budget and
        it has not come to its next wait yet."""
        if self._free and self._back.acquire(blocking=False):
            self._free = False
        return self._free

    def cancel(self) -> None:
        """End the conversation: the worker gets :class:`Cancelled` at its wait (its
        ``finally`` blocks run, on the caller's thread's time)."""
        self.cancelled = True
        if self._thread is None:
            self.done = True
            return
        if self._free:  # let it come to its wait first
            self._free = False
            self._acquire_back(None)
        if not self.done:
            self._hand_over(None)

    def _hand_over(self, budget: float | None) -> None:
        self.steps += 1
        self._ready = None
        self._ends = None if budget is None else time.monotonic() + budget
        self._took = False
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
            self._thread.start()
        self._go.release()
        if not self._acquire_back(budget):
            self._free = True

    def _acquire_back(self, budget: float | None) -> bool:
        """Wait for the worker to come to its wait (or end), ``budget`` seconds at most
        (None: however long); a Ctrl-C meanwhile waits for it too: never two running
        where the caller's exception would run the stop beside the worker."""
        pending: BaseException | None = None
        got = False
        while True:
            try:
                got = self._back.acquire() if budget is None else \
                    self._back.acquire(timeout=max(0.0, budget))
                break
            except KeyboardInterrupt as err:
                pending = err
                budget = None
        if pending is not None:
            raise pending
        return got

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
            if self._took and self._ends is not None and time.monotonic() >= self._ends:
                self._park(ready)  # the step's time is spent: the next frames at the next
                continue  # step (handled in one go, a description's kept the loop waiting)
            got = dispatcher.take(sub)
            if got is not None:
                self._took = True
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


class SteppedJob:
    """A :class:`Stepped` conversation as a loop holds it among others: :attr:`done`,
    :meth:`busy`, :meth:`step`, :meth:`cancel`; at its end :attr:`ok`, else :attr:`how`
    says why not (:attr:`FAILED` in front of the error that ended the worker, or of "the
    run ended")."""

    FAILED = ""

    def __init__(self, work: Callable[[], Any], name: str) -> None:
        self.ok = False
        self.how = ""
        self._stepped = Stepped(work, name)

    @property
    def done(self) -> bool:
        return self._stepped.done

    def busy(self) -> bool:
        """Its worker computes beside the loop (see :meth:`Stepped.busy`)."""
        return self._stepped.busy()

    def step(self, budget: float | None = None) -> None:
        self._stepped.step(budget)
        if self._stepped.done and not self.ok and not self.how:
            err = self._stepped.error
            self.how = self.FAILED + (str(err) if err is not None else "the run ended")

    def cancel(self) -> None:
        self._stepped.cancel()
