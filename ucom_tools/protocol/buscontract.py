"""What a bus may offer the dispatcher beyond python-can's ``can.BusABC``: the bus contract.

Every ``can.BusABC`` works with a :class:`~ucom_tools.protocol.dispatch.Dispatcher`: it
reads with ``recv`` and sends with ``send``, on the wall clock.  A bus may also have any of
the methods below (python-can's ``BusABC`` documents its extension points, ``_recv_internal``
and ``send``, the same way: what each means, who calls it, what happens without it).  The
dispatcher looks for them once, when it is built (:func:`extensions_of`), and calls what it
found on every frame; it never asks again, so a bus must have them from its constructor on.

``clock()`` (:class:`Clocked`)
    Seconds on the bus's time base, the one ``recv``'s timeouts count on.  The dispatcher's
    deadlines, waits and periodic frames are on it.  Without it: ``time.monotonic``.
``stamp()`` (:class:`Stamped`)
    Now, on the time base of the received frames' timestamps: what the dispatcher stamps a
    frame it sent with for its taps and sink.  Without it: ``time.time``.
``send_data(arbitration_id, data, timeout)`` (:class:`SendsData`)
    ``send`` of a standard (11-bit) data frame given by identifier and data, without a
    ``can.Message``; the same errors as ``send``.  The dispatcher's ``send_data`` (the
    link's frames, the run time's cyclic maps) uses it.  Without it: ``send`` of a message
    built for it.
``send_data_many(frames, timeout)`` (:class:`SendsDataMany`)
    ``send_data`` of several frames in one call, within ``timeout`` for all of them: all of
    them or, when it raises, none.  The dispatcher's ``send_data_many`` (a cycle's frames)
    uses it and says so (``batches``).  Without it: ``send_data`` of each in turn.
``advance_frames(timeout)`` (:class:`AdvancesFrames`)
    Run the bus's clock ``timeout`` seconds on and return every frame received meanwhile,
    in order, at once (a standard data frame as a
    :data:`~ucom_tools.protocol.frames.DataFrame`); None when that would not be what
    ``recv`` gives (filters set, or the bus runs in real time).  The dispatcher's ``pump``
    runs the clock from one periodic frame due to the next with it.  Without it (or when
    it returns None): one ``recv`` per frame.
``recv_ready_frames(limit)`` (:class:`HandsOverReady`)
    Every frame that has arrived (about ``limit`` at most), without waiting, at once, a
    standard data frame as a :data:`~ucom_tools.protocol.frames.DataFrame`; None when
    ``recv`` would give something else (filters set).  The dispatcher's ``drain`` uses it.
    Without it (or when it returns None): ``recv(0)`` until it gives nothing.
``message_of(frame)`` (:class:`BuildsMessages`)
    The message ``recv`` would have given for a :data:`~ucom_tools.protocol.frames.
    DataFrame` the bus handed over, built only for a tap or a subscriber that takes
    messages.  Without it: :func:`~ucom_tools.protocol.frames.received_message` on the
    dispatcher's name as the channel.

Two buses of ours implement the contract, and say so where mypy checks it:
:class:`VirtualTimeBus` is the in-process fleet's (:class:`~ucom_tools.virtual.canbus.
VirtualUcomBus`), :class:`BatchingBus` the socketcand client's
(:class:`~ucom_tools.transport.socketcand.SocketcandBus`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import can

from ucom_tools.protocol.frames import DataFrame

Frames = list[can.Message | DataFrame]
"""What ``advance_frames`` and ``recv_ready_frames`` hand over, in the order received."""


@runtime_checkable
class Clocked(Protocol):
    """A bus with a time base of its own (virtual time on the in-process fleet)."""

    def clock(self) -> float:
        """Seconds on the time base of ``recv``'s timeouts."""


@runtime_checkable
class Stamped(Protocol):
    """A bus that says what time its received frames would be stamped with now."""

    def stamp(self) -> float:
        """Now, on the received frames' time base (seconds since the epoch)."""


@runtime_checkable
class SendsData(Protocol):
    """A bus that sends a standard data frame without a ``can.Message``."""

    def send_data(self, arbitration_id: int, data: bytes, timeout: float | None, /,
                  ) -> None:
        """``send`` of the standard data frame ``arbitration_id``, ``data``."""


@runtime_checkable
class SendsDataMany(Protocol):
    """A bus that sends several standard data frames in one call, all or none."""

    def send_data_many(self, frames: list[tuple[int, bytes]], timeout: float | None, /,
                       ) -> None:
        """``send_data`` of each of ``frames`` (identifier, data), within ``timeout``."""


@runtime_checkable
class BuildsMessages(Protocol):
    """A bus that hands over :data:`~ucom_tools.protocol.frames.DataFrame` s."""

    def message_of(self, frame: DataFrame, /) -> can.Message:
        """The message ``recv`` would have given for ``frame``."""


@runtime_checkable
class AdvancesFrames(BuildsMessages, Protocol):
    """A bus whose clock the reader runs on, taking what came meanwhile in one call."""

    def advance_frames(self, timeout: float, /) -> Frames | None:
        """Run the clock ``timeout`` seconds on; every frame received by then."""


@runtime_checkable
class HandsOverReady(BuildsMessages, Protocol):
    """A bus that hands over every frame that has arrived in one call."""

    def recv_ready_frames(self, limit: int, /) -> Frames | None:
        """Every frame that has arrived, without waiting."""


@runtime_checkable
class VirtualTimeBus(Clocked, Stamped, SendsData, AdvancesFrames, Protocol):
    """The contract of a bus on a virtual clock that the reader drives (the in-process
    fleet, :class:`~ucom_tools.virtual.canbus.VirtualUcomBus`)."""


@runtime_checkable
class BatchingBus(SendsData, SendsDataMany, HandsOverReady, Protocol):
    """The contract of a network bus that reads and writes many frames a call (the
    socketcand client, :class:`~ucom_tools.transport.socketcand.SocketcandBus`)."""


@dataclass(frozen=True)
class Extensions:
    """The methods of the contract a bus has (None: it has not), looked up once; the
    clocks are the wall clock's where the bus has none."""

    clock: Callable[[], float]
    stamp: Callable[[], float]
    send_data: Callable[[int, bytes, float | None], None] | None
    send_data_many: Callable[[list[tuple[int, bytes]], float | None], None] | None
    advance_frames: Callable[[float], Frames | None] | None
    recv_ready_frames: Callable[[int], Frames | None] | None
    message_of: Callable[[DataFrame], can.Message] | None


def extensions_of(bus: can.BusABC) -> Extensions:
    """Which methods of the contract ``bus`` has (an attribute that is not callable
    counts as none)."""
    clock, stamp = _method(bus, "clock"), _method(bus, "stamp")
    return Extensions(clock=clock if clock is not None else time.monotonic,
                      stamp=stamp if stamp is not None else time.time,
                      send_data=_method(bus, "send_data"),
                      send_data_many=_method(bus, "send_data_many"),
                      advance_frames=_method(bus, "advance_frames"),
                      recv_ready_frames=_method(bus, "recv_ready_frames"),
                      message_of=_method(bus, "message_of"))


def _method(bus: can.BusABC, name: str) -> Any:
    """``bus``'s method ``name``, or None."""
    method = getattr(bus, name, None)
    return method if callable(method) else None
