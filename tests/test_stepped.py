"""A stepped conversation beside the loop (:mod:`ucom_tools.protocol.stepped`): a worker
whose step's budget is spent hands control back at its next wait, although frames wait
for it; one that computes past its budget is busy until it comes to a wait.

Over a real :class:`~ucom_tools.protocol.dispatch.Dispatcher` on python-can's virtual bus,
the frames delivered as the loop's drain delivers them; the budget's clock is a fake one
the worker moves on, so that "the budget is spent" happens where the test says."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import can
import pytest

from ucom_tools.protocol import stepped as stepped_module
from ucom_tools.protocol.dispatch import Dispatcher
from ucom_tools.protocol.stepped import Stepped

FRAMES = 5
ANSWER_ID = 0x123


class FakeClock:
    """``time.monotonic`` for the stepped module: moves only when told."""

    def __init__(self) -> None:
        self.now = 1000.0

    def monotonic(self) -> float:
        return self.now


@pytest.fixture
def dispatcher() -> Iterator[Dispatcher]:
    bus = can.Bus(interface="virtual", channel="test-stepped", receive_own_messages=False)
    d = Dispatcher(bus)
    try:
        yield d
    finally:
        bus.shutdown()


def frames() -> list[can.Message]:
    return [can.Message(arbitration_id=ANSWER_ID, data=bytes([i]), is_extended_id=False)
            for i in range(FRAMES)]


def collector(d: Dispatcher, clock: FakeClock | None, got: list[int]) -> Stepped:
    """A conversation that waits for :data:`FRAMES` answers; each it takes costs it ten
    seconds of ``clock`` (more than the steps' budget: spent at once)."""
    sub = d.subscribe(lambda m: m.arbitration_id == ANSWER_ID, "collector")

    def work() -> int:
        while len(got) < FRAMES:
            msg = d.wait(sub, time.monotonic() + 30.0)
            assert msg is not None
            got.append(msg.data[0])
            if clock is not None:
                clock.now += 10.0
        return len(got)

    return Stepped(work, "test-collector")


def test_a_spent_budget_hands_control_back_at_the_next_wait(
        dispatcher: Dispatcher, monkeypatch: pytest.MonkeyPatch) -> None:
    clock = FakeClock()
    monkeypatch.setattr(stepped_module, "time", clock)
    got: list[int] = []
    s = collector(dispatcher, clock, got)
    assert s.step(5.0)  # it starts and waits: nothing there yet
    assert got == [] and not s.done
    dispatcher.dispatch_all(frames())  # the loop's drain: all five at once
    for n in range(1, FRAMES + 1):
        assert s.step(5.0)  # each step: one frame, then its budget is spent
        assert got == list(range(n)), f"step {n}: {got}"
        assert not s.busy()
    assert s.done and s.result == FRAMES


def test_without_a_budget_one_step_takes_every_frame_there(
        dispatcher: Dispatcher, monkeypatch: pytest.MonkeyPatch) -> None:
    clock = FakeClock()
    monkeypatch.setattr(stepped_module, "time", clock)
    got: list[int] = []
    s = collector(dispatcher, clock, got)
    s.step(None)
    dispatcher.dispatch_all(frames())
    s.step(None)  # virtual time: the loop waits for the worker, whatever it costs
    assert got == list(range(FRAMES)) and s.done


def test_a_worker_computing_past_its_budget_is_busy_until_its_next_wait(
        dispatcher: Dispatcher) -> None:
    go_on = threading.Event()
    computing = threading.Event()
    sub = dispatcher.subscribe(lambda m: m.arbitration_id == ANSWER_ID, "busy")

    def work() -> can.Message | None:
        computing.set()
        go_on.wait(30.0)  # its computation: longer than any budget
        return dispatcher.wait(sub, time.monotonic() + 30.0)

    s = Stepped(work, "test-busy")
    assert s.step(0.0)
    assert computing.wait(30.0)
    assert s.busy()
    assert not s.step(0.0)  # still computing: nothing handed over
    go_on.set()
    deadline = time.monotonic() + 30.0
    while s.busy():  # it comes to its wait and hands control back
        assert time.monotonic() < deadline, "the worker never came to its wait"
    assert not s.done
    dispatcher.dispatch_all(frames()[:1])
    s.step(None)
    assert s.done and isinstance(s.result, can.Message)
