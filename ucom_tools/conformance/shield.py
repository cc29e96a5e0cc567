"""Signals that cannot skip the restore: Ctrl-C, SIGTERM and SIGHUP end the cases, never
the restore that follows them.

While a :class:`Shield` is entered, the handlers of SIGINT, SIGTERM and SIGHUP that raise
in Python (the default :class:`KeyboardInterrupt` of SIGINT, the
:class:`~ucom_tools.signals.Terminated` of :func:`~ucom_tools.signals.stop_signals`) are
wrapped: inside :meth:`Shield.raising` a signal is handled as before (it raises, and from
then on every further signal is deferred, so that the unwinding and the restore run to
their end); anywhere else it is only noted (:attr:`Shield.pending`) and handed back by
:meth:`Shield.take` once the boards are restored.  A signal whose handler is the default
action or ignored is left alone, and outside the main thread nothing changes.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Callable, Iterator
from types import FrameType
from typing import Any

SHIELDED = tuple(s for s in (getattr(signal, "SIGINT", None), getattr(signal, "SIGTERM", None),
                             getattr(signal, "SIGHUP", None)) if s is not None)
"""The signals that end a job as Ctrl-C does (``ucom_tools.signals``)."""


class Shield:
    """Defers the stop signals outside :meth:`raising` (see the module docstring).

    ``notice`` is called (in the main thread, from the signal handler) with the number of
    each signal that is deferred."""

    def __init__(self, notice: Callable[[int], None] | None = None) -> None:
        self.notice = notice
        self.pending: list[int] = []
        """Signals that came while deferred, in order, not yet taken."""
        self._previous: dict[int, Callable[[int, FrameType | None], Any]] = {}
        self._open = False

    def __enter__(self) -> Shield:
        if threading.current_thread() is threading.main_thread():
            for sig in SHIELDED:
                handler = signal.getsignal(sig)
                if callable(handler):
                    self._previous[sig] = handler
                    signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()

    @contextlib.contextmanager
    def raising(self) -> Iterator[None]:
        """Meanwhile a stop signal raises as its own handler does (once: the signals
        after it are deferred again); one deferred before raises at once."""
        stop = self.take()
        if stop is not None:
            raise stop
        self._open = True
        try:
            yield
        finally:
            self._open = False

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self._open:
            self._open = False  # what follows (unwinding, the restore) is not cut short
            self._previous[signum](signum, frame)
            self._open = True  # that handler raised nothing: nothing ends
            return
        self.pending.append(signum)
        if self.notice is not None:
            with contextlib.suppress(Exception):  # it must not cut the restore short
                self.notice(signum)

    def take(self) -> BaseException | None:
        """The exception the first deferred signal's own handler raises (None when none
        is pending, or its handler raises nothing); the others are dropped."""
        if not self.pending:
            return None
        signum = self.pending[0]
        self.pending.clear()
        handler = self._previous.get(signum)
        if handler is None:
            return None
        try:
            handler(signum, None)
        except BaseException as stop:
            return stop
        return None
