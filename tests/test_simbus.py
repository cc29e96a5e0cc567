"""The bus model: arbitration order and bit-exact time accounting."""

from __future__ import annotations

from ucom_tools.virtual.simbus import SimBus
from ucom_tools.wire.canbits import frame_bits


class Recorder:
    def __init__(self) -> None:
        self.seen: list[tuple[int, float]] = []

    def on_frame(self, arbitration_id: int, data: bytes, t_end: float) -> None:
        self.seen.append((arbitration_id, t_end))


def test_pending_frames_go_out_in_arbitration_order() -> None:
    bus = SimBus("CAN0", 1_000_000)
    rx = Recorder()
    bus.attach(rx)
    a, b, c = object(), object(), object()
    bus.send(a, 10.0, 0x300, b"\x01")
    bus.send(b, 10.0, 0x100, b"\x02")
    bus.send(c, 10.0, 0x200, b"\x03")
    bus.run_until(10_000)
    assert [i for i, _ in rx.seen] == [0x100, 0x200, 0x300]


def test_a_frame_waits_for_the_bus_and_time_follows_the_bit_count() -> None:
    bus = SimBus("CAN0", 500_000)
    rx = Recorder()
    bus.attach(rx)
    first = frame_bits(0x400, b"\x00" * 8)
    second = frame_bits(0x001, b"")
    bus.send(object(), 0.0, 0x400, bytes(8))
    bus.send(object(), 1.0, 0x001, b"")  # higher priority, but the bus is busy
    bus.run_until(1e6)
    (id1, t1), (id2, t2) = rx.seen
    assert (id1, id2) == (0x400, 0x001)
    assert t1 == first * 2.0  # 2 us per bit at 500 kbit/s
    assert t2 == t1 + second * 2.0
    assert bus.stats.frames == 2
    assert bus.stats.bits == first + second
    assert bus.stats.busy_us == (first + second) * 2.0
    assert bus.stats.payload_bits == 64
    assert 0 < bus.stats.load(1e6) < 0.001


def test_timers_and_idle_time() -> None:
    bus = SimBus("CAN0", 1_000_000)
    fired: list[float] = []
    bus.at(500.0, fired.append)
    bus.run_until(400.0)
    assert fired == [] and bus.now == 400.0
    bus.run_until(600.0)
    assert fired == [500.0]


def test_identical_identifiers_from_two_nodes_are_counted_as_clashes() -> None:
    bus = SimBus("CAN0", 1_000_000)
    bus.send(object(), 0.0, 0x0C1, b"\x01")
    bus.send(object(), 0.0, 0x0C1, b"\x02")
    bus.run_until(1000.0)
    assert bus.stats.clashes == 1
