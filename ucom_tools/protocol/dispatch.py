"""One reader per bus: the frames a bus receives, handed to whoever waits for them.

A :class:`Dispatcher` is the only code that reads its ``can.BusABC`` (python-can's
Notifier/Listener model).  Clients subscribe with a filter: the bootloader link takes the
bootloader answers, the run-time client the MCA answers and process data; a frame goes to
every subscriber whose filter takes it (an Error, say, to both), into a bounded queue or
to a callback (latest-value data needs no queue).  A frame nobody takes is counted by
function code, not lost silently.

Reading happens in whichever thread waits (virtual time: the wait drives the fleet
clock), one at a time: a second waiter sleeps until the reader has delivered, or its
deadline passes; with :meth:`Dispatcher.start` a background thread reads instead (real
buses shared by a console and a running exchange).  Sends from several threads are
serialised.

A thread whose waits are stepped by another (:func:`stepped_by`: a conversation beside
the run time's loop, :mod:`~ucom_tools.protocol.stepped`) does not read at all: its
:meth:`Dispatcher.wait` hands control back to the loop, which stays the bus's one reader.

Periodic frames (:meth:`Dispatcher.every`: the cyclic exchange's CI maps, MCA Alive) are
sent by the reader too, on their deadlines on the bus clock: whoever waits for a frame
keeps them going, so a console command that waits for a board's answer never starves the
watchdog of a running exchange.  A task that could not be sent within its period counts
the occurrences it missed (``late``) and keeps its schedule.
"""

from __future__ import annotations

import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Iterable
from typing import Any, Final

import can

from ucom_tools.errors import BusError
from ucom_tools.protocol.frames import DataFrame, data_frame, received_message
from ucom_tools.wire.canbits import frame_bits

STUFF_SAMPLE: Final = 64
"""The stuff bits of one frame in this many are computed (for the measured bus load: at
1 kHz on four buses some 400 frames a second, plenty for their share of the bits)."""
QUEUE_LIMIT: Final = 10_000
"""Frames a subscriber may have waiting; older ones are dropped (and counted) beyond."""
POLL_S: Final = 0.05
"""How long the background reader waits for a frame before it looks at its stop flag."""

_stepping = threading.local()
"""``stepper``: the :class:`~ucom_tools.protocol.stepped.Stepped` conversation whose
worker this thread is (its waits yield to the loop, :func:`stepped_by`)."""


def stepped_by(stepper: Any) -> None:
    """From now on this thread's :meth:`Dispatcher.wait` calls are
    ``stepper.wait(dispatcher, sub, deadline)``: the thread never reads a bus (None: it
    reads again)."""
    _stepping.stepper = stepper


Accepts = Callable[[can.Message], bool]
"""A subscriber's filter.  It must look only at the identifier and the frame's type
(extended, remote, error): its answer is kept per identifier."""
OnData = Callable[[int, bytes, float], None]
"""A subscriber's callback for standard data frames by identifier, data and time stamp."""
SENT: Final = 1
""":attr:`Dispatcher.sink` flags: the frame was sent (else received), ..."""
EXTENDED: Final = 2
"""... has a 29-bit identifier, ..."""
REMOTE: Final = 4
"""... is a remote frame, ..."""
ERROR: Final = 8
"""... is an error frame."""
SinkEntry = tuple[int, bytes, float, int]
"""A frame in :attr:`Dispatcher.sink`: identifier, data, time stamp, flags."""


def _flags(msg: can.Message) -> int:
    """The :data:`SinkEntry` flags of a frame's type."""
    return ((EXTENDED if msg.is_extended_id else 0) | (REMOTE if msg.is_remote_frame else 0)
            | (ERROR if msg.is_error_frame else 0))


