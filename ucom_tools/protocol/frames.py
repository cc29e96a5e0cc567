"""``can.Message`` built without its constructor, for the per-frame paths; and
:data:`DataFrame`, a received frame without one.

The run time's loop builds a message for every frame it receives over socketcand, and for
every frame it sends while a tap (a recorder) listens; python-can's constructor, with its
keyword arguments and data conversion, costs about a microsecond there, more than the
rest of the frame's decoding.  :func:`data_frame` sets the same attributes directly.  It
is used only while ``can.Message`` has exactly the attributes set here (python-can 4.x,
:data:`FAST`); otherwise the constructor is.
"""

from __future__ import annotations

import can

DataFrame = tuple[int, bytes, float]
"""A received standard (11-bit) data frame as the run time's receiving paths carry it:
identifier, data and time stamp, no ``can.Message``.  A bus that hands these over
(``recv_ready_frames``, ``advance_frames``: :class:`~ucom_tools.protocol.dispatch.
Dispatcher`) builds the message its ``recv`` would have given with ``message_of``, for
the subscribers and taps that take messages."""

_ATTRIBUTES = frozenset({"arbitration_id", "bitrate_switch", "channel", "data", "dlc",
                         "error_state_indicator", "is_error_frame", "is_extended_id",
                         "is_fd", "is_remote_frame", "is_rx", "timestamp"})
FAST = frozenset(getattr(can.Message, "__slots__", ())) - {"__weakref__"} == _ATTRIBUTES
"""Whether :func:`data_frame` may set the attributes itself (it sets every one)."""
new_message = object.__new__
"""``new_message(can.Message)``: a message without attributes, for code that sets all of
:data:`_ATTRIBUTES` inline (the socketcand client's receiving loop), when :data:`FAST`."""


def data_frame(timestamp: float, arbitration_id: int, data: bytearray, *,
               is_extended_id: bool, is_rx: bool, channel: str | None) -> can.Message:
    """``can.Message(timestamp=..., arbitration_id=..., data=data, ...)`` of a data frame
    (not remote, not an error, not FD); ``data`` is taken as it is, not copied."""
    if not FAST:
        return can.Message(timestamp=timestamp, arbitration_id=arbitration_id, data=data,
                           is_extended_id=is_extended_id, is_rx=is_rx, channel=channel)
    msg: can.Message = new_message(can.Message)
    msg.timestamp = timestamp
    msg.arbitration_id = arbitration_id
    msg.is_extended_id = is_extended_id
    msg.is_remote_frame = False
    msg.is_error_frame = False
    msg.channel = channel
    msg.is_fd = False
    msg.is_rx = is_rx
    msg.bitrate_switch = False
    msg.error_state_indicator = False
    msg.data = data
    msg.dlc = len(data)
    return msg


def received_message(frame: DataFrame, channel: str | None) -> can.Message:
    """The received message of a :data:`DataFrame` on ``channel``: what a bus's ``recv``
    gives for it (its data copied into a bytearray, as python-can's own messages hold)."""
    ident, data, stamp = frame
    return data_frame(stamp, ident, bytearray(data), is_extended_id=False, is_rx=True,
                      channel=channel)
