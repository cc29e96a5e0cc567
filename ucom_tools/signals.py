"""SIGTERM and SIGHUP as Ctrl-C: the same safe stop for every way a user ends a job.

A job that is ended by ``kill``, a service manager or a closed terminal must stop its
boards (or restore them) exactly as after Ctrl-C.  :func:`stop_signals` turns both signals
into :class:`Terminated`, a :class:`KeyboardInterrupt`, raised in the main thread, so that
every ``except KeyboardInterrupt`` and ``finally`` of the job runs; the CLI then exits
with 128 + the signal's number (143, 129), as a shell reports a job killed by it
(``man/ucom.1``, EXIT STATUS).
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator
from typing import Any, Final

from ucom_tools.native import mypyc_attr

STOP_SIGNALS: Final = (signal.SIGTERM, signal.SIGHUP)
"""The signals that end a job as Ctrl-C does."""

_MAIN: Final[int] = threading.main_thread().ident or 0
_get_ident: Final = threading.get_ident
"""Bound once: :data:`deferred` asks it twice for every step of the in-process fleet."""


@mypyc_attr(native_class=False)  # a built-in exception's subclass (see compiled.py)
class Terminated(KeyboardInterrupt):
    """The job was ended by ``signum`` (SIGTERM or SIGHUP); handled as Ctrl-C."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


def stop_signal(exc: BaseException) -> Terminated | None:
    """The :class:`Terminated` that ended a job: ``exc`` itself, or the cause it was raised
    from (a job that undid its work raises what it left from the interrupt); None for
    Ctrl-C (or a cancel without a signal)."""
    seen: BaseException | None = exc
    for _ in range(8):  # a chain of causes is short; never a loop
        if seen is None:
            return None
        if isinstance(seen, Terminated):
            return seen
        seen = seen.__cause__
    return None


def interrupt_exit_code(exc: BaseException) -> int:
    """130 for Ctrl-C, 128 + the signal's number for :class:`Terminated` (also as the
    cause an interrupted job's exception was raised from)."""
    stop = stop_signal(exc)
    return stop.exit_code if stop is not None else 130


def stopped_how(exc: BaseException) -> str:
    """"terminated (SIGTERM)", "terminated (SIGHUP)", or "cancelled" for Ctrl-C."""
    stop = stop_signal(exc)
    return f"terminated ({stop.name})" if stop is not None else "cancelled"


class _Deferred:
    """See :data:`deferred`.  Its state is its own attributes, not module globals (see
    compiled.py)."""

    def __init__(self) -> None:
        self.depth = 0
        """Blocks of the main thread open now."""
        self.pending = 0
        """The stop signal that came meanwhile (0: none)."""

    def __enter__(self) -> None:
        if _get_ident() == _MAIN:
            self.depth += 1

    def __exit__(self, kind: Any, exc: Any, tb: Any) -> None:
        if _get_ident() != _MAIN:
            return
        self.depth -= 1
        if self.depth == 0 and self.pending:
            signum, self.pending = self.pending, 0
            if kind is None or not issubclass(kind, KeyboardInterrupt):
                # also when the block ends by an error: a caller that takes that error
                # (a full transmit queue, offered again) must not swallow the stop with it
                raise _stop(signum)


deferred = _Deferred()
"""``with deferred:``: a stop signal (Ctrl-C, SIGTERM, SIGHUP, under :func:`stop_signals`)
that comes meanwhile is raised when the block ends, not inside it: for work that must not
be cut in the middle, such as one step of the in-process fleet's simulation (an event
taken off the clock and not run would leave a board half-way through a frame)."""


def _stop(signum: int) -> KeyboardInterrupt:
    return KeyboardInterrupt() if signum == signal.SIGINT else Terminated(signum)


@contextlib.contextmanager
def stop_signals() -> Iterator[None]:
    """Meanwhile SIGTERM and SIGHUP raise :class:`Terminated` in the main thread, and
    Ctrl-C its KeyboardInterrupt, each deferred to the end of a :data:`deferred` block
    (outside the main thread, or where a signal is ignored by the parent, as ``nohup``
    does, nothing changes).
    The second signal of a kind is raised too: a job stuck in its clean-up can still be
    ended, with the same exit code."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def terminate(signum: int, frame: Any) -> None:
        if deferred.depth:
            deferred.pending = deferred.pending or signum  # raised when the block ends
            return
        raise _stop(signum)

    previous: dict[signal.Signals, Any] = {}
    for sig in (signal.SIGINT, *STOP_SIGNALS):
        current = signal.getsignal(sig)
        if current is signal.SIG_IGN:  # nohup: the user asked us to survive it
            continue
        if sig == signal.SIGINT and current is not signal.default_int_handler:
            continue  # someone else's Ctrl-C handling: left alone
        previous[sig] = signal.signal(sig, terminate)
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
