"""A CANopen master for tests/test_gateway_canopen.py, run in a process of its own
(``python -c TEXT HOST PORT CHANNEL``): canopen's ``Network``, ``RemoteNode`` and
``BaseNode402`` as they are, over python-can's own socketcand interface.

It reads one JSON command a line on standard input (``{"op": NAME, "args": {...}}``) and
answers each with one JSON line: ``{"ok": RESULT}``, ``{"abort": CODE}`` for an SDO abort,
or ``{"error": TEXT}``.  The first line it writes is ``{"ok": "ready"}``.  Every wait has
the deadline the command gives.
"""

import json
import struct
import sys
import time
import traceback

import canopen
from canopen.profiles.p402 import BaseNode402
from canopen.sdo import SdoAbortedError

HOST, PORT, CHANNEL = sys.argv[1], int(sys.argv[2]), sys.argv[3]
SDO_TIMEOUT_S = 1.0
"""canopen's default is 0.3 s: the gateway answers in milliseconds, but on a machine as
busy as a CI runner its process (niceness 10) now and then waits longer than that."""
net = canopen.Network()
net.connect(interface="socketcand", host=HOST, port=PORT, channel=CHANNEL)
nodes: dict[int, BaseNode402] = {}
emcys: list[tuple[int, int, float]] = []
heartbeat_task = None


def key(k):
    """An object as the test names it: an index, [index, sub-index] or a name (canopen's
    look-up by ParameterName in the EDS)."""
    return tuple(k) if isinstance(k, list) else k


def sdo_var(node, k):
    k = key(k)
    return node.sdo[k[0]][k[1]] if isinstance(k, tuple) else node.sdo[k]


def add(node_id, eds):
    node = BaseNode402(node_id, eds)
    node.sdo.RESPONSE_TIMEOUT = SDO_TIMEOUT_S
    net.add_node(node)
    node.emcy.add_callback(lambda e, n=node_id: emcys.append((n, e.code, e.timestamp)))
    nodes[node_id] = node
    return node_id


def heartbeat(node_id, within):
    return nodes[node_id].nmt.wait_for_heartbeat(within)


def setup(node_id):
    nodes[node_id].setup_402_state_machine()
    return True


def nmt(node_id, state):
    nodes[node_id].nmt.state = state
    return state


def sync(period):
    """The master's SYNC every ``period`` s (canopen's producer, started once); 0 stops
    it."""
    net.sync.stop()
    if period:
        net.sync.start(period)
    return period


def produce_heartbeat(period):
    """The master's own heartbeat (node 1, OPERATIONAL) every ``period`` s; 0 stops it."""
    global heartbeat_task
    if heartbeat_task is not None:
        heartbeat_task.stop()
        heartbeat_task = None
    if period:
        heartbeat_task = net.send_periodic(0x701, b"\x05", period)
    return period


def state(node_id, target, within):
    """BaseNode402's state setter, tried again (a loaded machine may answer a step later
    than its 0.4 s) until ``within``: [the state, the attempts]."""
    begin = time.monotonic()
    attempts = 0
    while True:
        attempts += 1
        try:
            nodes[node_id].state = target
            return [nodes[node_id].state, attempts]
        except RuntimeError:
            if time.monotonic() - begin > within:
                raise


def op_mode(node_id, mode):
    nodes[node_id].op_mode = mode
    return nodes[node_id].op_mode


def read(node_id, k):
    value = sdo_var(nodes[node_id], k).raw
    return value.decode() if isinstance(value, bytes) else value


def write(node_id, k, value):
    sdo_var(nodes[node_id], k).raw = value
    return value


def controlword(node_id, value):
    nodes[node_id].controlword = value
    return value


def statusword(node_id):
    return nodes[node_id].statusword


def wait_status(node_id, mask, value, within):
    """Poll 0x6041 (as BaseNode402 reads it: its TPDO, else SDO) until ``sw & mask ==
    value``: [seconds it took, the statusword]."""
    start = time.monotonic()
    while True:
        sw = nodes[node_id].statusword
        if sw & mask == value:
            return [time.monotonic() - start, sw]
        if time.monotonic() - start > within:
            raise TimeoutError(f"node {node_id}: statusword 0x{sw:04X}, not "
                               f"0x{value:04X} under mask 0x{mask:04X} within {within} s")
        time.sleep(0.005)  # polling interval


def tpdo(node_id, number, within):
    """The next reception of a TPDO: {object name: value} and its data length."""
    pdo = nodes[node_id].tpdo[number]
    if pdo.wait_for_reception(within) is None:
        raise TimeoutError(f"node {node_id}: TPDO{number} did not arrive within {within} s")
    return {"values": {v.name: v.raw for v in pdo.map}, "length": len(pdo.data)}


def read_pdos(node_id):
    """The node's PDO configuration read again by SDO (after a remap)."""
    nodes[node_id].tpdo.read()
    nodes[node_id].rpdo.read()
    return [[p.cob_id, p.enabled, [v.name for v in p.map]]
            for p in nodes[node_id].tpdo.values()]


def rpdo(node_id, number, values):
    pdo = nodes[node_id].rpdo[number]
    for name, value in values.items():
        pdo[name].raw = value
    pdo.transmit()
    return True


def csp_ramp(node_id, start, step, count, period, within):
    """Cyclic synchronous position as a master drives it, on its own clock (the periodic
    SYNC stopped first): each period 0x607A by RPDO2, then the SYNC.  Before each, the
    latest TPDO2 (0x6064 of the SYNC before): [[target of that SYNC, position], ...]."""
    net.sync.stop()
    node = nodes[node_id]
    position = node.tpdo[2]["Position actual value"]
    out = []
    target = None
    due = begin = time.monotonic()
    for k in range(count + 1):
        if time.monotonic() - begin > within:
            raise TimeoutError(f"{k} of {count} periods within {within} s")
        if target is not None:
            out.append([target, position.raw])
        if k == count:
            break
        target = start + k * step
        node.rpdo[2]["Target position"].raw = target
        node.rpdo[2].transmit()
        net.sync.transmit()
        due += period
        time.sleep(max(0.0, due - time.monotonic()))  # the master's clock
    sync(period)
    return out


def replay(node_id, path):
    """A concise DCF (CiA 302-3) as Lely's master writes it at boot: each entry by SDO
    download, in order."""
    with open(path, "rb") as f:
        data = f.read()
    (count,), at = struct.unpack_from("<I", data), 4
    for _ in range(count):
        index, sub, size = struct.unpack_from("<HBI", data, at)
        at += 7
        nodes[node_id].sdo.download(index, sub, data[at:at + size])
        at += size
    return count


def received_emcys():
    return emcys


COMMANDS = {f.__name__: f for f in (
    add, heartbeat, setup, nmt, sync, produce_heartbeat, state, op_mode, read, write,
    controlword, statusword, wait_status, tpdo, read_pdos, rpdo, csp_ramp, replay,
    received_emcys)}


def answer(obj):
    sys.stdout.write(json.dumps(obj) + "\n")
    sys.stdout.flush()


answer({"ok": "ready"})
for line in sys.stdin:
    command = json.loads(line)
    try:
        answer({"ok": COMMANDS[command["op"]](**command.get("args", {}))})
    except SdoAbortedError as err:
        answer({"abort": err.code})
    except Exception:
        answer({"error": traceback.format_exc()})
net.disconnect()
