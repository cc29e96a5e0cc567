"""What waits to be written to one client of ``ucom fleet serve``: its bounded queue of
replies and frames (:class:`Outbox`), and a frame written as socketcand's
``< frame ... >`` element (:func:`encode_line`).

The bus thread fills the queue without ever waiting; a writer thread per client, or the
paced driver after its step (:meth:`Outbox.flush`), empties it.  Part of the socketcand
server, :mod:`ucom_tools.virtual.serve.socketcand`.
"""

from __future__ import annotations

import binascii
import threading
from collections import deque
from collections.abc import Callable
from typing import Final

from ucom_tools.wire.socketcand import CAN_EFF_FLAG, CAN_EFF_MASK, FRAME_EXT_HEAD, FRAME_STD_HEAD

MAX_QUEUED_FRAMES = 10_000
"""Frames and replies that may wait for one client; one more and it is dropped."""
_WRITE_BATCH = 512

Frame = tuple[int, bytes, float]
"""A frame for a client: identifier (with :data:`~ucom_tools.wire.socketcand.CAN_EFF_FLAG`
if extended), data, end time on the bus (virtual microseconds)."""
Line = bytes | Frame
"""What a client's writer sends: an encoded reply or a frame."""


class Outbox:
    """Lines waiting for one client.  Bounded, and :meth:`put` never blocks, so the bus
    thread hands each frame to every client without waiting for any.

    Replies (:meth:`put`) go to the client's writer thread, woken only when a line arrives
    in an empty queue (it waits only then).  Frames of a paced fleet (:meth:`put_quiet`)
    wake nobody: after the driver's step, :meth:`flush` writes every line waiting in one
    non-blocking send from the driver's thread; what the socket does not take then goes
    to the writer thread, which waits until it can write it."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self._lines: deque[Line] = deque()
        self._cond = threading.Condition(threading.Lock())
        self._closed = False
        self._writing = False
        self._flushing = False
        self._watchers = 0
        """Threads in :meth:`wait_written`."""
        self.deferred = False
        """A :meth:`flush` after the running step is asked for (the bus thread's flag)."""

    def put(self, line: Line) -> bool:
        """Queue ``line``; false if the queue is full (a closed outbox drops lines)."""
        with self._cond:
            lines = self._lines
            if self._closed:
                return True
            if len(lines) >= self.limit:
                return False
            lines.append(line)
            if len(lines) == 1:  # the writer may be waiting (it waits only when empty)
                self._cond.notify_all()
            return True

    def put_quiet(self, line: Line) -> bool:
        """Queue ``line`` without waking the writer (:meth:`flush` or :meth:`wake`
        follows); false if the queue is full.  One deque operation: no lock."""
        lines = self._lines
        if len(lines) >= self.limit:
            return self._closed
        lines.append(line)
        return True

    def wake(self) -> None:
        """Wake the writer for the lines :meth:`put_quiet` queued."""
        with self._cond:
            self.deferred = False
            if self._lines:
                self._cond.notify_all()

    def flush(self, send: Callable[[bytes], int], epoch: float) -> None:
        """Write every line waiting with one call of ``send`` (non-blocking: it returns
        how many bytes the socket took), unless the writer is busy (then it takes them);
        the rest goes to the writer.  ``OSError`` from ``send`` passes through."""
        with self._cond:
            self.deferred = False
            lines = self._lines
            if self._closed or self._writing or self._flushing or not lines:
                return
            batch = list(lines)
            lines.clear()
            self._flushing = True
        data = encode_lines(batch, epoch)
        sent = 0
        try:
            sent = send(data)
        finally:
            with self._cond:
                self._flushing = False
                if sent < len(data) and not self._closed:
                    self._lines.appendleft(data[sent:])
                if self._lines or self._watchers:
                    self._cond.notify_all()

    def take(self) -> list[Line] | None:
        """The writer's next batch (waits for one); None once the outbox is closed."""
        with self._cond:
            self._writing = False
            if self._watchers:
                self._cond.notify_all()
            while (not self._lines or self._flushing) and not self._closed:
                self._cond.wait()
            if self._closed:
                return None
            n = min(len(self._lines), _WRITE_BATCH)
            self._writing = True
            return [self._lines.popleft() for _ in range(n)]

    def wait_written(self, timeout: float) -> bool:
        """Wait until everything queued so far is written or the outbox is closed."""
        with self._cond:
            self._watchers += 1
            try:
                return self._cond.wait_for(
                    lambda: self._closed or not (self._lines or self._writing
                                                 or self._flushing), timeout)
            finally:
                self._watchers -= 1

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._lines.clear()
            self._cond.notify_all()


def encode_line(line: Line, epoch: float) -> bytes:
    """A reply as is; a frame as ``< frame ID SEC.USEC HEXDATA >``, ID of 3 hex digits
    (standard) or 8 (extended), as socketcand writes them
    (:func:`ucom_tools.wire.socketcand.frame_element`, the same bytes)."""
    return encode_lines([line], epoch)


def encode_lines(lines: list[Line], epoch: float) -> bytes:
    """:func:`encode_line` of each line, joined: what one write to the client carries.

    This runs for every frame to every client, so a frame is put together from pieces
    instead of ``%`` formatting a float: the identifier's ``< frame ID `` once per
    identifier (:data:`_PREFIXES`), the time from its integer seconds and microseconds
    (:func:`_append_time`), the data as hex digits."""
    out: list[bytes] = []
    prefixes = _PREFIXES
    digits = _DIGITS
    second = -1
    second_text = b""
    for line in lines:
        if isinstance(line, bytes):
            out.append(line)
            continue
        arbitration_id, data, t_end = line
        prefix = prefixes.get(arbitration_id)
        out.append(_prefix(arbitration_id) if prefix is None else prefix)
        seconds = epoch + t_end / 1e6
        if EXACT_FROM <= seconds < EXACT_UNTIL:
            whole = int(seconds)
            micro = round((seconds - whole) * 1e6)
            if micro >= 1_000_000:  # rounded up to the next second
                whole += 1
                micro -= 1_000_000
            if whole != second:  # the frames of one write are mostly in one second
                second = whole
                second_text = b"%d." % whole
            out.append(second_text)
            out.append(digits[micro // 1000])
            out.append(digits[micro % 1000])
            out.append(b" ")
        else:
            out.append(b"%.6f " % seconds)
        out.append(_hexlify(data).upper())
        out.append(b" >")
    return b"".join(out)


_PREFIXES: Final[dict[int, bytes]] = {}
"""``< frame ID `` of each standard identifier met so far (at most 2048)."""
_DIGITS: Final = [b"%03d" % n for n in range(1000)]
"""Three decimal digits of each number below 1000."""
_hexlify: Final = binascii.hexlify
EXACT_FROM: Final = 2.0 ** 30
"""From here on (January 2004, as seconds since 1970) a time's fraction times 10**6 is
exact in a float: at most 22 bits of it are fraction, and 10**6 = 15625 * 2**6.  So
``round`` of it is the correctly rounded (half to even) microsecond that ``%.6f`` prints
(of larger times fewer bits are fraction; below it, ``%.6f`` itself is used)."""
EXACT_UNTIL: Final = 2.0 ** 52


def _prefix(arbitration_id: int) -> bytes:
    if arbitration_id & CAN_EFF_FLAG:
        return FRAME_EXT_HEAD % (arbitration_id & CAN_EFF_MASK)
    prefix = _PREFIXES[arbitration_id] = FRAME_STD_HEAD % arbitration_id
    return prefix

