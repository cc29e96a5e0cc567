"""The dispatcher: one reader per bus, subscribers by filter, unclaimed frames counted,
periodic frames on their deadlines (in virtual time, over the simulated bus)."""

from __future__ import annotations

from itertools import pairwise

import can

from tests.conftest import chain_topology
from ucom_tools.protocol.dispatch import Dispatcher
from ucom_tools.virtual.canbus import VirtualUcomBus
from ucom_tools.wire.ids import Function


class Recorder:
    """A second node on the bus that notes when frames arrive."""

    def __init__(self) -> None:
        self.frames: list[tuple[int, float]] = []

    def on_frame(self, arbitration_id: int, data: bytes, t_end: float) -> None:
        self.frames.append((arbitration_id, t_end))


def _setup():
    fleet = chain_topology(1)
    bus = VirtualUcomBus("CAN0", fleet=fleet)
    rec = Recorder()
    fleet.bus("CAN0").attach(rec)
    return fleet, bus, Dispatcher(bus, "CAN0"), rec


def test_periodic_frames_go_out_on_their_deadlines_while_someone_waits() -> None:
    _fleet, bus, d, rec = _setup()
    alive = can.Message(arbitration_id=Function.MCA_ALIVE << 6, data=b"", is_extended_id=False)
    task = d.every(0.010, lambda: [alive], "alive")
    d.pump(d.clock() + 0.1005)
    starts = [t for _, t in rec.frames]
    assert task.sent == 11 and task.late == 0 and len(starts) == 11
    gaps = {round(b - a) for a, b in pairwise(starts)}
    assert gaps == {10_000}  # us: every 10 ms exactly on the bus clock
    d.cancel(task)
    d.pump(d.clock() + 0.05)
    assert task.sent == 11
    bus.shutdown()


def test_a_reader_that_comes_late_counts_the_occurrences_it_missed() -> None:
    fleet, bus, d, _rec = _setup()
    msg = can.Message(arbitration_id=Function.MCA_ALIVE << 6, data=b"", is_extended_id=False)
    task = d.every(0.010, lambda: [msg], "alive")
    d.pump(d.clock())  # first one now
    fleet.bus("CAN0").run_until(fleet.clock.now + 35_000)  # nobody reads for 35 ms
    d.pump(d.clock())
    # due at 10 ms, sent at 35: the 10 and 20 ms occurrences were missed, this is the
    # 30 ms one
    assert (task.sent, task.late) == (2, 2)
    assert abs(task.max_delay - 0.025) < 1e-4  # (the first frame took 50 us)
    d.pump(d.clock() + 0.0051)  # and the schedule holds: next at 40 ms
    assert task.sent == 3
    bus.shutdown()


def test_frames_nobody_takes_are_counted_by_function() -> None:
    fleet, bus, d, _rec = _setup()
    taken: list[can.Message] = []
    d.subscribe(lambda m: m.arbitration_id >> 6 == Function.INIT_ACK, "init", taken.append)
    from ucom_tools.protocol.bootloader import BootloaderClient
    from ucom_tools.protocol.link import Link
    link = Link(bus, "CAN0", dispatcher=d)
    BootloaderClient(link).init_chain()
    assert taken  # the callback subscriber saw the init acks
    assert sum(d.unclaimed.values()) == 0  # the link took the rest
    second = VirtualUcomBus("CAN0", fleet=fleet)  # another PC on the bus, no subscribers
    other = Dispatcher(second, "CAN0 (nobody listens)")
    BootloaderClient(link).reset()
    other.pump(other.clock() + 0.01)
    assert other.unclaimed[Function.RESET] == 1 and other.unclaimed[Function.READY] == 1
    assert other.received == 2
    second.shutdown()
    bus.shutdown()
