"""The bus contract (protocol/buscontract.py): what a bus may offer the dispatcher beyond
can.BusABC, which of our buses keep which part of it, and that the dispatcher uses what a
bus has, looked up once, and does without what it has not."""

from __future__ import annotations

import dataclasses
import time

import can

from tests.conftest import chain_topology
from tests.test_frame_path import offline_bus
from ucom_tools.protocol import buscontract
from ucom_tools.protocol.buscontract import (
    AdvancesFrames,
    BatchingBus,
    Clocked,
    HandsOverReady,
    SendsData,
    SendsDataMany,
    VirtualTimeBus,
    extensions_of,
)
from ucom_tools.protocol.dispatch import Dispatcher
from ucom_tools.protocol.frames import DataFrame
from ucom_tools.virtual.canbus import VirtualUcomBus

PROTOCOLS = (buscontract.Clocked, buscontract.Stamped, buscontract.SendsData,
             buscontract.SendsDataMany, buscontract.BuildsMessages,
             buscontract.AdvancesFrames, buscontract.HandsOverReady)


class PlainBus(can.BusABC):
    """A bus with nothing but can.BusABC: frames queued by the test for recv."""

    def __init__(self) -> None:
        self.inbox: list[can.Message] = []
        self.sent: list[tuple[int, bytes]] = []
        super().__init__(channel="plain")

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.sent.append((msg.arbitration_id, bytes(msg.data)))

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return (self.inbox.pop(0) if self.inbox else None), False


class FastBus(PlainBus):
    """PlainBus with the contract's ways of handing frames over many at a time (each
    may say "not now": None); the calls counted."""

    def __init__(self, willing: bool = True) -> None:
        super().__init__()
        self.willing = willing
        self.calls: dict[str, int] = {"advance_frames": 0, "recv_ready_frames": 0,
                                      "message_of": 0}

    def _hand_over(self, name: str) -> list[can.Message | DataFrame] | None:
        self.calls[name] += 1
        if not self.willing:
            return None
        out: list[can.Message | DataFrame] = [
            (m.arbitration_id, bytes(m.data), m.timestamp) for m in self.inbox]
        self.inbox.clear()
        return out

    def advance_frames(self, timeout: float) -> list[can.Message | DataFrame] | None:
        return self._hand_over("advance_frames")

    def recv_ready_frames(self, limit: int = 1000) -> list[can.Message | DataFrame] | None:
        return self._hand_over("recv_ready_frames")

    def message_of(self, frame: DataFrame) -> can.Message:
        self.calls["message_of"] += 1
        ident, data, stamp = frame
        return can.Message(timestamp=stamp, arbitration_id=ident, data=data,
                           is_extended_id=False, channel="from message_of")


def frame(ident: int) -> can.Message:
    return can.Message(timestamp=1.5, arbitration_id=ident, data=b"\x01\x02",
                       is_extended_id=False)


def test_the_virtual_bus_and_the_socketcand_client_keep_their_contracts() -> None:
    fleet = chain_topology(1)
    bus = VirtualUcomBus("CAN0", fleet=fleet)
    try:
        assert isinstance(bus, VirtualTimeBus)
        assert not isinstance(bus, SendsDataMany) and not isinstance(bus, HandsOverReady)
        found = extensions_of(bus)
        assert found.clock() == bus.clock() and found.stamp() == bus.stamp()
        assert found.send_data_many is None and found.recv_ready_frames is None
        assert None not in (found.send_data, found.advance_frames, found.message_of)
    finally:
        bus.shutdown()
    with offline_bus() as client:
        assert isinstance(client, BatchingBus)
        assert not isinstance(client, Clocked) and not isinstance(client, AdvancesFrames)
        found = extensions_of(client)
        assert found.clock is time.monotonic and found.stamp is time.time
        assert None not in (found.send_data, found.send_data_many,
                            found.recv_ready_frames, found.message_of)


