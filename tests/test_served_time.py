"""Frames from a served fleet carry the wall time at which they were on the simulated bus,
also right after the bus was idle (issue 17, 4): python-can's own socketcand client sends
an Init Request after the fleet stood idle for longer than its driver's longest wait, and
the answer's time stamp lies between the request's sending and the answer's arrival."""

from __future__ import annotations

import time

import can

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
    host, port = served_armar3
    bus = can.Bus(interface="socketcand", host=host, port=port, channel="CAN0")
    try:
        for round_ in range(2):
            time.sleep(IDLE_S)  # the scenario: a bus nobody used for a while
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
