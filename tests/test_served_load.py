"""A served fleet on a busy machine: its driver wakes later than asked (the scheduler
gave the core to someone else), a step then carries every frame of a client's transmit
queue, and the frames still waiting in the client's backlog must go onto the bus in that
same step, not after the driver's next long sleep (which stalled a flash: the boards got
a tenth of the image, then nothing, and never answered its END)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.helpers import served_in_process
from ucom_tools.image.formats import load_image
from ucom_tools.ops.flash import flash
from ucom_tools.ops.flash_types import FlashRequest
from ucom_tools.ops.robot import ConnectSpec, open_robot
from ucom_tools.virtual.bus import clock as clock_mod
from ucom_tools.virtual.bus.simbus import TX_QUEUE
from ucom_tools.virtual.fleet import Fleet

REPO = Path(__file__).resolve().parent.parent

LATE_WAKE_S = 0.02
"""The driver's shortest sleep, made longer than the bus takes to carry a full transmit
queue (TX_QUEUE frames of at most 160 bits at 1 Mbit/s: about 5 ms)."""


@pytest.fixture
def late_waking_fleet(monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[Fleet, int]]:
    assert LATE_WAKE_S > 2 * TX_QUEUE * 160e-6
    monkeypatch.setattr(clock_mod, "STEP_MIN_S", LATE_WAKE_S)
    with served_in_process(str(REPO / "tests/data/armar3_can0.toml")) as served:
        yield served


def test_a_late_waking_driver_still_feeds_the_bus_a_whole_image(
        late_waking_fleet: tuple[Fleet, int]) -> None:
    fleet, port = late_waking_fleet
    robot = open_robot(ConnectSpec(interface="socketcand", host="127.0.0.1", port=port,
                                   channels=("CAN0",)))
    try:
        result = flash(robot, FlashRequest(load_image(REPO / "firmware_images/armar3.fl.S")))
    finally:
        robot.close()
    assert result.all_verified, [b.detail for b in result.failed]
    assert len(result.boards) == len(fleet.boards["CAN0"]) == 3


def test_a_served_round_trip_holds_the_drivers_step_latency_not_the_raw_mode_switch(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The echo is answered after the fleet's next step, as a frame's answer comes: a
    driver that wakes every 20 ms makes the round trip (and so every deadline's margin)
    that long; a prompt one keeps it far below the server's 20 ms switch to raw mode,
    which only the first echo waits for."""
    from ucom_tools.transport.socketcand import SocketcandBus
    from ucom_tools.virtual.serve.connection import RAWMODE_SETTLE_S

    def round_trip(port: int) -> float:
        bus = SocketcandBus("CAN0", "127.0.0.1", port)
        try:
            assert bus.round_trip_s is not None
            return bus.round_trip_s
        finally:
            bus.shutdown()

    with served_in_process(str(REPO / "tests/data/armar3_can0.toml")) as (_, port):
        prompt = min(round_trip(port) for _ in range(3))
    monkeypatch.setattr(clock_mod, "STEP_MIN_S", LATE_WAKE_S)
    with served_in_process(str(REPO / "tests/data/armar3_can0.toml")) as (_, port):
        late = round_trip(port)
    assert prompt < RAWMODE_SETTLE_S / 2
    assert late >= 0.9 * LATE_WAKE_S
