"""The PC side's per-cycle shortcuts do what the plain paths do: SO maps unpacked by a
precompiled struct (:class:`~ucom_tools.ops.remote.values._SoFeed`) as ``values_of``,
``EdgeRef.raw``/``value`` of ints as the edge's spec, ``Link.send_frames`` as
``send_raw`` of each frame, and ``VirtualUcomBus.send_data`` as ``send``."""

from __future__ import annotations

import random
from decimal import Decimal

import can
import pytest

from tests.helpers import assert_send_data_refuses_as_send
from ucom_tools.edgelists.model import EdgeKind, EdgeSpec
from ucom_tools.errors import BusError, FrameError
from ucom_tools.ops.edges import EdgeRef
from ucom_tools.ops.remote.values import _SoFeed
from ucom_tools.protocol.link import Link
from ucom_tools.protocol.mca import ProcessImage, values_of
from ucom_tools.wire import mca


def record(width: int, signed: bool, exponent: int = 0) -> mca.EdgeRecord:
    bits = 8 * width
    lo, hi = (-(1 << bits - 1), (1 << bits - 1) - 1) if signed else (0, (1 << bits) - 1)
    return mca.EdgeRecord(width, signed, exponent, max(lo, -(1 << 31)), hi, "e", "")


def test_a_feed_decodes_as_values_of() -> None:
    rng = random.Random(5)
    for _ in range(500):
        records = [record(rng.choice((2, 4)), rng.random() < 0.5)
                   for _ in range(rng.randrange(1, 4))]
        feed = _SoFeed("CAN0", 1, ProcessImage(), [None] * len(records), records)
        size = sum(r.width for r in records)
        for n in (size, size - 1, size + 1, 0):
            frame = bytes(rng.randrange(256) for _ in range(max(0, n)))
            try:
                expected: list[int] | str = values_of(frame, records)
            except FrameError as err:
                expected = str(err)
            try:
                got: list[int] | str = feed.decode(frame)
            except FrameError as err:
                got = str(err)
            assert got == expected


def ref_of(spec: EdgeSpec) -> EdgeRef:
    return EdgeRef("CAN0", 1, "CAN0 board 1", "P", "U", "g", mca.Kind.CI, 0, spec)


@pytest.mark.parametrize("exponent", [-3, -1, 0, 2])
def test_raw_and_value_of_ints_are_the_specs(exponent: int) -> None:
    spec = EdgeSpec(EdgeKind.CI, "x", width=2, signed=True, exponent=exponent,
                    minimum=-1000, maximum=1000, unit="", default=0)
    ref = ref_of(spec)
    for value in [*range(-1002, 1003, 7), True, False, 0, 1000, -1000, 10**6]:
        try:
            expected: int | str = spec.raw(Decimal(value) if not isinstance(value, bool)
                                           else value)
        except ValueError as err:
            expected = f"P/U: {err}"
        try:
            got: int | str = ref.raw(value)
        except Exception as err:  # InputError naming the edge
            got = str(err)
        assert got == expected, value
    for raw in range(-1000, 1001, 13):
        v = spec.value(raw)
        assert ref.value(raw) == (int(raw) * 10 ** exponent if exponent >= 0 else v)
        assert type(ref.value(raw)) is (int if exponent >= 0 else Decimal)


class _Noting(can.BusABC):
    """Takes standard frames by send_data; refuses one identifier (not a full queue)."""

    def __init__(self) -> None:
        self.sent: list[tuple[int, bytes, float | None]] = []
        self.t = 0.0
        super().__init__(channel="t")

    def clock(self) -> float:
        return self.t

    def send_data(self, ident: int, data: bytes, timeout: float | None = None) -> None:
        if ident == 0x7FF:
            raise can.CanOperationError("refused")
        self.sent.append((ident, bytes(data), timeout))

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        raise AssertionError("send_data expected")

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return None, False


def test_send_frames_is_send_raw_of_each() -> None:
    rng = random.Random(7)
    frames = [(rng.randrange(0x7FF), bytes(rng.randrange(9))) for _ in range(40)]
    results = []
    for batched in (True, False):
        bus = _Noting()
        link = Link(bus, "t", margin=0.01)
        for k in range(0, len(frames), 4):
            bus.t = k * 1e-5
            if batched:
                link.send_frames(frames[k:k + 4])
            else:
                for ident, data in frames[k:k + 4]:
                    link.send_raw(ident, data)
        refused = [(1, b""), (0x7FF, b"\x01"), (2, b"")]  # the bus refuses the second
        with pytest.raises(BusError, match=r"^t: cannot send: refused$"):
            if batched:
                link.send_frames(refused)
            else:
                for ident, data in refused:
                    link.send_raw(ident, data)
        results.append((bus.sent, link._horizon, link.frames_sent, link.dispatcher.sent,
                        link.dispatcher.bits))
        bus.shutdown()
    assert results[0] == results[1]
    assert results[0][0][-1][:2] == (1, b"")  # the frame before it went, none after


def test_virtual_send_data_is_send(tmp_path) -> None:
    from ucom_tools.config.topology import load
    from ucom_tools.virtual.canbus import VirtualUcomBus
    from ucom_tools.virtual.fleet import Fleet
    fleet = Fleet(load("armar3"))
    bus = VirtualUcomBus("CAN0", fleet=fleet)
    try:
        assert_send_data_refuses_as_send(bus)
    finally:
        bus.shutdown()
