"""A protocol link: sends and receives decoded messages over one python-can bus.

Turns python-can exceptions into :class:`~ucom_tools.errors.BusError` and frames into
``(Address, message)`` pairs.  The link is one subscriber of its bus's
:class:`~ucom_tools.protocol.dispatch.Dispatcher` (the bus's one reader): it takes the
bootloader-level answers of the boards; run-time traffic goes to other subscribers, and
what nobody takes is counted there.

Every wait of the host is derived from the work (``man/ucom-protocol.7``, TIMEOUTS): the
link keeps a *wire horizon*, the time by which every frame it has handed to the bus has
crossed the wire at the bus bitrate, assuming worst-case bit stuffing; a wait for an
answer is the rest of that horizon, plus the wire time of the answer frames, plus the
board's own time, plus the transport margin of this link (a network bus needs more than
a local adapter).  Wire times are doubled to leave room for other traffic on the bus.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Final

import can

from ucom_tools.errors import BusError, FrameError
from ucom_tools.native import mypyc_attr
from ucom_tools.protocol.dispatch import Dispatcher
from ucom_tools.wire import messages as m
from ucom_tools.wire.canbits import worst_frame_bits
from ucom_tools.wire.ids import Address, Direction

_ANSWERS: Final = frozenset(f.value for f in m.BOOTLOADER_FUNCTIONS
                      if f.direction is Direction.BOARD_TO_HOST)


def _bootloader_answer(msg: can.Message) -> bool:
    """A board's bootloader-level frame (standard data frame of a board -> PC function)."""
    return not (msg.is_extended_id or msg.is_error_frame or msg.is_remote_frame) and \
        (msg.arbitration_id >> 6) in _ANSWERS


SEND_SLACK: Final = 1.0
"""Seconds an interface may take to accept a frame beyond the frames ahead of it."""
SHARED_BUS_FACTOR: Final = 2.0
"""Wire times in deadlines are multiplied by this: the bus may carry other traffic."""


@dataclass(frozen=True)
class Received:
    address: Address
    message: m.BootMessage
    timestamp: float