def test_a_plain_bus_has_none_of_it_and_a_value_that_is_not_callable_counts_as_none(
        ) -> None:
    bus = PlainBus()
    bus.clock = 5.0  # type: ignore[attr-defined]  (an attribute, not a method)
    found = extensions_of(bus)
    assert found.clock is time.monotonic and found.stamp is time.time
    assert [f.name for f in dataclasses.fields(found)
            if getattr(found, f.name) is None] == [
        "send_data", "send_data_many", "advance_frames", "recv_ready_frames", "message_of"]
    assert not any(isinstance(bus, p) for p in (SendsData, HandsOverReady, AdvancesFrames))
    bus.shutdown()


def test_the_contract_documented_is_the_contract_looked_up() -> None:
    """Every method of the protocols is a field of Extensions and has its entry in the
    module's documentation, and the other way round."""
    members = {name for p in PROTOCOLS for name in p.__dict__
               if not name.startswith("_") and callable(p.__dict__[name])}
    fields = {f.name for f in dataclasses.fields(buscontract.Extensions)}
    documented = {line.split("(")[0].strip("`") for line in
                  (buscontract.__doc__ or "").splitlines() if line.startswith("``")}
    assert members == fields == documented
    assert len(members) == 7


def test_the_dispatcher_reads_a_stretch_at_once_where_the_bus_advances() -> None:
    bus = FastBus()
    d = Dispatcher(bus, "CAN0")
    got: list[tuple[int, bytes, float]] = []
    d.subscribe(lambda msg: True, "all", on_data=lambda i, data, t: got.append((i, data, t)))
    tapped: list[str | None] = []
    d.taps.append(lambda msg: tapped.append(msg.channel))
    bus.inbox += [frame(0x101), frame(0x102)]
    assert d.pump(d.clock()) == 2
    assert bus.calls["advance_frames"] == 2 and not bus.inbox  # both, then none: done
    assert got == [(0x101, b"\x01\x02", 1.5), (0x102, b"\x01\x02", 1.5)]
    assert tapped == ["from message_of"] * 2  # the tap's messages are the bus's own
    bus.shutdown()


def test_the_dispatcher_drains_in_one_call_where_the_bus_hands_over_what_came() -> None:
    bus = FastBus()
    d = Dispatcher(bus, "CAN0")
    sub = d.subscribe(lambda msg: True, "queued")
    bus.inbox += [frame(0x201), frame(0x202), frame(0x203)]
    assert d.drain() == 3
    assert bus.calls["recv_ready_frames"] == 1 and bus.calls["message_of"] == 3
    assert [m.arbitration_id for m in sub.queue] == [0x201, 0x202, 0x203]
    bus.shutdown()


def test_a_bus_that_cannot_now_is_read_one_frame_at_a_time() -> None:
    for bus in (FastBus(willing=False), PlainBus()):
        d = Dispatcher(bus, "CAN0")
        sub = d.subscribe(lambda msg: True, "queued")
        bus.inbox += [frame(0x301), frame(0x302)]
        assert d.drain() == 2
        bus.inbox += [frame(0x303)]
        assert d.pump(d.clock()) == 1
        assert [m.arbitration_id for m in sub.queue] == [0x301, 0x302, 0x303]
        if isinstance(bus, FastBus):
            assert bus.calls["message_of"] == 0  # recv's own messages
        bus.shutdown()


def test_the_dispatcher_looks_the_methods_up_once() -> None:
    """A method the bus gets after its dispatcher was built is not used (the contract:
    a bus has its methods from its constructor on)."""
    bus = PlainBus()
    d = Dispatcher(bus, "CAN0")
    taken: list[tuple[int, bytes]] = []
    bus.send_data = lambda i, data, timeout=None: taken.append((i, data))  # type: ignore[attr-defined]
    d.send_data(0x123, b"\x07", 1.0)
    assert taken == [] and bus.sent == [(0x123, b"\x07")] and not d.batches
    bus.shutdown()
