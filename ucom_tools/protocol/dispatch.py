"""One reader per bus: the frames a bus receives, handed to whoever waits for them.

A :class:`Dispatcher` is the only code that reads its ``can.BusABC`` (python-can's
Notifier/Listener model).  It puts together one bus's parts, each in a module of its own:

- :mod:`~ucom_tools.protocol.routing`: received frames to the subscribers whose filter
  takes them (a queue or a callback), and those nobody took counted;
- :mod:`~ucom_tools.protocol.sending`: sends from several threads, serialised;
- :mod:`~ucom_tools.protocol.periodic`: periodic frames (:meth:`Dispatcher.every`: the
  cyclic exchange's CI maps, MCA Alive), sent by the reader on their deadlines on the
  bus clock;
- :mod:`~ucom_tools.protocol.turns`: which thread reads now: whichever waits (virtual
  time: the wait drives the fleet clock), one at a time;
- :mod:`~ucom_tools.protocol.background`: with :meth:`Dispatcher.start`, a thread that
  reads instead (real buses shared by a console and a running exchange);
- :mod:`~ucom_tools.protocol.traffic`: every frame both ways counted for the bus load and
  shown to the taps and the sink;
- :mod:`~ucom_tools.protocol.buscontract`: what the bus may offer beyond ``can.BusABC``
  (its own clock, frames handed over many at a time, ...), looked up once.

A thread whose waits are stepped by another (:func:`stepped_by`: a conversation beside
the run time's loop, :mod:`~ucom_tools.protocol.stepped`) does not read at all: its
:meth:`Dispatcher.wait` hands control back to the loop, which stays the bus's one reader.
"""

from __future__ import annotations

import threading
from collections import Counter
from collections.abc import Callable, Iterable
from typing import Any

import can

from ucom_tools.errors import BusError
from ucom_tools.protocol.background import BackgroundReader
from ucom_tools.protocol.buscontract import extensions_of
from ucom_tools.protocol.frames import DataFrame
from ucom_tools.protocol.periodic import Frames, Periodic, Schedule, earliest
from ucom_tools.protocol.routing import Accepts, OnData, Router, Subscription
from ucom_tools.protocol.sending import Sender
from ucom_tools.protocol.traffic import SinkEntry, Tap, Traffic
from ucom_tools.protocol.turns import Turns

_stepping = threading.local()
"""``stepper``: the :class:`~ucom_tools.protocol.stepped.Stepped` conversation whose
worker this thread is (its waits yield to the loop, :func:`stepped_by`)."""


def stepped_by(stepper: Any) -> None:
    """From now on this thread's :meth:`Dispatcher.wait` calls are
    ``stepper.wait(dispatcher, sub, deadline)``: the thread never reads a bus (None: it
    reads again)."""
    _stepping.stepper = stepper


