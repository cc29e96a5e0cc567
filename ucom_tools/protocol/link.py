"""A protocol link: sends and receives decoded messages over one python-can bus.

Turns python-can exceptions into :class:`~ucom_tools.errors.BusError` and frames into
``(Address, message)`` pairs; frames that are not bootloader-level messages (MCA traffic,
foreign identifiers) are passed to ``on_other`` or dropped.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import can

from ucom_tools.errors import BusError, FrameError
from ucom_tools.wire import messages as m
from ucom_tools.wire.ids import Address, Direction


@dataclass(frozen=True)
class Received:
    address: Address
    message: m.BootMessage
    timestamp: float


class Link:
    """Send and receive UCoM messages on one bus."""

    def __init__(self, bus: can.BusABC, name: str = "") -> None:
        self.bus = bus
        self.name = name or str(getattr(bus, "channel_info", "bus"))
        self.malformed: list[tuple[can.Message, FrameError]] = []
        self.on_other: Callable[[can.Message], None] | None = None

    def send(self, message: m.BootMessage, address: Address) -> None:
        arb, data = m.encode(message, address)
        self.send_raw(arb, data)

    def send_raw(self, arbitration_id: int, data: bytes) -> None:
        msg = can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=False)
        for attempt in range(50):
            try:
                self.bus.send(msg, timeout=0.1)
                return
            except can.CanOperationError as err:
                if "buffer" not in str(err).lower() or attempt == 49:
                    raise BusError(f"{self.name}: cannot send: {err}") from err
                time.sleep(0.001)
            except can.CanError as err:
                raise BusError(f"{self.name}: cannot send: {err}") from err

    def recv(self, timeout: float) -> Received | None:
        """The next bootloader-level message from a board, or None after ``timeout``.

        On the virtual fleet in virtual time the wait costs no wall time."""
        deadline = time.monotonic() + timeout
        remaining = timeout
        while True:
            try:
                raw = self.bus.recv(max(0.0, remaining))
            except can.CanError as err:
                raise BusError(f"{self.name}: cannot receive: {err}") from err
            if raw is None:
                return None
            got = self._decode(raw)
            if got is not None:
                return got
            remaining = deadline - time.monotonic()

    def _decode(self, raw: can.Message) -> Received | None:
        if raw.is_extended_id or raw.is_error_frame or raw.is_remote_frame:
            return None
        try:
            address, msg = m.decode(raw.arbitration_id, bytes(raw.data),
                                    sender=Direction.BOARD_TO_HOST)
        except FrameError as err:
            code = raw.arbitration_id >> 6
            if code <= 27 and code in m.BOOTLOADER_FUNCTIONS:
                self.malformed.append((raw, err))
            elif self.on_other is not None:
                self.on_other(raw)
            return None
        return Received(address, msg, raw.timestamp)

    def drain(self, quiet: float = 0.0) -> list[Received]:
        """Everything already received (and whatever arrives within ``quiet``)."""
        out = []
        while (got := self.recv(quiet)) is not None:
            out.append(got)
        return out

    def messages(self, timeout: float) -> Iterator[Received]:
        while (got := self.recv(timeout)) is not None:
            yield got
