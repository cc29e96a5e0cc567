"""The bus model: arbitration order and bit-exact time accounting."""

from __future__ import annotations

import heapq
import random
from collections.abc import Callable

from ucom_tools.virtual.bus.clock import FleetClock
from ucom_tools.virtual.bus.simbus import SimBus
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


def _events_run(seed: int, at: Callable[[float, int, Callable[[float], None]], None],
                run: Callable[[], None]) -> list[tuple[float, int, int]]:
    """Schedule 1,000 events (many at equal times and tiers), each of which may schedule
    another while it runs (some in the past: at once), through ``at(t, tier, fn)``; run
    them with ``run()``; the (time, tier, number) of each as it ran."""
    rng = random.Random(seed)
    ran: list[tuple[float, int, int]] = []
    count = 0

    def event(t: float, tier: int, number: int) -> None:
        ran.append((t, tier, number))
        if count < 2500 and rng.random() < 0.4:
            schedule(t + rng.choice([-5.0, 0.0, 0.0, 1.0, 2.5]), rng.randrange(2))

    def schedule(t: float, tier: int) -> None:
        nonlocal count
        number = count
        count += 1
        at(t, tier, lambda when: event(when, tier, number))

    for _ in range(1000):
        schedule(float(rng.randrange(50)), rng.randrange(2))
    run()
    return ran


def test_the_clock_runs_events_by_time_then_tier_then_order_of_scheduling() -> None:
    """Compiled, the clock keeps its events in a heap of its own (FleetClock._push/_pop),
    from source in heapq (make test runs both): either way in the order of a reference
    queue of (max(t, now), tier, sequence) tuples."""
    clock = FleetClock()
    got = _events_run(17, lambda t, tier, fn: clock.at(t, fn, tier=tier),
                      lambda: clock.run_until(1e9))
    queue: list[tuple[float, int, int, Callable[[float], None]]] = []
    now, seq = 0.0, 0

    def at(t: float, tier: int, fn: Callable[[float], None]) -> None:
        nonlocal seq
        heapq.heappush(queue, (max(t, now), tier, seq, fn))
        seq += 1

    def run() -> None:
        nonlocal now
        while queue:
            now, _tier, _seq, fn = heapq.heappop(queue)
            fn(now)

    want = _events_run(17, at, run)
    assert len(want) > 1500 and len({(t, tier) for t, tier, _ in want}) < len(want) / 4
    assert got == want
