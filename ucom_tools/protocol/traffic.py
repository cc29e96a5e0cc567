"""What one bus carried, as this PC saw it: every frame received and sent, counted for the
bus load and shown to whoever listens (the taps, python-can's Listeners; the sink).

The :class:`~ucom_tools.protocol.dispatch.Dispatcher` of a bus keeps one :class:`Traffic`;
its router (received frames) and its sender (sent frames) feed it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Final

import can

from ucom_tools.wire.canbits import frame_bits

STUFF_SAMPLE: Final = 64
"""The stuff bits of one frame in this many are computed (for the measured bus load: at
1 kHz on four buses some 400 frames a second, plenty for their share of the bits)."""

SENT: Final = 1
""":attr:`Traffic.sink` flags: the frame was sent (else received), ..."""
EXTENDED: Final = 2
"""... has a 29-bit identifier, ..."""
REMOTE: Final = 4
"""... is a remote frame, ..."""
ERROR: Final = 8
"""... is an error frame."""
SinkEntry = tuple[int, bytes, float, int]
"""A frame in :attr:`Traffic.sink`: identifier, data, time stamp, flags."""

Tap = Callable[[can.Message], None]
"""A listener called with every frame received and sent."""


def flags(msg: can.Message) -> int:
    """The :data:`SinkEntry` flags of a frame's type."""
    return ((EXTENDED if msg.is_extended_id else 0) | (REMOTE if msg.is_remote_frame else 0)
            | (ERROR if msg.is_error_frame else 0))


class Traffic:
    """The frames of one bus, both ways: their bits, and their listeners.

    The per-frame paths (:meth:`~ucom_tools.protocol.routing.Router.dispatch_all`,
    :meth:`~ucom_tools.protocol.sending.Sender.note_sent`) add to the counts inline, as
    :meth:`count` does (one Python call fewer for every frame, as before the split)."""

    def __init__(self) -> None:
        self.taps: list[Tap] = []
        """Called with every frame received and sent (recorders), in the reading or
        sending thread."""
        self.sink: list[SinkEntry] | None = None
        """Where set, every frame received and sent is appended to it as plain data
        (:data:`SinkEntry`), cheaper than a tap (no ``can.Message``): the run time hands
        them to another process (``ucom remote run --record``); its owner swaps the list
        for an empty one as it takes them."""
        self.nominal = 0
        """Bits of the frames counted, without stuff bits."""
        self.frames = 0
        """Frames counted (standard data frames, the bus load's)."""
        self.sample_nominal = 0
        """:attr:`nominal` of the frames whose stuff bits were computed, ..."""
        self.sample_exact = 0
        """... and their bits with the stuff bits."""

    def count(self, arbitration_id: int, data: bytes | bytearray) -> None:
        """Bits on the bus: 47 + 8n per frame (Tab. B.2), scaled by the stuff bits of
        every :data:`STUFF_SAMPLE` th frame (computing them for every frame would cost
        more than the rest of the frame's handling)."""
        nominal = 47 + 8 * len(data)
        self.nominal += nominal
        self.frames += 1
        if self.frames % STUFF_SAMPLE == 1:
            self.sample_nominal += nominal
            self.sample_exact += frame_bits(arbitration_id, bytes(data))

    @property
    def bits(self) -> int:
        """Bits of every frame seen on the bus (received and sent), stuff bits included
        as sampled: the bus load this PC measures."""
        if not self.sample_nominal:
            return self.nominal
        return round(self.nominal * self.sample_exact / self.sample_nominal)
