"""``ucom_tools.gateway.bridge.pdo_load``: the CANopen bus load of a group of gateway
nodes' PDOs and the SYNC at a SYNC rate, for the warning at start when the PDO
configuration cannot fit the rate the master uses.  Expected figures are computed here
from CAN's frame format (a standard data frame of n bytes: 47 + 8n bits, Tab. B.2; its
34 + 8n bits from SOF to the CRC can need a stuff bit per 4 after the first 5), not from
the product's helpers."""

from __future__ import annotations

import uuid
from collections.abc import Iterator

import can
import canopen
import pytest

from ucom_tools.gateway import dictionary, joints
from ucom_tools.gateway.codes import NmtState
from ucom_tools.gateway.load import pdo_load
from ucom_tools.gateway.node import NodeRuntime

BITRATE = 1_000_000


def nominal(n: int) -> int:
    return 47 + 8 * n


def worst(n: int) -> int:
    return 47 + 8 * n + (34 + 8 * n - 1) // 4


# the gateway's default mapping (dictionary.py, as ros2_canopen's examples map a drive):
# TPDO1 0x6041 + 0x6061 (3 bytes), TPDO2 0x6064 + 0x606C (8), both every SYNC;
# RPDO1 0x6040 + 0x6060 (3), RPDO2 0x607A + 0x60FF (8); PDO 3 and 4 disabled
NODE_BYTES = (3, 8, 3, 8)


@pytest.fixture(scope="module")
def can0() -> list[canopen.ObjectDictionary]:
    """The dictionaries of ARMAR-III's CAN0 joints (nodes 2-8)."""
    robot = joints.load("armar3")
    return [dictionary.to_canopen(dictionary.build(j)) for j in robot.joints
            if j.bus == "CAN0"]


def test_one_node_at_100_hz(can0: list[canopen.ObjectDictionary]) -> None:
    load = pdo_load(can0[:1], 100.0)
    sizes = (0, *NODE_BYTES)  # the SYNC carries no counter
    assert load.frames_per_s == pytest.approx(100 * 5)
    assert load.nominal_bits_per_s == pytest.approx(100 * sum(nominal(n) for n in sizes))
    assert load.worst_bits_per_s == pytest.approx(100 * sum(worst(n) for n in sizes))


def test_a_bus_of_seven_joints_fits_250_hz_but_not_1_khz(
        can0: list[canopen.ObjectDictionary]) -> None:
    assert len(can0) == 7
    per_sync = worst(0) + 7 * sum(worst(n) for n in NODE_BYTES)
    for rate in (100.0, 250.0, 1000.0):
        load = pdo_load(can0, rate)
        assert load.frames_per_s == pytest.approx(rate * (1 + 7 * 4))
        assert load.worst_bits_per_s == pytest.approx(rate * per_sync)
    assert pdo_load(can0, 250.0).worst_bits_per_s < BITRATE < \
        pdo_load(can0, 1000.0).worst_bits_per_s


def test_a_sync_counter_adds_a_byte_to_each_sync(can0: list[canopen.ObjectDictionary]
                                                 ) -> None:
    without, with_counter = pdo_load(can0[:1], 50.0), pdo_load(can0[:1], 50.0,
                                                                sync_counter=True)
    assert with_counter.frames_per_s == without.frames_per_s
    assert with_counter.nominal_bits_per_s - without.nominal_bits_per_s == \
        pytest.approx(50 * 8)


def test_no_nodes_is_the_sync_alone() -> None:
    load = pdo_load([], 200.0)
    assert load.frames_per_s == pytest.approx(200)
    assert load.worst_bits_per_s == pytest.approx(200 * worst(0))


# ------------------------------------------------------------ as the master configured it
@pytest.fixture
def served(can0: list[canopen.ObjectDictionary]
           ) -> Iterator[tuple[NodeRuntime, canopen.RemoteNode]]:
    """Node 2 in the node runtime, and canopen's master side of it, on a virtual bus."""
    channel = f"gw-load-{uuid.uuid4().hex}"
    node_bus = can.Bus(interface="virtual", channel=channel)
    net = canopen.Network(can.Bus(interface="virtual", channel=channel))
    net.connect()
    od = dictionary.to_canopen(dictionary.build(joints.load("armar3").joints[0]))
    runtime = NodeRuntime(node_bus, {2: od})
    try:
        runtime.start()
        yield runtime, net.add_node(2, dictionary.to_canopen(
            dictionary.build(joints.load("armar3").joints[0])))
    finally:
        runtime.close()
        net.disconnect()
        node_bus.shutdown()


def test_a_slave_node_counts_its_pdos_as_the_master_set_them(
        served: tuple[NodeRuntime, canopen.RemoteNode]) -> None:
    runtime, remote = served
    node = runtime.node(2)
    assert node.state is NmtState.PRE_OPERATIONAL
    before = pdo_load([node], 100.0)
    assert before.frames_per_s == pytest.approx(100 * 5)
    # TPDO2 every 4th SYNC, RPDO1 disabled (CiA 301: invalid first, then the new type)
    cob = remote.sdo.upload(0x1801, 1)
    invalid = int.from_bytes(cob, "little") | 1 << 31
    remote.sdo.download(0x1801, 1, invalid.to_bytes(4, "little"))
    remote.sdo.download(0x1801, 2, bytes([4]))
    remote.sdo.download(0x1801, 1, cob)
    rpdo1 = int.from_bytes(remote.sdo.upload(0x1400, 1), "little")
    remote.sdo.download(0x1400, 1, (rpdo1 | 1 << 31).to_bytes(4, "little"))
    # (the SDO server stored each value before it answered: read from the node's store)
    after = pdo_load([node], 100.0)
    assert after.frames_per_s == pytest.approx(100 * (1 + 1 + 0.25 + 1))
    assert after.nominal_bits_per_s == pytest.approx(
        100 * (nominal(0) + nominal(3) + nominal(8) / 4 + nominal(8)))
    # the dictionary itself still holds the EDS's configuration
    assert pdo_load([node.od], 100.0) == before
