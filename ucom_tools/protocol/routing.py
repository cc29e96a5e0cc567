"""Received frames to their subscribers (python-can's Notifier handing a frame to its
Listeners, by filter).

Clients subscribe with a filter: the bootloader link takes the bootloader answers, the
run-time client the MCA answers and process data; a frame goes to every subscriber whose
filter takes it (an Error, say, to both), into a bounded queue or to a callback
(latest-value data needs no queue).  A frame nobody takes is counted by function code, not
lost silently.  A :class:`Router` is one bus's; its
:class:`~ucom_tools.protocol.dispatch.Dispatcher` hands it what it read.
"""

from __future__ import annotations

import threading
from collections import Counter, deque
from collections.abc import Callable, Iterable
from typing import Final

import can

from ucom_tools.protocol.frames import DataFrame, received_message
from ucom_tools.protocol.traffic import STUFF_SAMPLE, Traffic, flags
from ucom_tools.wire.canbits import frame_bits

QUEUE_LIMIT: Final = 10_000
"""Frames a subscriber may have waiting; older ones are dropped (and counted) beyond."""

Accepts = Callable[[can.Message], bool]
"""A subscriber's filter.  It must look only at the identifier and the frame's type
(extended, remote, error): its answer is kept per identifier."""
OnData = Callable[[int, bytes, float], None]
"""A subscriber's callback for standard data frames by identifier, data and time stamp."""
RouteKey = int | tuple[int, bool, bool, bool]
"""A route's key: the identifier of a standard data frame, else identifier and type."""


class Subscription:
    """Frames a client takes: queued for :meth:`~ucom_tools.protocol.dispatch.Dispatcher.
    wait`, passed to ``on_frame``, or, standard data frames (all a filter that takes only
    those gets), to ``on_data`` as identifier, data and time stamp: no ``can.Message``
    where the bus hands over :data:`~ucom_tools.protocol.frames.DataFrame` s (the run
    time's SO maps)."""

    def __init__(self, accepts: Accepts, name: str,
                 on_frame: Callable[[can.Message], None] | None = None,
                 on_data: OnData | None = None) -> None:
        self.accepts = accepts
        self.name = name
        self.on_frame = on_frame
        self.on_data = on_data
        self.queue: deque[can.Message] = deque()
        self.dropped = 0


class Router:
    """The subscribers of one bus's received frames, and what none of them took."""

    def __init__(self, name: str, lock: threading.RLock, traffic: Traffic,
                 message_of: Callable[[DataFrame], can.Message] | None) -> None:
        self.name = name
        self.lock = lock
        """Held to change the subscribers and their queues (the reading turns' lock: a
        frame queued under it wakes a waiter, :mod:`~ucom_tools.protocol.turns`)."""
        self.traffic = traffic
        self.message_of = message_of
        """The bus's ``message_of`` (:mod:`~ucom_tools.protocol.buscontract`), if any."""
        self.subscriptions: list[Subscription] = []
        self.unclaimed: Counter[int] = Counter()
        """Frames no subscriber took, by function code (identifier bits 10-6)."""
        self.received = 0
        self.routes: dict[RouteKey, list[Subscription]] = {}
        """The subscribers per identifier and type (:meth:`route`): keyed by the
        identifier alone for a standard data frame, the frames of the run time."""

    def subscribe(self, sub: Subscription) -> None:
        with self.lock:
            self.subscriptions.append(sub)
            self.routes = {}

    def unsubscribe(self, sub: Subscription) -> None:
        with self.lock:
            if sub in self.subscriptions:
                self.subscriptions.remove(sub)
            self.routes = {}

    def discard(self, sub: Subscription) -> int:
        """Drop what waits in ``sub``'s queue; how many."""
        with self.lock:
            n = len(sub.queue)
            sub.queue.clear()
        return n

    def take(self, sub: Subscription) -> can.Message | None:
        """The next frame queued for ``sub`` now, or None."""
        with self.lock:
            return sub.queue.popleft() if sub.queue else None

    def route(self, msg: can.Message) -> list[Subscription]:
        """The subscribers of frames with this identifier and type (a filter looks only
        at those: its answer is kept per identifier until the subscribers change)."""
        key: RouteKey = msg.arbitration_id
        if msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame:
            key = (msg.arbitration_id, msg.is_extended_id, msg.is_remote_frame,
                   msg.is_error_frame)
        subs = self.routes.get(key)
        if subs is None:
            with self.lock:
                subs = [s for s in self.subscriptions if s.accepts(msg)]
                self.routes[key] = subs
        return subs

    def dispatch_all(self, msgs: Iterable[can.Message | DataFrame]) -> None:
        """Hand each received frame in turn to every subscriber that takes it, counted
        and shown to the taps and the sink.  One flat loop on purpose: the run time's
        loop hands over some 16 frames a millisecond (the counting, the taps and the
        route of a standard data frame, looked up by its identifier alone, inline).  A
        frame may be a :data:`~ucom_tools.protocol.frames.DataFrame` from the bus (then
        its message is built only for a tap or a subscriber without ``on_data``)."""
        traffic = self.traffic
        taps = traffic.taps
        sink = traffic.sink
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
                nominal = 47 + 8 * len(data)  # traffic.count(), inline
                traffic.nominal += nominal
                counted = traffic.frames = traffic.frames + 1
                if counted % STUFF_SAMPLE == 1:
                    traffic.sample_nominal += nominal
                    traffic.sample_exact += frame_bits(ident, data)
            if sink is not None:
                if plain:
                    sink.append((ident, data, stamp, 0))
                else:
                    assert msg is not None
                    sink.append((ident, bytes(msg.data), stamp, flags(msg)))
            if taps:
                if msg is None:
                    msg = self.message(item)
                for tap in taps:
                    tap(msg)
            subs = self.routes.get(ident) if plain else None
            if subs is None:
                if msg is None:
                    msg = self.message(item)
                subs = self.route(msg)
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
                    msg = self.message(item)
                on_frame = sub.on_frame
                if on_frame is not None:
                    on_frame(msg)
                    continue
                with self.lock:
                    if len(sub.queue) >= QUEUE_LIMIT:
                        sub.queue.popleft()
                        sub.dropped += 1
                    sub.queue.append(msg)

    def message(self, item: can.Message | DataFrame) -> can.Message:
        """The message of a frame :meth:`dispatch_all` was handed."""
        if not isinstance(item, tuple):
            return item
        message_of = self.message_of
        if message_of is not None:
            return message_of(item)
        return received_message(item, self.name)
