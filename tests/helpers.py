"""Small builders shared by the tests (images and transfers, ARMAR-III's head as a robot
of its own, a bus that holds answers back), a check that a bus's ``send_data`` shortcut
refuses what ``send`` refuses, and ending the processes they start."""

from __future__ import annotations

import contextlib
import random
import signal
import subprocess
import threading
from collections.abc import Callable, Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import can
import pytest

from ucom_tools.protocol.programmer import Programmer, TransferResult
from ucom_tools.virtual.bus.loss import LossyBus
from ucom_tools.wire.codes import Space, StatusOp, Target
from ucom_tools.wire.ids import ALL, Address
from ucom_tools.wire.transfer import TransferPlan

WHEN = datetime(2026, 11, 22, 12, 0, tzinfo=UTC)
ROOT = Path(__file__).resolve().parent.parent


class HeldBack(LossyBus):
    """A virtual bus that holds each received frame ``hold(msg)`` picks back for ``delay``
    seconds of bus time (a network's delay spike, a busy fleet), every other frame as it
    comes.  (:class:`LossyBus` with no loss gives the wrapper: the inner bus's clock,
    stamps, sending and shutdown.)"""

    def __init__(self, inner: can.BusABC, hold: Callable[[can.Message], bool],
                 delay: float) -> None:
        super().__init__(inner)
        self.hold, self.delay = hold, delay
        self.held: list[tuple[float, can.Message]] = []

    def _due(self, t: float) -> bool:
        return bool(self.held) and self.held[0][0] <= t

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        end = self.clock() + (timeout or 0.0)
        while True:
            if self._due(self.clock()):
                return self.held.pop(0)[1], False
            until = min(end, self.held[0][0]) if self.held else end
            msg, _ = super()._recv_internal(max(0.0, until - self.clock()))
            if msg is None:
                if self.clock() >= end and not self._due(end):
                    return None, False
                continue
            if self.hold(msg):
                self.held.append((self.clock() + self.delay, msg))
                continue
            return msg, False


@contextlib.contextmanager
def served_in_process(topology: str, state: Path | None = None,
                      ) -> Iterator[tuple[Any, int]]:
    """``topology`` (with the flash in ``state``), paced and served over socketcand from
    this process on 127.0.0.1: (the fleet, its port); closed afterwards."""
    from ucom_tools.virtual.fleet import Fleet
    from ucom_tools.virtual.serve.socketcand import FleetServer
    fleet = Fleet.load(topology, state_dir=state, realtime=True)
    server = FleetServer(fleet, "127.0.0.1", 0)
    thread = threading.Thread(target=server.serve_forever, args=(0.05,), daemon=True)
    thread.start()
    try:
        yield fleet, server.address[1]
    finally:
        server.shutdown()
        server.server_close()
        thread.join(10)
        fleet.close()


def head_topology(where: Path) -> Path:
    """ARMAR-III's CAN0 (neck and head: 3 boards) as a robot of its own, with its trees:
    a topology file in ``where``."""
    text = (ROOT / "ucom_tools/config/topologies/armar3.toml").read_text()
    head = text[:text.index("[[bus]]", text.index("[[bus]]") + 1)]
    head = head.replace('tree = "attribute_trees/', f'tree = "{ROOT}/attribute_trees/')
    path = where / "head.toml"
    path.write_text(head)
    return path


def image_words(p_words: int, x_words: int = 0, seed: int = 1) -> dict[tuple[Space, int], int]:
    rnd = random.Random(seed)
    words = {(Space.P, a): rnd.getrandbits(16) for a in range(0x0004, 0x0004 + p_words)}
    words.update({(Space.X, a): rnd.getrandbits(16) for a in range(0x1000, 0x1000 + x_words)})
    return words


def plan_of(words: dict[tuple[Space, int], int], *, name: str = "test.S",
            target: Target = Target.FLASH) -> TransferPlan:
    return TransferPlan.build(words, entry=4, name=name, when=WHEN, target=target)


def program(host, plan: TransferPlan, boards: list[Address] | None = None) -> TransferResult:
    """Init, ProgEnable and transfer over the host connection (the real code path)."""
    init = host.client.init_chain()
    targets = boards or [Address(0, n) for n in init.numbers]
    for a in targets:
        host.client.set_status(a, StatusOp.PROG_ENABLE, 1)
    return Programmer(host.link).transfer(plan, targets)


def enable_all(host) -> None:
    host.client.set_status(ALL, StatusOp.PROG_ENABLE, 1)


def terminate(proc: subprocess.Popen[str], timeout: float = 15.0) -> None:
    """End a ``ucom`` process as a user's SIGTERM does, and kill it where it does not end
    within ``timeout`` seconds (a test must not leave it behind)."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def assert_send_data_refuses_as_send(bus: Any) -> None:
    """``bus.send_data(id, data)`` (a bus's shortcut for a standard data frame) refuses a
    bad identifier or an over-long payload with the same error text as ``bus.send``."""
    for ident, data in [(0x800, b""), (-1, b"\x01"), (0x123, bytes(9))]:
        with pytest.raises(can.CanOperationError) as fast:
            bus.send_data(ident, data)
        with pytest.raises(can.CanOperationError) as plain:
            bus.send(can.Message(arbitration_id=ident, data=data, is_extended_id=False,
                                 check=False))
        assert str(fast.value) == str(plain.value)