class Subscription:
    """Frames a client takes: queued for :meth:`Dispatcher.wait`, passed to ``on_frame``,
    or, standard data frames (all a filter that takes only those gets), to ``on_data`` as
    identifier, data and time stamp: no ``can.Message`` where the bus hands over
    :data:`~ucom_tools.protocol.frames.DataFrame` s (the run time's SO maps)."""

    def __init__(self, accepts: Accepts, name: str,
                 on_frame: Callable[[can.Message], None] | None = None,
                 on_data: OnData | None = None) -> None:
        self.accepts = accepts
        self.name = name
        self.on_frame = on_frame
        self.on_data = on_data
        self.queue: deque[can.Message] = deque()
        self.dropped = 0


Frames = Callable[[], Iterable[can.Message | tuple[int, bytes]]]
"""A periodic task's frames: messages, or standard data frames as (identifier, data),
sent without a ``can.Message`` (:meth:`Dispatcher.send_data`)."""


class Periodic:
    """Frames sent every ``period`` seconds of the bus clock, due at ``start + k period``."""

    def __init__(self, period: float, frames: Frames, name: str, due: float) -> None:
        if period <= 0:
            raise ValueError("period must be positive")
        self.period = period
        self.frames = frames
        self.name = name
        self.due = due
        self.sent = 0
        """Occurrences sent."""
        self.late = 0
        """Occurrences missed: the reader came to the task a whole period or more after
        it was due (the bus clock was not read in time)."""
        self.max_delay = 0.0
        """Longest time between an occurrence's due time and its sending (seconds)."""
        self.cancelled = False


def _earliest(times: list[float | None]) -> float | None:
    """The earliest of ``times`` that is not None (None if none is): ``min()`` of a
    generator with ``default=`` as a loop, which mypyc compiles (the builtin is an
    interpreter call, several times a step of a pump)."""
    out: float | None = None
    for t in times:
        if t is not None and (out is None or t < out):
            out = t
    return out