class Dispatcher:
    """The reader of one bus and the frames' subscribers."""

    def __init__(self, bus: can.BusABC, name: str = "") -> None:
        self.bus = bus
        self.name = name or str(getattr(bus, "channel_info", "bus"))
        extensions = extensions_of(bus)
        self.clock: Callable[[], float] = extensions.clock
        """Seconds on the bus's time base (virtual time on the in-process fleet)."""
        self.turns = Turns()
        self.traffic = Traffic()
        self.router = Router(self.name, self.turns.lock, self.traffic,
                             extensions.message_of)
        self.sender = Sender(bus, self.name, extensions, self.traffic)
        self.schedule = Schedule(self.clock, self.turns.lock, self.sender)
        self.group: list[Schedule] = [self.schedule]
        """The periodic frames this dispatcher sends while it reads: its own, and those of
        the other buses of one in-process fleet, whose clock whichever of them waits
        drives (:func:`share_clock`)."""
        self.batches = self.sender.batches
        """Whether :meth:`send_data_many` hands frames to the bus in one call."""
        self._background = BackgroundReader(self.turns, self._read_one, self.name)
        self._advance = extensions.advance_frames
        """The bus's ``advance_frames``, if it has one: :meth:`pump` uses it."""
        self._ready = extensions.recv_ready_frames
        """The bus's ``recv_ready_frames``, if it has one: :meth:`drain` uses it."""

    # ------------------------------------------------------------------ what it keeps
    @property
    def subscriptions(self) -> list[Subscription]:
        return self.router.subscriptions

    @property
    def unclaimed(self) -> Counter[int]:
        """Frames no subscriber took, by function code (identifier bits 10-6)."""
        return self.router.unclaimed

    @property
    def received(self) -> int:
        return self.router.received

    @property
    def sent(self) -> int:
        return self.sender.sent

    @property
    def bits(self) -> int:
        """:attr:`Traffic.bits <ucom_tools.protocol.traffic.Traffic.bits>`: the bus load."""
        return self.traffic.bits

    @property
    def taps(self) -> list[Tap]:
        """:attr:`Traffic.taps <ucom_tools.protocol.traffic.Traffic.taps>`."""
        return self.traffic.taps

    @taps.setter
    def taps(self, taps: list[Tap]) -> None:
        self.traffic.taps = taps

    @property
    def sink(self) -> list[SinkEntry] | None:
        """:attr:`Traffic.sink <ucom_tools.protocol.traffic.Traffic.sink>`."""
        return self.traffic.sink

    @sink.setter
    def sink(self, sink: list[SinkEntry] | None) -> None:
        self.traffic.sink = sink

    @property
    def failure(self) -> BusError | None:
        """Why the bus can no longer be read (every wait raises it), or None."""
        return self.turns.failure

    # ------------------------------------------------------------------ subscribers
    def subscribe(self, accepts: Accepts, name: str,
                  on_frame: Callable[[can.Message], None] | None = None, *,
                  on_data: OnData | None = None) -> Subscription:
        """Frames that ``accepts`` takes from now on: to ``on_frame``, or ``on_data``
        (standard data frames only: an ``accepts`` that takes no other), else queued for
        :meth:`wait`."""
        sub = Subscription(accepts, name, on_frame, on_data)
        self.router.subscribe(sub)
        return sub

    def unsubscribe(self, sub: Subscription) -> None:
        self.router.unsubscribe(sub)

    # ------------------------------------------------------------------ sending
    def send(self, msg: can.Message, timeout: float | None) -> None:
        self.sender.send(msg, timeout)

    def send_data(self, arbitration_id: int, data: bytes, timeout: float | None) -> None:
        """:meth:`Sender.send_data <ucom_tools.protocol.sending.Sender.send_data>`."""
        self.sender.send_data(arbitration_id, data, timeout)

    def send_data_many(self, frames: list[tuple[int, bytes]], timeout: float | None,
                       ) -> None:
        """:meth:`Sender.send_data_many
        <ucom_tools.protocol.sending.Sender.send_data_many>`."""
        self.sender.send_data_many(frames, timeout)

    def stamp(self) -> float:
        """Now, on the time base of this bus's received frames' timestamps (what a sent
        frame is stamped with for the taps)."""
        return self.sender.stamp()

    def every(self, period: float, frames: Frames, name: str,
              *, start: float | None = None) -> Periodic:
        """Send ``frames()`` every ``period`` seconds of :attr:`clock`, the first time at
        ``start`` (now when None); a frame given as (identifier, data) by
        :meth:`send_data`."""
        return self.schedule.every(period, frames, name, start)

    def cancel(self, task: Periodic) -> None:
        self.schedule.cancel(task)

    # ------------------------------------------------------------------ receiving
    def discard(self, sub: Subscription) -> int:
        """Drop what waits in ``sub``'s queue (a subscription whose owner reads it only
        while it asks something, and answers meant for another came meanwhile); how many."""
        return self.router.discard(sub)

    def take(self, sub: Subscription) -> can.Message | None:
        """The next frame queued for ``sub`` now, or None (never reads the bus)."""
        return self.router.take(sub)

    def dispatch(self, msg: can.Message) -> None:
        """Hand a received frame to every subscriber that takes it."""
        self.router.dispatch_all((msg,))

    def dispatch_all(self, msgs: Iterable[can.Message | DataFrame]) -> None:
        """:meth:`dispatch` of each frame in turn (:meth:`Router.dispatch_all
        <ucom_tools.protocol.routing.Router.dispatch_all>`)."""
        self.router.dispatch_all(msgs)

    def wait(self, sub: Subscription, deadline: float) -> can.Message | None:
        """The next frame for ``sub``, or None at ``deadline`` (on :attr:`clock`).  In a
        thread stepped by a loop (:func:`stepped_by`) the loop reads and this waits for
        it."""
        stepper = getattr(_stepping, "stepper", None)
        if stepper is not None:
            got: can.Message | None = stepper.wait(self, sub, deadline)
            return got
        queue = sub.queue
        turns = self.turns
        taken: list[can.Message] = []

        def ready() -> bool:  # (under the turns' lock)
            if queue:
                taken.append(queue.popleft())
                return True
            if turns.failure is not None:
                raise turns.failure
            return False

        def finished(remaining: float, _frames: int) -> bool:
            return remaining <= 0 and not queue

        turns.read_until(deadline, self.clock, self._read_one, finished, ready)
        return taken[0] if taken else None

    def pump(self, deadline: float) -> int:
        """Read and dispatch everything until ``deadline``; returns the frames read.
        (For callers that only feed callback subscribers, e.g. a cyclic exchange.)

        On a bus that can ``advance`` (the in-process fleet in virtual time) the clock
        runs from one periodic frame due to the next, not from frame to frame: the frames
        that came meanwhile are dispatched together, each with its own time stamp, at
        the end of the stretch (the periodic frames go out at the same bus times)."""
        clock = self.clock

        def finished(_remaining: float, frames: int) -> bool:
            return not frames and clock() >= deadline

        return self.turns.read_until(deadline, clock, self._read_stretch, finished)

    def drain(self, limit: int = 1000) -> int:
        """Read and dispatch what has arrived, without waiting (at most ``limit`` frames);
        0 at once when another thread is reading.  For a loop that polls several buses."""
        turns = self.turns
        with turns.lock:  # turns.take() and give_back(), inline: once a cycle of every bus
            if turns.background or turns.reading:
                return 0
            turns.reading = True
        try:
            for schedule in self.group:  # the periodic frames due, once (not once per frame)
                schedule.run_due()
            ready = self._ready
            if ready is not None:  # a bus that hands over what has arrived in one call
                try:
                    msgs = ready(limit)
                except can.CanError as err:
                    raise turns.fail(f"{self.name}: cannot receive: {err}") from err
                except OSError as err:
                    raise turns.fail(f"{self.name}: cannot receive: "
                                     f"{err.strerror or err}") from err
                if msgs is not None:
                    self.router.dispatch_all(msgs)
                    return len(msgs)
            return self._drain_one_by_one(limit)
        finally:
            with turns.lock:
                turns.reading = False
                if turns.sleepers:
                    turns.cond.notify_all()

    def _drain_one_by_one(self, limit: int) -> int:
        """:meth:`drain` by ``recv(0)``."""
        count = 0
        recv, dispatch = self.bus.recv, self.dispatch
        while count < limit:
            msg = self._received(recv, 0.0)
            if msg is None:
                break
            dispatch(msg)
            count += 1
        return count

    def _received(self, receive: Callable[[Any], Any], arg: float | int) -> Any:
        """``receive(arg)``, a failure of the bus noted and raised as :class:`BusError`."""
        try:
            return receive(arg)
        except can.CanError as err:
            raise self.turns.fail(f"{self.name}: cannot receive: {err}") from err
        except OSError as err:
            raise self.turns.fail(f"{self.name}: cannot receive: "
                                  f"{err.strerror or err}") from err

    def _read_one(self, timeout: float) -> int:
        """Send the periodic frames due, read one frame (waiting up to ``timeout``, or
        until the next periodic frame is due) and dispatch it; 0 if none came, else 1."""
        nxt = earliest([s.run_due() for s in self.group])
        if nxt is not None:
            timeout = max(0.0, min(timeout, nxt - self.clock()))
        msg = self._received(self.bus.recv, timeout)
        if msg is None:
            return 0
        self.router.dispatch_all((msg,))
        return 1

    def _read_stretch(self, timeout: float) -> int:
        """:meth:`_read_one` by the bus's ``advance_frames`` where it can: send the
        periodic frames due, run the bus's clock ``timeout`` on (or until the next
        periodic frame is due) and dispatch every frame that came meanwhile, in order;
        how many."""
        advance = self._advance
        if advance is None:
            return self._read_one(timeout)
        nxt = earliest([s.run_due() for s in self.group])
        if nxt is not None:
            timeout = max(0.0, min(timeout, nxt - self.clock()))
        try:
            msgs = advance(timeout)
        except can.CanError as err:
            raise self.turns.fail(f"{self.name}: cannot receive: {err}") from err
        if msgs is None:  # the bus cannot now: one by one
            return self._read_one(timeout)
        self.router.dispatch_all(msgs)
        return len(msgs)

    # ------------------------------------------------------------------ background
    def start(self) -> None:
        """Read in a background thread from now on (for real-time buses)."""
        self._background.start()

    def stop(self) -> None:
        self._background.stop()


def share_clock(dispatchers: list[Dispatcher]) -> None:
    """Dispatchers of buses on one virtual clock (one in-process fleet, one thread): a wait
    on any of them drives the clock for all, so each sends the others' periodic frames too
    (a wait on one bus must not starve another bus's MCA Alive)."""
    for d in dispatchers:
        d.group = [x.schedule for x in dispatchers]
