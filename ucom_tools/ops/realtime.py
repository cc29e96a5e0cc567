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

At normal priority the loop's thread asks for a short time slice (:func:`short_slice`):
Linux's fair scheduler (EEVDF, kernel 6.12 and later) lets a thread that wakes with a
shorter slice than the running task's preempt it, so the loop gets the processor at its
deadline instead of after another process's slice (1.4 ms on two cores); any thread may
ask.

The loop's process keeps its start-up's objects out of Python's collector while it runs
(:func:`frozen_heap`): a full collection walks only what the run made since.
"""

from __future__ import annotations

import contextlib
import ctypes
import gc
import os
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Final

PRIORITY = 40
"""SCHED_FIFO priority of the loop's thread: below the kernel's IRQ threads (50)."""
TIMER_SLACK_NS = 1000
"""The loop thread's timer slack (Linux's default is 50 us: a sleep may end that late)."""
_PR_SET_TIMERSLACK = 29
SLICE_NS: Final = 100_000
"""The time slice the loop's thread asks for at normal priority: the least Linux grants
(its default is 0.7 ms times 1 + log2 of the processors, at most 8 of them).
Measured over ``fleet serve armar3`` on two cores beside a process that keeps one of them
busy (``benchmarks/runtime.py``, three runs in turns): lateness p99 0.020-0.048 ms against
0.036-0.173 ms with the default slice; on an otherwise idle machine the same as without."""
_SCHED_SYSCALLS: Final = {"x86_64": (314, 315), "aarch64": (274, 275)}
"""``sched_setattr`` and ``sched_getattr`` by machine (Python has neither)."""


class _SchedAttr(ctypes.Structure):
    """``struct sched_attr`` (sched_setattr(2)), its first version's 56 bytes."""

    _fields_ = [("size", ctypes.c_uint32), ("sched_policy", ctypes.c_uint32),
                ("sched_flags", ctypes.c_uint64), ("sched_nice", ctypes.c_int32),
                ("sched_priority", ctypes.c_uint32), ("sched_runtime", ctypes.c_uint64),
                ("sched_deadline", ctypes.c_uint64), ("sched_period", ctypes.c_uint64),
                ("util_min", ctypes.c_uint32), ("util_max", ctypes.c_uint32)]


def _sched_attr() -> tuple[ctypes.CDLL, int, _SchedAttr] | None:
    """libc, sched_setattr's number and the calling thread's attributes, or None where
    they cannot be had (not Linux, another machine, a kernel without them)."""
    numbers = _SCHED_SYSCALLS.get(os.uname().machine) if sys.platform.startswith(
        "linux") else None
    if numbers is None:
        return None
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        attr = _SchedAttr()
        if libc.syscall(numbers[1], 0, ctypes.byref(attr), ctypes.sizeof(attr), 0) != 0:
            return None
    except (OSError, AttributeError):
        return None
    return libc, numbers[0], attr


def thread_slice() -> int | None:
    """The calling thread's time slice in nanoseconds under the fair policy (None where
    that cannot be read, or the thread is not under it)."""
    got = _sched_attr()
    if got is None or got[2].sched_policy != os.SCHED_OTHER:
        return None
    return int(got[2].sched_runtime)


def short_slice(slice_ns: int = SLICE_NS) -> int | None:
    """Give the calling thread a time slice of ``slice_ns`` under the fair policy (its nice
    value kept); returns the slice it had, for :func:`restore_slice`, or None where the
    thread is not under that policy or the kernel does not keep the slice (before 6.12,
    another system), and then nothing changed."""
    got = _sched_attr()
    if got is None:
        return None
    libc, setattr_nr, before = got
    if before.sched_policy != os.SCHED_OTHER:
        return None  # SCHED_FIFO (--realtime) or another policy: no slice to ask for
    if not _set_slice(libc, setattr_nr, before, slice_ns):
        return None
    if thread_slice() != slice_ns:  # accepted and ignored: an older kernel
        _set_slice(libc, setattr_nr, before, int(before.sched_runtime))
        return None
    return int(before.sched_runtime)


def restore_slice(slice_ns: int) -> None:
    """The calling thread's slice back to ``slice_ns`` (what :func:`short_slice` gave)."""
    got = _sched_attr()
    if got is not None and got[2].sched_policy == os.SCHED_OTHER:
        _set_slice(got[0], got[1], got[2], slice_ns)


@dataclass
class ShortSlice:
    """The calling thread's short time slice (:func:`short_slice`, :meth:`enter`) and back
    (:meth:`leave`, only from the thread that asked), as :class:`RealtimeScheduling`
    does for SCHED_FIFO; ``granted``: the slice in nanoseconds the thread runs (or ran)
    with, None where the kernel keeps its own."""

    granted: int | None = None
    _thread: int | None = None
    _before: int = 0

    def enter(self) -> bool:
        """Ask for :data:`SLICE_NS`; False where it is not granted (nothing changed)."""
        before = short_slice()
        if before is None:
            return False
        self._thread, self._before, self.granted = threading.get_ident(), before, SLICE_NS
        return True

    def leave(self) -> None:
        """The slice the thread had before (another thread's call does nothing)."""
        if self._thread is None or threading.get_ident() != self._thread:
            return
        restore_slice(self._before)
        self._thread = None


def _set_slice(libc: ctypes.CDLL, setattr_nr: int, current: _SchedAttr, slice_ns: int,
               ) -> bool:
    attr = _SchedAttr(size=ctypes.sizeof(_SchedAttr), sched_policy=os.SCHED_OTHER,
                      sched_nice=current.sched_nice, sched_runtime=slice_ns)
    return bool(libc.syscall(setattr_nr, 0, ctypes.byref(attr), 0) == 0)


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
    """Nothing, in interpreted Python, called by the loop once a cycle: entering it lets
    Python run a signal handler that is pending, so that a Ctrl-C that came while the
    loop computed (a busy machine) does not wait for the end of the run.  Why a compiled
    loop needs it, and why this module stays out of the compiled build: see
    :mod:`ucom_tools.compiled`."""


def like_the_loop(scheduling: RealtimeScheduling | None, time_slice: ShortSlice) -> None:
    """Schedule the calling thread as the loop's (SCHED_FIFO where the loop has it, else
    its short time slice): a conversation the loop steps (a rejoin, a write it does not
    wait for) runs while the loop waits for it, so it must not wait for others."""
    if scheduling is not None and scheduling.active:
        with contextlib.suppress(OSError, AttributeError):
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(scheduling.priority))
    elif time_slice.granted is not None:
        short_slice()


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


@contextlib.contextmanager
def frozen_heap() -> Iterator[None]:
    """What exists when the loop starts is moved out of Python's collector (``gc.freeze``)
    for the block's time: a full collection then walks only what the run made since, not
    the whole program (ARMAR-III's run time over socketcand holds some 37,000 objects: a
    full collection of them took 8-16 ms with the GIL held, the loop waiting; frozen,
    0.02 ms).  Process-wide: for the
    process that runs the loop (``ucom remote run``, the benchmarks)."""
    gc.collect()
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()