class Dispatcher:
    """The reader of one bus and the frames' subscribers."""

    def __init__(self, bus: can.BusABC, name: str = "") -> None:
        self.bus = bus
        self.name = name or str(getattr(bus, "channel_info", "bus"))
        clock = getattr(bus, "clock", None)
        self.clock: Callable[[], float] = clock if callable(clock) else time.monotonic
        """Seconds on the bus's time base (virtual time on the in-process fleet)."""
        stamp = getattr(bus, "stamp", None)
        self._stamp: Callable[[], float] = stamp if callable(stamp) else time.time
        """A timestamp on the base of the received frames' (the wall clock, or the
        virtual fleet's epoch plus its time): for the sent frames the taps see."""
        self.subscriptions: list[Subscription] = []
        self.unclaimed: Counter[int] = Counter()
        """Frames no subscriber took, by function code (identifier bits 10-6)."""
        self.received = 0
        self.sent = 0
        self._nominal = 0
        self._frames_counted = 0
        self._sample_nominal = 0
        self._sample_exact = 0
        self._routes: dict[int | tuple[int, bool, bool, bool], list[Subscription]] = {}
        """The subscribers per identifier and type (:meth:`_route`): keyed by the
        identifier alone for a standard data frame, the frames of the run time."""
        self.taps: list[Callable[[can.Message], None]] = []
        """Called with every frame received and sent (recorders), in the reading or
        sending thread."""
        self.sink: list[SinkEntry] | None = None
        """Where set, every frame received and sent is appended to it as plain data
        (:data:`SinkEntry`), cheaper than a tap (no ``can.Message``): the run time hands
        them to another process (``ucom remote run --record``); its owner swaps the list
        for an empty one as it takes them."""
        self._lock = threading.RLock()
        """``_cond``'s lock: ``with self._lock`` is ``with self._cond`` without the Python
        wrapper around it (the per-cycle paths take it several times).  The reading flag
        is set and cleared under it, never under ``_cond``: a stop signal's exception
        can be raised in Condition's Python ``__exit__``, after the flag was set and
        before the ``try`` that clears it, and then every later wait (the boards' stop)
        would wait for a reader that is gone."""
        self._cond = threading.Condition(self._lock)
        self._sleepers = 0
        """Threads in ``_cond.wait``: the reader notifies only when there are any."""
        self._reading = False
        self._send_lock = threading.Lock()
        self._reader: threading.Thread | None = None
        self._stop = False
        self.failure: BusError | None = None
        self._tasks: list[Periodic] = []
        self._in_tasks = False
        self.group: list[Dispatcher] = [self]
        """Dispatchers whose periodic frames this one sends too while it waits: the buses
        of one in-process fleet, whose clock whichever of them waits drives
        (:func:`share_clock`)."""
        self._next_due: float | None = None
        """When the next periodic task is due (None: look)."""
        advance = getattr(bus, "advance_frames", None)
        self._advance: Callable[[float], list[can.Message | DataFrame] | None] | None = \
            advance if callable(advance) else None
        """The bus's way to run its clock on and hand over every frame that came meanwhile
        in one call (:meth:`~ucom_tools.virtual.canbus.VirtualUcomBus.advance_frames`:
        the in-process fleet in virtual time), if it has one: :meth:`pump` uses it."""
        ready = getattr(bus, "recv_ready_frames", None)
        self._ready: Callable[[int], list[can.Message | DataFrame] | None] | None = \
            ready if callable(ready) else None
        """The bus's way to hand over every frame that has arrived in one call, without
        waiting (:meth:`~ucom_tools.transport.socketcand.SocketcandBus.
        recv_ready_frames`), if it has one: :meth:`drain` uses it."""
        message_of = getattr(bus, "message_of", None)
        self._message_of: Callable[[DataFrame], can.Message] | None = \
            message_of if callable(message_of) else None
        """The message the bus's ``recv`` gives for a :data:`DataFrame` it handed over
        (a bus with ``advance_frames`` or ``recv_ready_frames`` has one)."""
        send_many = getattr(bus, "send_data_many", None)
        self._send_many: Callable[[list[tuple[int, bytes]], float | None], None] | None = \
            send_many if callable(send_many) else None
        """The bus's way to send several standard data frames in one call, all or none
        (:meth:`~ucom_tools.transport.socketcand.SocketcandBus.send_data_many`), if it
        has one."""
        self.batches = self._send_many is not None
        """Whether :meth:`send_data_many` hands frames to the bus in one call."""
        send_data = getattr(bus, "send_data", None)
        self._send_data: Callable[[int, bytes, float | None], None] | None = \
            send_data if callable(send_data) else None
        """The bus's way to send a standard data frame without a can.Message
        (:meth:`~ucom_tools.transport.socketcand.SocketcandBus.send_data`), if it has one."""

    # ------------------------------------------------------------------ subscribers
    def subscribe(self, accepts: Accepts, name: str,
                  on_frame: Callable[[can.Message], None] | None = None, *,
                  on_data: OnData | None = None) -> Subscription:
        """Frames that ``accepts`` takes from now on: to ``on_frame``, or ``on_data``
        (standard data frames only: an ``accepts`` that takes no other), else queued for
        :meth:`wait`."""
        sub = Subscription(accepts, name, on_frame, on_data)
        with self._cond:
            self.subscriptions.append(sub)
            self._routes = {}
        return sub

    def unsubscribe(self, sub: Subscription) -> None:
        with self._cond:
            if sub in self.subscriptions:
                self.subscriptions.remove(sub)
            self._routes = {}

    # ------------------------------------------------------------------ sending
    def send(self, msg: can.Message, timeout: float | None) -> None:
        with self._send_lock:
            self.bus.send(msg, timeout=timeout)
        self.sent += 1
        self._count(msg)
        sink = self.sink
        if sink is not None:
            sink.append((msg.arbitration_id, bytes(msg.data), self.stamp(),
                         SENT | _flags(msg)))
        if self.taps:
            out = can.Message(timestamp=self.stamp(), arbitration_id=msg.arbitration_id,
                              data=msg.data, is_extended_id=False, is_rx=False,
                              channel=self.name)
            for tap in self.taps:
                tap(out)

    def send_data(self, arbitration_id: int, data: bytes, timeout: float | None) -> None:
        """:meth:`send` of a standard data frame given by identifier and data (the link's
        frames): without a can.Message where the bus takes the two (socketcand), and
        then one only for the taps."""
        fast = self._send_data
        if fast is None:
            self.send(can.Message(arbitration_id=arbitration_id, data=data,
                                  is_extended_id=False, check=False), timeout)
            return
        with self._send_lock:
            fast(arbitration_id, data, timeout)
        self.sent += 1
        self._note_sent(arbitration_id, data)

    def _note_sent(self, arbitration_id: int, data: bytes) -> None:
        """A standard data frame the bus took: counted (:meth:`_count_data`, inlined) and
        shown to the taps."""
        nominal = 47 + 8 * len(data)
        self._nominal += nominal
        counted = self._frames_counted = self._frames_counted + 1
        if counted % STUFF_SAMPLE == 1:
            self._sample_nominal += nominal
            self._sample_exact += frame_bits(arbitration_id, bytes(data))
        sink = self.sink
        if sink is not None:
            sink.append((arbitration_id, bytes(data), self._stamp(), SENT))
        taps = self.taps
        if taps:
            out = data_frame(self._stamp(), arbitration_id, bytearray(data),
                             is_extended_id=False, is_rx=False, channel=self.name)
            for tap in taps:
                tap(out)

    def send_data_many(self, frames: list[tuple[int, bytes]], timeout: float | None,
                       ) -> None:
        """:meth:`send_data` of each frame, in one call to a bus that :attr:`batches`
        (within ``timeout`` for all of them; if the bus raises, it took none), else one
        by one."""
        fast = self._send_many
        if fast is None:
            for ident, data in frames:
                self.send_data(ident, data, timeout)
            return
        with self._send_lock:
            fast(frames, timeout)
        self.sent += len(frames)
        for ident, data in frames:
            self._note_sent(ident, data)

    def stamp(self) -> float:
        """Now, on the time base of this bus's received frames' timestamps (what a sent
        frame is stamped with for the taps)."""
        return self._stamp()

    def every(self, period: float, frames: Frames, name: str,
              *, start: float | None = None) -> Periodic:
        """Send ``frames()`` every ``period`` seconds of :attr:`clock`, the first time at
        ``start`` (now when None); a frame given as (identifier, data) by
        :meth:`send_data`."""
        task = Periodic(period, frames, name, self.clock() if start is None else start)
        with self._cond:
            self._tasks.append(task)
            self._next_due = None  # look at the tasks again
        return task

    def cancel(self, task: Periodic) -> None:
        with self._cond:
            task.cancelled = True
            if task in self._tasks:
                self._tasks.remove(task)
            self._next_due = None

    def _run_due(self) -> float | None:
        """Send every periodic task that is due; the time the next one is due."""
        if not self._tasks:
            return None
        nxt = self._next_due
        if nxt is not None and self.clock() < nxt:
            return nxt  # nothing due (the common case: no lock taken)
        with self._lock:  # (_cond's lock, without Condition's Python __enter__)
            if self._in_tasks:
                return min(t.due for t in self._tasks) if self._tasks else None
            self._in_tasks = True
            tasks = list(self._tasks)
        try:
            now = self.clock()
            for task in tasks:
                if task.cancelled or task.due > now:
                    continue
                delay = now - task.due
                missed = int(delay // task.period)
                task.late += missed
                task.max_delay = max(task.max_delay, delay)
                for frame in task.frames():
                    if isinstance(frame, tuple):
                        self.send_data(frame[0], frame[1], task.period)
                    else:
                        self.send(frame, timeout=task.period)
                task.sent += 1
                task.due += (missed + 1) * task.period
            earliest: float | None = None  # the earliest due (a loop: min() of a generator
            for t in tasks:  # with default= is an interpreter call, every step of a pump)
                if not t.cancelled and (earliest is None or t.due < earliest):
                    earliest = t.due
            self._next_due = earliest
            return self._next_due
        finally:
            with self._lock:
                self._in_tasks = False

    # ------------------------------------------------------------------ receiving
    def discard(self, sub: Subscription) -> int:
        """Drop what waits in ``sub``'s queue (a subscription whose owner reads it only
        while it asks something, and answers meant for another came meanwhile); how many."""
        with self._lock:
            n = len(sub.queue)
            sub.queue.clear()
        return n

    def take(self, sub: Subscription) -> can.Message | None:
        """The next frame queued for ``sub`` now, or None (never reads the bus)."""
        with self._lock:
            return sub.queue.popleft() if sub.queue else None

    def wait(self, sub: Subscription, deadline: float) -> can.Message | None:
        """The next frame for ``sub``, or None at ``deadline`` (on :attr:`clock`).  In a
        thread stepped by a loop (:func:`stepped_by`) the loop reads and this waits for
        it."""
        stepper = getattr(_stepping, "stepper", None)
        if stepper is not None:
            got: can.Message | None = stepper.wait(self, sub, deadline)
            return got
        while True:
            with self._lock:
                if sub.queue:
                    return sub.queue.popleft()
                if self.failure is not None:
                    raise self.failure
                remaining = deadline - self.clock()
                busy = self._reading or self._reader is not None
                if busy:  # another thread reads: wait for it (continue after the lock)
                    if remaining <= 0:
                        return None
                    self._sleep(min(remaining, POLL_S))
                else:
                    self._reading = True
            if busy:
                continue
            try:
                self._read_one(max(0.0, remaining))
            finally:
                with self._lock:
                    self._reading = False
                    if self._sleepers:
                        self._cond.notify_all()
            if remaining <= 0 and not sub.queue:
                return None

    def _read_one(self, timeout: float) -> bool:
        """Send the periodic frames due, read one frame (waiting up to ``timeout``, or
        until the next periodic frame is due) and dispatch it; False if none came."""
        dues = [d._run_due() for d in self.group]
        nxt = _earliest(dues)
        if nxt is not None:
            timeout = max(0.0, min(timeout, nxt - self.clock()))
        try:
            msg = self.bus.recv(timeout)
        except can.CanError as err:
            raise self._fail(f"{self.name}: cannot receive: {err}") from err
        except OSError as err:
            raise self._fail(f"{self.name}: cannot receive: {err.strerror or err}") from err
        if msg is None:
            return False
        self.dispatch(msg)
        return True

    def _sleep(self, timeout: float) -> None:
        """``_cond.wait``, counted in :attr:`_sleepers` (called with ``_cond`` held)."""
        self._sleepers += 1
        try:
            self._cond.wait(timeout)
        finally:
            self._sleepers -= 1

    def _fail(self, text: str) -> BusError:
        err = BusError(text)
        with self._cond:
            self.failure = err
            self._cond.notify_all()
        return err

    def _count(self, msg: can.Message) -> None:
        """Bits on the bus: 47 + 8n per frame (Tab. B.2), scaled by the stuff bits of
        every 64th frame (computing them for every frame would cost more than the rest
        of the frame's handling)."""
        self._count_data(msg.arbitration_id, msg.data)

    def _count_data(self, arbitration_id: int, data: bytes | bytearray) -> None:
        """:meth:`_count` of a frame given by identifier and data."""
        nominal = 47 + 8 * len(data)
        self._nominal += nominal
        self._frames_counted += 1
        if self._frames_counted % STUFF_SAMPLE == 1:
            self._sample_nominal += nominal
            self._sample_exact += frame_bits(arbitration_id, bytes(data))

    @property
    def bits(self) -> int:
        """Bits of every frame seen on the bus (received and sent), stuff bits included
        as sampled: the bus load this PC measures."""
        if not self._sample_nominal:
            return self._nominal
        return round(self._nominal * self._sample_exact / self._sample_nominal)

    def _route(self, msg: can.Message) -> list[Subscription]:
        """The subscribers of frames with this identifier and type (a filter looks only
        at those: its answer is kept per identifier until the subscribers change)."""
        key: int | tuple[int, bool, bool, bool] = msg.arbitration_id
        if msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame:
            key = (msg.arbitration_id, msg.is_extended_id, msg.is_remote_frame,
                   msg.is_error_frame)
        subs = self._routes.get(key)
        if subs is None:
            with self._cond:
                subs = [s for s in self.subscriptions if s.accepts(msg)]
                self._routes[key] = subs
        return subs

    def dispatch(self, msg: can.Message) -> None:
        """Hand a received frame to every subscriber that takes it."""
        self.dispatch_all((msg,))

    def dispatch_all(self, msgs: Iterable[can.Message | DataFrame]) -> None:
        """:meth:`dispatch` of each frame in turn, with the per-frame work inlined: the
        loop of the run time hands over some 16 frames a millisecond (counting, taps,
        the route of a standard data frame looked up by its identifier alone).  A frame
        may be a :data:`~ucom_tools.protocol.frames.DataFrame` from the bus (then its
        message is built only for a tap or a subscriber without ``on_data``)."""
        taps = self.taps
        sink = self.sink
        for item in msgs:
            self.received += 1
            msg: can.Message | None
            if isinstance(item, tuple):
                ident, data, stamp = item
                msg = None
                plain = True
            else:
                msg = item
                ident = msg.arbitration_id
                plain = not (msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame)
                data = bytes(msg.data) if plain else b""
                stamp = msg.timestamp
            if plain:
                nominal = 47 + 8 * len(data)  # _count_data(), inlined
                self._nominal += nominal
                counted = self._frames_counted = self._frames_counted + 1
                if counted % STUFF_SAMPLE == 1:
                    self._sample_nominal += nominal
                    self._sample_exact += frame_bits(ident, data)
            if sink is not None:
                if plain:
                    sink.append((ident, data, stamp, 0))
                else:
                    assert msg is not None
                    sink.append((ident, bytes(msg.data), stamp, _flags(msg)))
            if taps:
                if msg is None:
                    msg = self._message(item)
                for tap in taps:
                    tap(msg)
            subs = self._routes.get(ident) if plain else None
            if subs is None:
                if msg is None:
                    msg = self._message(item)
                subs = self._route(msg)
            if not subs:
                self.unclaimed[ident >> 6] += 1
                continue
            for sub in subs:
                on_data = sub.on_data
                if on_data is not None:  # (it takes standard data frames only)
                    if plain:
                        on_data(ident, data, stamp)
                    continue
                if msg is None:
                    msg = self._message(item)
                on_frame = sub.on_frame
                if on_frame is not None:
                    on_frame(msg)
                    continue
                with self._lock:
                    if len(sub.queue) >= QUEUE_LIMIT:
                        sub.queue.popleft()
                        sub.dropped += 1
                    sub.queue.append(msg)

    def _message(self, item: can.Message | DataFrame) -> can.Message:
        """The message of a frame :meth:`dispatch_all` was handed."""
        if not isinstance(item, tuple):
            return item
        message_of = self._message_of
        if message_of is not None:
            return message_of(item)
        return received_message(item, self.name)

    def _advance_one(self, timeout: float) -> int | None:
        """:meth:`_read_one` by the bus's ``advance_frames``: send the periodic frames due, run
        the bus's clock ``timeout`` on (or until the next periodic frame is due) and
        dispatch every frame that came meanwhile, in order; how many (None: the bus
        cannot now, read one by one)."""
        advance = self._advance
        if advance is None:
            return None
        dues = [d._run_due() for d in self.group]
        nxt = _earliest(dues)
        if nxt is not None:
            timeout = max(0.0, min(timeout, nxt - self.clock()))
        try:
            msgs = advance(timeout)
        except can.CanError as err:
            raise self._fail(f"{self.name}: cannot receive: {err}") from err
        if msgs is None:
            return None
        self.dispatch_all(msgs)
        return len(msgs)

    def pump(self, deadline: float) -> int:
        """Read and dispatch everything until ``deadline``; returns the frames read.
        (For callers that only feed callback subscribers, e.g. a cyclic exchange.)

        On a bus that can ``advance`` (the in-process fleet in virtual time) the clock
        runs from one periodic frame due to the next, not from frame to frame: the frames
        that came meanwhile are dispatched together, each with its own time stamp, at
        the end of the stretch (the periodic frames go out at the same bus times)."""
        count = 0
        while True:
            remaining = deadline - self.clock()
            with self._lock:
                busy = self._reader is not None or self._reading
                if busy:
                    if remaining <= 0:
                        return count
                    self._sleep(min(remaining, POLL_S))
                else:
                    self._reading = True
            if busy:
                continue
            try:
                taken = self._advance_one(max(0.0, remaining))
                if taken is None:
                    taken = 1 if self._read_one(max(0.0, remaining)) else 0
            finally:
                with self._lock:
                    self._reading = False
                    if self._sleepers:
                        self._cond.notify_all()
            if taken:
                count += taken
            elif self.clock() >= deadline:
                return count

    def drain(self, limit: int = 1000) -> int:
        """Read and dispatch what has arrived, without waiting (at most ``limit`` frames);
        0 at once when another thread is reading.  For a loop that polls several buses."""
        with self._lock:
            if self._reader is not None or self._reading:
                return 0
            self._reading = True
        count = 0
        try:
            for d in self.group:  # the periodic frames due, once (not once per frame)
                d._run_due()
            recv, dispatch = self.bus.recv, self.dispatch
            ready = self._ready
            if ready is not None:  # a bus that hands over what has arrived in one call
                try:
                    msgs = ready(limit)
                except can.CanError as err:
                    raise self._fail(f"{self.name}: cannot receive: {err}") from err
                except OSError as err:
                    raise self._fail(f"{self.name}: cannot receive: "
                                     f"{err.strerror or err}") from err
                if msgs is not None:
                    self.dispatch_all(msgs)
                    return len(msgs)
            while count < limit:
                try:
                    msg = recv(0.0)
                except can.CanError as err:
                    raise self._fail(f"{self.name}: cannot receive: {err}") from err
                except OSError as err:
                    raise self._fail(f"{self.name}: cannot receive: "
                                     f"{err.strerror or err}") from err
                if msg is None:
                    break
                dispatch(msg)
                count += 1
        finally:
            with self._lock:
                self._reading = False
                if self._sleepers:
                    self._cond.notify_all()
        return count

    # ------------------------------------------------------------------ background
    def start(self) -> None:
        """Read in a background thread from now on (for real-time buses)."""
        if self._reader is not None:
            return
        self._stop = False
        self._reader = threading.Thread(target=self._run, name=f"ucom-reader-{self.name}",
                                        daemon=True)
        self._reader.start()

    def stop(self) -> None:
        thread = self._reader
        if thread is None:
            return
        self._stop = True
        thread.join(timeout=2)
        with self._cond:
            self._reader = None
            self._cond.notify_all()

    def _run(self) -> None:
        while not self._stop:
            try:
                self._read_one(POLL_S)
            except BusError:
                return
            with self._cond:
                self._cond.notify_all()


def share_clock(dispatchers: list[Dispatcher]) -> None:
    """Dispatchers of buses on one virtual clock (one in-process fleet, one thread): a wait
    on any of them drives the clock for all, so each sends the others' periodic frames too
    (a wait on one bus must not starve another bus's MCA Alive)."""
    for d in dispatchers:
        d.group = list(dispatchers)
