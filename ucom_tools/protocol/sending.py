"""Frames to one bus, from any thread: serialised, counted and shown to the taps and the
sink (:mod:`~ucom_tools.protocol.traffic`), by the bus's fastest way that the bus contract
(:mod:`~ucom_tools.protocol.buscontract`) says it has.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import can

from ucom_tools.protocol.buscontract import Extensions
from ucom_tools.protocol.frames import data_frame
from ucom_tools.protocol.traffic import SENT, STUFF_SAMPLE, Traffic, flags
from ucom_tools.wire.canbits import frame_bits


class Sender:
    """The sending side of one bus's :class:`~ucom_tools.protocol.dispatch.Dispatcher`."""

    def __init__(self, bus: can.BusABC, name: str, extensions: Extensions,
                 traffic: Traffic) -> None:
        self.bus = bus
        self.name = name
        self.traffic = traffic
        self.sent = 0
        self._lock = threading.Lock()
        self.stamp: Callable[[], float] = extensions.stamp
        """A timestamp on the base of the received frames' (the wall clock, or the
        virtual fleet's epoch plus its time): for the sent frames the taps see."""
        self._send_data = extensions.send_data
        """The bus's ``send_data``, if it has one."""
        self._send_many = extensions.send_data_many
        """The bus's ``send_data_many``, if it has one."""
        self.batches = self._send_many is not None
        """Whether :meth:`send_data_many` hands frames to the bus in one call."""

    def send(self, msg: can.Message, timeout: float | None) -> None:
        with self._lock:
            self.bus.send(msg, timeout=timeout)
        self.sent += 1
        traffic = self.traffic
        traffic.count(msg.arbitration_id, msg.data)
        sink = traffic.sink
        if sink is not None:
            sink.append((msg.arbitration_id, bytes(msg.data), self.stamp(),
                         SENT | flags(msg)))
        if traffic.taps:
            out = can.Message(timestamp=self.stamp(), arbitration_id=msg.arbitration_id,
                              data=msg.data, is_extended_id=False, is_rx=False,
                              channel=self.name)
            for tap in traffic.taps:
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
        with self._lock:
            fast(arbitration_id, data, timeout)
        self.sent += 1
        self.note_sent(arbitration_id, data)

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
        with self._lock:
            fast(frames, timeout)
        self.sent += len(frames)
        for ident, data in frames:
            self.note_sent(ident, data)

    def note_sent(self, arbitration_id: int, data: bytes) -> None:
        """A standard data frame the bus took: counted (:meth:`Traffic.count`, inline:
        every frame sent) and shown to the taps and the sink."""
        traffic = self.traffic
        nominal = 47 + 8 * len(data)
        traffic.nominal += nominal
        counted = traffic.frames = traffic.frames + 1
        if counted % STUFF_SAMPLE == 1:
            traffic.sample_nominal += nominal
            traffic.sample_exact += frame_bits(arbitration_id, bytes(data))
        sink = traffic.sink
        if sink is not None:
            sink.append((arbitration_id, bytes(data), self.stamp(), SENT))
        taps = traffic.taps
        if taps:
            out = data_frame(self.stamp(), arbitration_id, bytearray(data),
                             is_extended_id=False, is_rx=False, channel=self.name)
            for tap in taps:
                tap(out)
