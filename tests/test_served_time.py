"""Frames from a served fleet carry the wall time at which they were on the simulated bus,
also right after the bus was idle (issue 17, 4): python-can's own socketcand client sends
an Init Request after the fleet stood idle for longer than its driver's longest wait, and
the answer's time stamp lies between the request's sending and the answer's arrival."""

from __future__ import annotations

import time

import can
import pytest

from tests.helpers import served_in_process
from ucom_tools.virtual.board.ucom import VirtualBoard
from ucom_tools.wire import messages
from ucom_tools.wire import requests as rq
from ucom_tools.wire.codes import InitOp
from ucom_tools.wire.ids import ALL

LOCAL = "127.0.0.1"
IDLE_S = 0.8
"""Longer than the paced driver's longest wait (0.5 s): its clock stood still meanwhile."""
TOLERANCE_S = 0.001


def test_an_answer_after_an_idle_bus_is_stamped_with_the_wall_time(
        served_armar3: tuple[str, int]) -> None:
    _answers_stamped_with_the_wall_time(*served_armar3, idle_s=IDLE_S)


def test_a_fleet_slow_to_build_still_stamps_with_the_wall_time(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The fleet's time starts when its driver does, not when it began to build its
    boards: on a busy machine that took milliseconds, and every frame was stamped that
    much before it was on the bus (a clean-clone CI run: an answer 1.7 ms before its
    request was sent)."""
    built = VirtualBoard.power_on

    def slowly(board: VirtualBoard, t: float) -> None:
        time.sleep(0.003)  # the scenario: a machine busy with something else
        built(board, t)

    monkeypatch.setattr(VirtualBoard, "power_on", slowly)
    with served_in_process("armar3") as (_, port):
        _answers_stamped_with_the_wall_time(LOCAL, port, idle_s=0.0)


def _answers_stamped_with_the_wall_time(host: str, port: int, *, idle_s: float) -> None:
    """Twice, after ``idle_s``: python-can's client sends an Init Request, and the first
    answer's stamp lies between the request's sending and the answer's arrival."""
    bus = can.Bus(interface="socketcand", host=host, port=port, channel="CAN0")
    try:
        for round_ in range(2):
            time.sleep(idle_s)  # the scenario: a bus nobody used for a while
            ident, data = messages.encode(rq.InitRequest(InitOp.BEGIN), ALL)
            request = can.Message(arbitration_id=ident, data=data, is_extended_id=False)
            sent = time.time()
            bus.send(request)
            deadline = time.monotonic() + 5
            answer = None
            while time.monotonic() < deadline:
                msg = bus.recv(timeout=1)
                if msg is not None and msg.arbitration_id != request.arbitration_id:
                    answer = msg
                    arrived = time.time()
                    break
            assert answer is not None, "no answer"
            assert sent - TOLERANCE_S <= answer.timestamp <= arrived + TOLERANCE_S, \
                (round_, answer.timestamp - sent, arrived - answer.timestamp)
    finally:
        bus.shutdown()