@mypyc_attr(native_class=False)  # a conformance case replaces send_raw on an instance
class Link:  # (frames lost on purpose): see compiled.py
    """Send and receive UCoM messages on one bus.

    ``bitrate`` is the bus bitrate the deadlines assume; ``margin`` the transport margin
    in seconds (0 for the in-process virtual fleet, a few ms for a local adapter, more for
    a network bus such as socketcand)."""

    def __init__(self, bus: can.BusABC, name: str = "", *, bitrate: int = 1_000_000,
                 margin: float = 0.0, dispatcher: Dispatcher | None = None) -> None:
        self.bus = bus
        self.name = name or str(getattr(bus, "channel_info", "bus"))
        self.bitrate = bitrate
        self.margin = margin
        self.malformed: list[tuple[can.Message, FrameError]] = []
        self.dispatcher = dispatcher or Dispatcher(bus, self.name)
        self.clock: Callable[[], float] = self.dispatcher.clock
        """Seconds on the bus's own time base (virtual time on the in-process fleet)."""
        self._sub = self.dispatcher.subscribe(_bootloader_answer, f"{self.name} bootloader")
        self._horizon = 0.0
        self._frame_time = [worst_frame_bits(dlc) / bitrate for dlc in range(9)]
        self.frames_sent = 0

    def close(self) -> None:
        """Take no more frames (a second link on a dispatcher, for a while)."""
        self.dispatcher.unsubscribe(self._sub)

    # ------------------------------------------------------------------ timing
    @property
    def horizon(self) -> float:
        """When the frames handed to the bus so far will have passed, as this link reckons
        (on :attr:`clock`: each frame's worst wire time, one after the other, from when it
        was handed over or the previous one passed)."""
        return self._horizon

    def wire_time(self, frames: int, dlc: int = 8) -> float:
        """Worst-case seconds ``frames`` frames of ``dlc`` bytes take on this bus."""
        return frames * self._frame_time[dlc]

    def budget(self, board_time: float, *, answers: int = 0) -> float:
        """Seconds to wait for an answer to the last frame sent: the frames still on their
        way, ``answers`` answer frames, the board's ``board_time`` and the margin."""
        ahead = max(0.0, self._horizon - self.clock())
        return (SHARED_BUS_FACTOR * (ahead + self.wire_time(answers)) + board_time
                + self.margin)

    def deadline(self, board_time: float, *, answers: int = 0) -> float:
        """:meth:`budget` as an absolute time on :attr:`clock`."""
        return self.clock() + self.budget(board_time, answers=answers)

    # ------------------------------------------------------------------ sending
    def send(self, message: m.BootMessage, address: Address) -> None:
        arb, data = m.encode(message, address)
        self.send_raw(arb, data)

    def send_raw(self, arbitration_id: int, data: bytes) -> None:
        """Hand one frame to the bus.  The interface may take a while to accept it (its
        transmit queue is full, a network bus pushes back): that wait is bounded like
        every other, by the frames still ahead plus :data:`SEND_SLACK` and the margin
        (:meth:`send_frames` of this one frame)."""
        self.send_frames([(arbitration_id, data)])

    def send_frames(self, frames: list[tuple[int, bytes]]) -> None:
        """Hand each frame to the bus in turn (a cyclic exchange's frames of one cycle),
        with the link's attributes looked up once per call, not per frame; each wait
        bounded as :meth:`send_raw` says, a frame the bus does not take at once offered
        again (:meth:`_offer_again`).  A bus that takes a cycle's frames in one call
        (:meth:`~ucom_tools.protocol.dispatch.Dispatcher.send_data_many`: socketcand)
        gets them so, within the last frame's bound; if it refuses them, it took none
        (all or nothing), and they are handed over one by one."""
        if not frames:
            return
        frame_time = self._frame_time
        base = SEND_SLACK + self.margin
        now = self.clock()
        horizon = self._horizon
        dispatcher = self.dispatcher
        if dispatcher.batches:
            start = horizon if horizon > now else now
            last = start
            for _, data in frames:
                last += frame_time[len(data)]
            final = last - frame_time[len(frames[-1][1])]  # the last frame's horizon before it
            try:
                dispatcher.send_data_many(frames, SHARED_BUS_FACTOR * (final - now) + base)
            except (can.CanError, OSError):
                pass  # none was taken: one by one, with their own bounds and retries
            else:
                self._horizon = last
                self.frames_sent += len(frames)
                return
        send_data = dispatcher.send_data
        try:
            for ident, data in frames:
                limit = SHARED_BUS_FACTOR * (horizon - now if horizon > now else 0.0) + base
                try:
                    send_data(ident, data, limit)
                except (can.CanError, OSError) as err:
                    self._offer_again(err, ident, data, limit)
                horizon = (horizon if horizon > now else now) + frame_time[len(data)]
                self.frames_sent += 1
        finally:
            self._horizon = horizon

    def _offer_again(self, err: Exception, arbitration_id: int, data: bytes,
                     limit: float) -> None:
        """After the bus refused a frame with ``err``: an adapter whose queue is full may
        refuse at once (SocketCAN: ENOBUFS), so that is offered again every millisecond
        within ``limit`` seconds; any other error is a BusError."""
        deadline = 0.0
        while True:
            if isinstance(err, can.CanOperationError):
                deadline = deadline or time.monotonic() + limit
                if "buffer" not in str(err).lower() or time.monotonic() >= deadline:
                    raise BusError(f"{self.name}: cannot send: {err}") from err
                time.sleep(0.001)  # back off, then offer the frame again
                limit = max(0.0, deadline - time.monotonic())
            elif isinstance(err, can.CanError):
                raise BusError(f"{self.name}: cannot send: {err}") from err
            else:
                reason = err.strerror if isinstance(err, OSError) else None
                raise BusError(f"{self.name}: cannot send: {reason or err}") from err
            try:
                self.dispatcher.send_data(arbitration_id, data, timeout=limit)
                return
            except (can.CanError, OSError) as again:
                err = again

    # ------------------------------------------------------------------ receiving
    def recv(self, timeout: float) -> Received | None:
        """The next bootloader-level message from a board, or None after ``timeout``
        seconds of the bus's clock (virtual time on the in-process fleet)."""
        return self.recv_until(self.clock() + timeout)

    def recv_until(self, deadline: float) -> Received | None:
        """The next bootloader-level message from a board, or None at ``deadline``."""
        while True:
            raw = self.dispatcher.wait(self._sub, deadline)
            if raw is None:
                return None
            got = self._decode(raw)
            if got is not None:
                return got

    def _decode(self, raw: can.Message) -> Received | None:
        try:
            address, msg = m.decode(raw.arbitration_id, bytes(raw.data),
                                    sender=Direction.BOARD_TO_HOST)
        except FrameError as err:
            self.malformed.append((raw, err))
            return None
        return Received(address, msg, raw.timestamp)

    def until(self, deadline: float) -> Iterator[Received]:
        """Every message until ``deadline`` (absolute, on :attr:`clock`); the caller stops
        early by breaking out."""
        while (got := self.recv_until(deadline)) is not None:
            yield got

    def quiet(self, gap: float, limit: float) -> Iterator[Received]:
        """Messages until none arrived for ``gap`` seconds, or until ``limit`` (absolute)."""
        while True:
            got = self.recv_until(min(limit, self.clock() + gap))
            if got is None:
                return
            yield got

    def drain(self, quiet: float = 0.0) -> list[Received]:
        """Everything already received (and whatever arrives within ``quiet``)."""
        return list(self.quiet(quiet, self.clock() + max(quiet, 0.0) * 100 + 1.0))
