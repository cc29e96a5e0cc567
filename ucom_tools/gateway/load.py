"""The CANopen bus load of a group of gateway nodes' PDOs and the SYNC, counted as
``remote`` counts a UCoM bus's (:mod:`ucom_tools.wire.canbits`): what ``gateway canopen``
says at its start (the SYNC rate each bus's PDOs fit) and warns about when a master's SYNC
rate, once measured, asks more of the bus than it has."""

from __future__ import annotations

from collections.abc import Iterable
from functools import partial

from canopen import ObjectDictionary

from ucom_tools.gateway.pdo import compile_pdos, find
from ucom_tools.gateway.slave import SlaveNode
from ucom_tools.protocol.plan import Load
from ucom_tools.wire.canbits import unstuffed_bits, worst_frame_bits


def pdo_load(nodes: Iterable[ObjectDictionary | SlaveNode], rate_hz: float, *,
             sync_counter: bool = False) -> Load:
    """What a group of nodes' enabled PDOs and the SYNC put on their CANopen bus at
    ``rate_hz`` SYNCs a second, counted as ``remote`` counts a UCoM bus's load (per
    second; ``worst_bits_per_s / bitrate`` is the share of the bus with every stuff bit
    a frame can need): the SYNC (1 byte with ``sync_counter``), each synchronous TPDO
    every n-th SYNC (type n; type 0 every SYNC), each RPDO and each event-driven TPDO
    once a SYNC (a master that writes every SYNC, values that change every SYNC).
    Heartbeats, EMCYs and SDO are not counted.  Each node's PDOs as its dictionary
    stores them, or a :class:`SlaveNode`'s as its master has configured them."""
    frames: list[tuple[int, float]] = [(1 if sync_counter else 0, 1.0)]  # (bytes, a SYNC)
    for n in nodes:
        od, read = (n.od, n.read) if isinstance(n, SlaveNode) else (n, partial(_stored, n))
        tpdos, rpdos = compile_pdos(od, read, lambda i, sub, size: {sub: bytes(size)},
                                    int(getattr(od, "node_id", 0) or 0))
        for t in tpdos:
            every = t.trans_type if t.trans_type <= 240 else 1
            frames.append((sum(e.bits for e in t.entries) // 8, 1.0 / max(1, every)))
        frames += [(r.length, 1.0) for r in rpdos]
    return Load(rate_hz * sum(k for _, k in frames),
                rate_hz * sum(k * unstuffed_bits(size) for size, k in frames),
                rate_hz * sum(k * worst_frame_bits(size) for size, k in frames))


CANOPEN_BITRATE = 1_000_000
"""The bit rate the gateway's warnings assume of a CANopen bus (python-can does not say a
bus's bit rate; ros2_canopen's and most robots' CANopen buses run at 1 Mbit/s)."""
WARN_SHARE = 1.0
"""A configuration whose worst case needs more than this share of the bus is warned of."""


def fitting_rate(nodes: Iterable[ObjectDictionary | SlaveNode],
                 bitrate: int = CANOPEN_BITRATE) -> float:
    """The highest SYNC rate [Hz] at which the nodes' PDOs fit the bus, every stuff bit
    counted (``inf``: none is configured)."""
    per_sync = pdo_load(nodes, 1.0).worst_bits_per_s
    return float("inf") if per_sync <= 0 else bitrate / per_sync


def _stored(od: ObjectDictionary, index: int, subindex: int) -> int:
    var = find(od, index, subindex)
    return int((var.value if var.value is not None else var.default) or 0)


__all__ = ["CANOPEN_BITRATE", "WARN_SHARE", "fitting_rate", "pdo_load"]
