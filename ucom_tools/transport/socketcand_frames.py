"""The socketcand client's frames as the elements it writes and reads: ``can.Message`` to
``< send ... >`` and ``< frame ... >`` to ``can.Message`` (the element grammar itself is
:mod:`ucom_tools.wire.socketcand`'s, shared with the server), and a cycle's standard data
frames as one write (:func:`data_elements`), and what an error frame says
(:func:`state_of_error`).  Every frame sent comes through here.
"""

from __future__ import annotations

from typing import Final

import can

from ucom_tools.wire.socketcand import (
    CAN_EFF_FLAG,
    CAN_EFF_MASK,
    CAN_ERR_ACK,
    CAN_ERR_BUSOFF,
    CAN_ERR_RESTARTED,
    CAN_SFF_MASK,
    SEND_STD,
    frame_words,
)
from ucom_tools.wire.socketcand import send_element as wire_send_element

_SEND_HEADS: Final[dict[int, bytes]] = {}
"""``< send ID DLC `` by ``ID << 4 | DLC`` (:func:`data_elements`)."""
_HEX_BLANK: Final = [b"%02X " % octet for octet in range(256)]
"""Each byte's two upper-case hex digits and a blank."""


def parse_frame(words: list[str], channel: str) -> can.Message:
    """``< frame ID SEC.USEC DATA >`` as words -> a received message; ``ValueError`` if bad
    (:func:`ucom_tools.wire.socketcand.frame_words`)."""
    can_id, stamp, data = frame_words(words)
    return can.Message(timestamp=stamp, arbitration_id=can_id & CAN_EFF_MASK, data=data,
                       is_extended_id=can_id > CAN_EFF_MASK, is_rx=True, channel=channel)


def send_element(msg: can.Message) -> str:
    """The ``< send ID DLC B0 B1 ... >`` element for a message; ``ValueError`` if it has none."""
    return send_bytes(msg).decode("ascii")


def send_bytes(msg: can.Message) -> bytes:
    """:func:`send_element` as the bytes written; the usual standard data frame in a few
    operations (this runs for every frame sent)."""
    data = msg.data
    dlc = msg.dlc
    ident = msg.arbitration_id
    if not (msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame or msg.is_fd) \
            and 0 <= ident <= CAN_SFF_MASK and 0 < dlc <= 8 and len(data) == dlc:
        return SEND_STD % (ident, dlc, bytes(data).hex(" ").upper().encode())
    if msg.is_remote_frame:
        raise ValueError("remote frames")
    if msg.is_error_frame:
        raise ValueError("error frames")
    if msg.is_fd:
        raise ValueError("CAN FD frames")
    if msg.dlc > 8 or len(data) < msg.dlc:
        raise ValueError(f"DLC {msg.dlc} with {len(msg.data)} data bytes")
    return wire_send_element(ident | CAN_EFF_FLAG if msg.is_extended_id else ident,
                             bytes(data[:dlc]))


def shown(element: bytes) -> str:
    """An element as text, with its brackets (for messages)."""
    return f"<{element.decode('ascii', 'replace')}>"


def data_elements(frames: list[tuple[int, bytes]]) -> bytes:
    """The ``< send ... >`` elements of standard data frames (identifier, data), one after
    the other, from cached pieces (no formatting); ``ValueError`` (what cannot be sent)
    for a frame that is not a standard data frame of at most 8 bytes."""
    pieces: list[bytes] = []
    heads = _SEND_HEADS
    for ident, data in frames:
        n = len(data)
        if not 0 <= ident <= CAN_SFF_MASK or n > 8:
            send_bytes(can.Message(arbitration_id=ident, data=data, is_extended_id=False,
                                   check=False))  # its own refusal, if it has one
            raise ValueError(f"identifier {ident:#x} with {n} bytes")
        key = ident << 4 | n
        head = heads.get(key)
        if head is None:
            head = heads[key] = b"< send %03X %d " % (ident, n)
        pieces.append(head)
        for octet in data:
            pieces.append(_HEX_BLANK[octet])
        pieces.append(b">")
    return b"".join(pieces)


def state_of_error(error_class: int) -> can.BusState | None:
    """What an error frame of the server's bus (``< error CLASS SEC.USEC >``) says of this
    node's state: bus-off, error-passive (no acknowledgement), active again (the
    controller restarted); None for the rest (the controller's details, CAN_ERR_CRTL,
    travel in data socketcand drops)."""
    if error_class & CAN_ERR_BUSOFF:
        return can.BusState.ERROR
    if error_class & CAN_ERR_ACK:
        return can.BusState.PASSIVE
    if error_class & CAN_ERR_RESTARTED:
        return can.BusState.ACTIVE
    return None
