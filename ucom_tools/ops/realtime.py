"""Real-time scheduling for the PC's cyclic loop (``ucom remote run --realtime``).

At 1 kHz a loop that shares the processor with other busy processes is preempted for a
whole time slice now and then (milliseconds under Linux's default policy) and misses
cycles.  The PC side of MCA2 ran under a real-time kernel for this reason.  Here the loop's
thread can ask for ``SCHED_FIFO`` (Linux; needs CAP_SYS_NICE or an ``rtprio`` limit, e.g.
``@realtime - rtprio 99`` in ``/etc/security/limits.conf``): it then runs whenever it is
ready, before every normal process.  The loop sleeps between its cycles, so it takes
what it needs and no more.  The priority is below the kernel's interrupt threads (50 on
PREEMPT_RT), so the network and CAN drivers the loop depends on still run first.

A refusal is not an error: the loop runs at normal priority and the reason is reported.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import sys
import threading
from dataclasses import dataclass

PRIORITY = 40
"""SCHED_FIFO priority of the loop's thread: below the kernel's IRQ threads (50)."""
TIMER_SLACK_NS = 1000
"""The loop thread's timer slack (Linux's default is 50 us: a sleep may end that late)."""
_PR_SET_TIMERSLACK = 29


def precise_sleep() -> bool:
    """Let the calling thread's sleeps end within about :data:`TIMER_SLACK_NS` of their
    time instead of Linux's default 50 us (``prctl(PR_SET_TIMERSLACK)``, allowed to any
    thread; SCHED_FIFO threads have no slack anyway).  False where it is not available."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return bool(libc.prctl(_PR_SET_TIMERSLACK, TIMER_SLACK_NS, 0, 0, 0) == 0)
    except (OSError, AttributeError):
        return False


def let_signals_in() -> None:
    """Nothing, in interpreted Python, called by the compiled loop once a cycle: entering
    it lets Python run a signal handler that is pending.  A loop compiled with mypyc never
    passes through the interpreter otherwise, and its sleep runs the handler only when the
    signal comes during it: a Ctrl-C that came while the loop computed (a busy machine)
    waited for the end of the run.  (This module stays interpreted: it is not in
    :data:`ucom_tools.compiled.MODULES`.)"""


@dataclass
class RealtimeScheduling:
    """The calling thread's switch to ``SCHED_FIFO`` and back (:meth:`enter`,
    :meth:`leave`); ``active`` tells whether it is in effect, ``refused`` why not."""

    priority: int = PRIORITY
    active: bool = False
    refused: str = ""
    _thread: int | None = None
    _before: tuple[int, int] | None = None

    def enter(self) -> bool:
        """Switch the calling thread to SCHED_FIFO; False (and ``refused`` says why) when
        the system does not allow it."""
        if self.active:
            return True
        setter = getattr(os, "sched_setscheduler", None)
        if setter is None or not hasattr(os, "SCHED_FIFO"):
            self.refused = "real-time scheduling is not available on this system"
            return False
        try:
            before = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)
            setter(0, os.SCHED_FIFO, os.sched_param(self.priority))
        except PermissionError:
            self.refused = ("SCHED_FIFO not permitted (needs CAP_SYS_NICE or an rtprio limit "
                            f"of at least {self.priority}, see limits.conf(5))")
            return False
        except OSError as err:
            self.refused = f"SCHED_FIFO refused: {err.strerror or err}"
            return False
        self._before, self._thread, self.active, self.refused = \
            before, threading.get_ident(), True, ""
        return True

    @property
    def used(self) -> bool:
        """Whether the loop ran under SCHED_FIFO (now or before :meth:`leave`)."""
        return self._thread is not None

    def describe(self) -> str:
        """'SCHED_FIFO 40', or 'normal (why)'."""
        if self.used:
            return f"SCHED_FIFO {self.priority}"
        return f"normal ({self.refused or 'the loop did not run'})"

    def leave(self) -> None:
        """Back to the policy the thread had (only from the thread that entered; another
        thread's call does nothing: scheduling policies are per thread)."""
        if not self.active or threading.get_ident() != self._thread:
            return
        assert self._before is not None
        policy, priority = self._before
        # lowering one's own priority is always allowed; nothing to do if it fails anyway
        with contextlib.suppress(OSError):
            os.sched_setscheduler(0, policy, os.sched_param(priority))
        self.active = False
