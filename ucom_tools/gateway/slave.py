"""One CANopen node of the gateway: canopen's ``LocalNode`` (object dictionary, SDO
server) with what it lacks as a slave (``docs-gateway-node.md``): the NMT state machine
with boot-up and resets, the heartbeat producer (0x1017), SYNC-driven and event-driven
TPDOs and RPDOs into the dictionary (``ucom_tools.gateway.pdo``), PDO remapping with its
checks, value limits on SDO writes, and the EMCY upkeep (``ucom_tools.gateway.emcy``).

Everything here runs on the runtime's thread (``ucom_tools.gateway.node``) except
:meth:`SlaveNode.set`, :meth:`SlaveNode.get` and :meth:`SlaveNode.emcy`, which the
application may call from any thread: each stores or reads one value whole.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Callable
from typing import Any

import canopen
from canopen import LocalNode, ObjectDictionary
from canopen.objectdictionary import ODArray, datatypes
from canopen.sdo import SdoAbortedError

from ucom_tools.errors import InputError
from ucom_tools.gateway.codes import (
    COB_29BIT,
    COB_ID_MASK,
    Cob,
    NmtCommand,
    NmtState,
    SdoAbort,
    StateChange,
)
from ucom_tools.gateway.emcy import EmcyProducer, history_size
from ucom_tools.gateway.pdo import (
    EVENT_TYPES,
    FORMATS,
    SYNC_TYPES,
    Rpdo,
    Store,
    Tpdo,
    check_write,
    compile_pdos,
    find,
)

log = logging.getLogger("ucom.gateway")

WriteCallback = Callable[[int, int, int, Any], None]
COMM_AREA = range(0x1000, 0x2000)
SYNC_COB, CYCLE_PERIOD, ERROR_FIELD = 0x1005, 0x1006, 0x1003
COB_ID_EMCY, INHIBIT_EMCY, CONSUMER, PRODUCER = 0x1014, 0x1015, 0x1016, 0x1017
#: objects whose writes change the node's communication (re-read after the write)
COMM_OBJECTS = frozenset((SYNC_COB, CYCLE_PERIOD, COB_ID_EMCY, INHIBIT_EMCY, CONSUMER,
                          PRODUCER))
SYNC_GENERATOR = 1 << 30
INF = float("inf")
LIVE = (NmtState.PRE_OPERATIONAL, NmtState.OPERATIONAL)


class _Object:
    """How the application's :meth:`SlaveNode.set` stores one object."""

    __slots__ = ("pack", "store", "sub", "var", "watchers")

    def __init__(self, var: canopen.objectdictionary.ODVariable, store: Store, sub: int,
                 watchers: list[Tpdo]) -> None:
        fmt = FORMATS.get(var.data_type or -1)
        self.pack: Callable[[Any], bytes] = (
            struct.Struct("<" + fmt).pack if fmt is not None else var.encode_raw)
        self.store = store
        self.sub = sub
        self.var = var
        self.watchers = watchers


class SlaveNode:
    """One node: its ``LocalNode`` (``local``), NMT state, PDOs, heartbeat and EMCY."""

    def __init__(self, node_id: int, od: ObjectDictionary, network: canopen.Network,
                 on_state: Callable[[StateChange], None], on_write: WriteCallback | None,
                 kick: Callable[[], None]) -> None:
        self.id = node_id
        self.local = LocalNode(node_id, od)
        # canopen's NmtSlave answers 0x1017 writes with a python-can periodic task (a
        # thread per node); the heartbeat is this runtime's (tick)
        self.local._write_callbacks.remove(self.local.nmt.on_write)
        self.local.add_write_callback(self._on_sdo_write)
        network[node_id] = self.local  # for the SDO server's answers (nothing else)
        self.od = od
        self._on_state = on_state
        self._on_write = on_write
        self._kick = kick
        self.state = NmtState.INITIALISING
        self.emergency = EmcyProducer(node_id, self.local.data_store)
        self.tpdos: list[Tpdo] = []
        self.rpdos: list[Rpdo] = []
        self.sync_tpdos: list[Tpdo] = []
        self.event_tpdos: list[Tpdo] = []
        self.watchers: dict[tuple[int, int], list[Tpdo]] = {}
        self.pending_rpdos: list[Rpdo] = []
        self.heartbeat = 0.0  # seconds; 0: none
        self.next_heartbeat = INF
        self.sync_cob = int(Cob.SYNC)
        self.consumers: dict[int, float] = {}
        self.cycle_period = 0.0
        self.dirty_pdo = self.dirty_comm = False
        self.next_due = INF
        self.rpdo_errors = 0  # RPDOs too short or with a value out of the limits
        self.applying = False
        """True while an RPDO's values go to the application (its ``on_write`` is an
        RPDO's, not an SDO's)."""
        self._objects: dict[tuple[int, int], _Object] = {}

    # ------------------------------------------------------------ configuration
    def read(self, index: int, subindex: int) -> int:
        """A stored unsigned value (0 where there is none)."""
        try:
            data = self.local.get_data(index, subindex)
        except (SdoAbortedError, KeyError):
            return 0
        return int.from_bytes(data[:8], "little")

    def _storage(self, index: int, subindex: int, size: int) -> Store:
        store = self.local.data_store.setdefault(index, {})
        if subindex not in store:
            try:
                data = bytes(self.local.get_data(index, subindex))
            except SdoAbortedError:
                data = b""
            store[subindex] = data if len(data) == size else bytes(size)
        return store

    def configure(self, now: float, pdo: bool = True, comm: bool = True) -> None:
        """(Re-)read the PDO records (``pdo``) and the communication objects (``comm``)
        from the dictionary."""
        if pdo:
            self.dirty_pdo = False
            self.tpdos, self.rpdos = compile_pdos(self.od, self.read, self._storage, self.id)
            self.sync_tpdos = [t for t in self.tpdos if t.trans_type in SYNC_TYPES]
            self.event_tpdos = [t for t in self.tpdos if t.trans_type in EVENT_TYPES]
            watchers: dict[tuple[int, int], list[Tpdo]] = {}
            for t in self.event_tpdos:
                for e in t.entries:
                    if not e.dummy:
                        watchers.setdefault((e.index, e.subindex), []).append(t)
            self.watchers = watchers
            self._objects = {}
            self.pending_rpdos = []
            for t in self.tpdos:
                t.reset()
        if comm:
            self.dirty_comm = False
            self._configure_comm(now)

    def _configure_comm(self, now: float) -> None:
        od, read = self.od, self.read
        heartbeat = read(PRODUCER, 0) * 1e-3 if PRODUCER in od else 0.0
        if heartbeat != self.heartbeat:
            self.heartbeat = heartbeat
            self.next_heartbeat = now + heartbeat if heartbeat else INF
        self.sync_cob = read(SYNC_COB, 0) & COB_ID_MASK if SYNC_COB in od else int(Cob.SYNC)
        self.cycle_period = read(CYCLE_PERIOD, 0) * 1e-6 if CYCLE_PERIOD in od else 0.0
        self.emergency.configure(read(COB_ID_EMCY, 0) if COB_ID_EMCY in od else None,
                            read(INHIBIT_EMCY, 0) if INHIBIT_EMCY in od else 0,
                            history_size(od[ERROR_FIELD]) if ERROR_FIELD in od else 0)
        consumers: dict[int, float] = {}
        array = od.get(CONSUMER)
        if isinstance(array, ODArray):
            for sub in array.subindices:
                entry = read(CONSUMER, sub) if sub else 0
                producer, ms = (entry >> 16) & 0xFF, entry & 0xFFFF
                if producer and ms and 1 <= producer <= 127:
                    consumers[producer] = min(ms * 1e-3, consumers.get(producer, INF))
        self.consumers = consumers
        self.next_due = min(self.next_due, self.next_heartbeat)

    # ------------------------------------------------------------ SDO writes
    def _on_sdo_write(self, index: int, subindex: int, od: Any, data: bytes,
                      **_: Any) -> None:
        """LocalNode's write callback: runs before the value is stored; an exception
        aborts the write with its code (nothing stored)."""
        value = od.decode_raw(data)
        if od.data_type in datatypes.NUMBER_TYPES:
            if od.min is not None and value < od.min:
                raise SdoAbortedError(SdoAbort.VALUE_TOO_LOW)
            if od.max is not None and value > od.max:
                raise SdoAbortedError(SdoAbort.VALUE_TOO_HIGH)
        if index in COMM_AREA:
            self._comm_write(index, subindex, value)
        elif self._on_write is not None:
            self._on_write(self.id, index, subindex, value)
        watchers = self.watchers.get((index, subindex))
        if watchers and self.local.data_store.get(index, {}).get(subindex) != bytes(data):
            for t in watchers:
                t.pending = True
            self._kick()

    def _comm_write(self, index: int, subindex: int, value: Any) -> None:
        if 0x1400 <= index < 0x1C00:
            check_write(self.od, self.read, index, subindex, value)
            self.dirty_pdo = True
        elif index == ERROR_FIELD:
            if value:
                raise SdoAbortedError(SdoAbort.VALUE_RANGE)  # only 0 (clear) may be written
            self.emergency.clear_history()
        elif index in COMM_OBJECTS:
            if index == SYNC_COB and value & (SYNC_GENERATOR | COB_29BIT):
                raise SdoAbortedError(SdoAbort.VALUE_RANGE)  # no SYNC producer here
            if index == CONSUMER and subindex:
                self._check_consumer(subindex, value)
            self.dirty_comm = True

    def _check_consumer(self, subindex: int, value: int) -> None:
        producer = (value >> 16) & 0xFF
        if not producer or not value & 0xFFFF:
            return
        array = self.od[CONSUMER]
        assert isinstance(array, ODArray)
        for sub in array.subindices:
            if sub and sub != subindex:
                other = self.read(CONSUMER, sub)
                if (other >> 16) & 0xFF == producer and other & 0xFFFF:
                    raise SdoAbortedError(SdoAbort.INCOMPATIBLE)  # one entry per node

    # ------------------------------------------------------------ application values
    def _object(self, index: int, subindex: int) -> _Object:
        info = self._objects.get((index, subindex))
        if info is None:
            try:
                var = find(self.od, index, subindex)
            except SdoAbortedError:
                raise InputError(f"node {self.id}: no object 0x{index:04X}:{subindex:02X} "
                                 "in its dictionary") from None
            store = self.local.data_store.setdefault(index, {})
            info = _Object(var, store, subindex, self.watchers.get((index, subindex), []))
            self._objects[(index, subindex)] = info
        return info

    def set(self, index: int, subindex: int, value: Any) -> None:
        """Store a value the application owns (what SDO reads and TPDOs carry); an
        event-driven TPDO that maps it goes out when it changed."""
        info = self._objects.get((index, subindex)) or self._object(index, subindex)
        try:
            data = info.pack(value)
        except (struct.error, TypeError, ValueError, AttributeError) as err:
            raise InputError(f"node {self.id}: 0x{index:04X}:{subindex:02X} "
                             f"({info.var.name}): {value!r} does not fit its data type "
                             f"({err})") from None
        store, sub = info.store, info.sub
        if store.get(sub) != data:
            store[sub] = data
            if info.watchers:
                for t in info.watchers:
                    t.pending = True
                self._kick()

    def get(self, index: int, subindex: int = 0) -> Any:
        """The value as SDO would read it."""
        var = self._object(index, subindex).var
        try:
            return var.decode_raw(self.local.get_data(index, subindex))
        except SdoAbortedError as err:
            raise InputError(f"node {self.id}: 0x{index:04X}:{subindex:02X} "
                             f"({var.name}) has no value") from err

    def emcy(self, code: int, register: int, data: bytes) -> None:
        """Record an EMCY (0x1001, 0x1003) and queue it; the runtime sends it."""
        try:
            self.emergency.record(code, register, bytes(data))
        except ValueError as err:
            raise InputError(f"node {self.id}: {err}") from None
        self._kick()

    # ------------------------------------------------------------ NMT
    def _enter(self, new: NmtState, command: NmtCommand | None) -> None:
        old = self.state
        if old is new:
            return
        if old is NmtState.OPERATIONAL:
            for r in self.pending_rpdos:
                r.pending = None
            self.pending_rpdos = []
        self.state = new
        if new is NmtState.OPERATIONAL:
            for t in self.tpdos:
                t.reset()
            self._kick()
        self._on_state(StateChange(self.id, old, new, command))

    def boot(self, now: float, out: list[tuple[int, bytes]],
             command: NmtCommand | None = None) -> None:
        """Boot-up: the configuration read, the boot-up message sent, PRE-OPERATIONAL."""
        self.configure(now)
        out.append((Cob.HEARTBEAT + self.id, b"\x00"))
        self.next_heartbeat = now + self.heartbeat if self.heartbeat else INF
        self.next_due = min(self.next_due, self.next_heartbeat)
        self._enter(NmtState.PRE_OPERATIONAL, command)

    def command(self, command: NmtCommand, now: float, out: list[tuple[int, bytes]]) -> None:
        """An NMT command addressed to this node (or to all)."""
        if self.state is NmtState.INITIALISING:
            return
        if command is NmtCommand.START:
            self._enter(NmtState.OPERATIONAL, command)
        elif command is NmtCommand.STOP:
            self._enter(NmtState.STOPPED, command)
        elif command is NmtCommand.ENTER_PRE_OPERATIONAL:
            self._enter(NmtState.PRE_OPERATIONAL, command)
        else:
            self._enter(NmtState.INITIALISING, command)
            whole = command is NmtCommand.RESET_NODE
            for index, store in self.local.data_store.items():
                if whole or index in COMM_AREA:
                    store.clear()  # in place: the stores' references stay good
            self.emergency.queue.clear()
            self.boot(now, out, command)

    # ------------------------------------------------------------ PDOs and time
    def on_rpdo(self, rpdo: Rpdo, data: bytes) -> None:
        """An RPDO frame: applied now (event-driven) or at the next SYNC."""
        if self.state is not NmtState.OPERATIONAL:
            return
        if len(data) < rpdo.length:
            self.rpdo_errors += 1
            return
        if rpdo.synchronous:
            if rpdo.pending is None:
                self.pending_rpdos.append(rpdo)
            rpdo.pending = data
        else:
            self.apply(rpdo, data)

    def apply(self, rpdo: Rpdo, data: bytes) -> None:
        """An RPDO's values into the dictionary and to the application, in map order
        (:attr:`applying` meanwhile)."""
        self.applying = True
        try:
            self._apply(rpdo, data)
        finally:
            self.applying = False

    def _apply(self, rpdo: Rpdo, data: bytes) -> None:
        values = rpdo.struct.unpack_from(data)
        app = self._on_write
        for position, offset, size, store, entry in rpdo.slots:
            value = values[position]
            if (entry.low is not None and value < entry.low) or \
                    (entry.high is not None and value > entry.high):
                self.rpdo_errors += 1
                continue
            raw = data[offset:offset + size]
            sub = entry.subindex
            if store.get(sub) != raw:
                store[sub] = raw
                watchers = self.watchers.get((entry.index, sub))
                if watchers:
                    for t in watchers:
                        t.pending = True
                    self._kick()
            if app is not None:
                try:
                    app(self.id, entry.index, sub, value)
                except Exception:
                    log.exception("node %d: the application's write of 0x%04X:%02X "
                                  "failed", self.id, entry.index, sub)

    def apply_sync_rpdos(self) -> None:
        """The synchronous RPDOs received since the last SYNC, in order."""
        pending, self.pending_rpdos = self.pending_rpdos, []
        for rpdo in pending:
            data, rpdo.pending = rpdo.pending, None
            if data is not None:
                self.apply(rpdo, data)

    def run_sync(self, counter: int | None, now: float, out: list[tuple[int, bytes]]) -> None:
        """The synchronous TPDOs due at this SYNC (OPERATIONAL only)."""
        for t in self.sync_tpdos:
            if not t.started:
                if counter is not None and counter != t.sync_start:
                    continue
                t.started = True
            if t.trans_type:
                t.count += 1
                if t.count < t.trans_type:
                    continue
                t.count = 0
                data = t.build()
            else:
                data = t.build()
                if data == t.last:
                    continue
            out.append((t.cob_id, data))
            t.last = data
            t.last_time = now

    def tick(self, now: float, out: list[tuple[int, bytes]]) -> float:
        """Heartbeat, event-driven TPDOs and EMCYs due at ``now``; the next due time."""
        due = INF
        if self.heartbeat:
            if now >= self.next_heartbeat:
                out.append((Cob.HEARTBEAT + self.id, bytes((self.state,))))
                following = self.next_heartbeat + self.heartbeat
                self.next_heartbeat = following if following > now else now + self.heartbeat
            due = self.next_heartbeat
        if self.state is NmtState.OPERATIONAL:
            for t in self.event_tpdos:
                due = min(due, self._event(t, now, out))
        due = min(due, self.emergency.due(now, self.state in LIVE, out))
        self.next_due = due
        return due

    @staticmethod
    def _event(t: Tpdo, now: float, out: list[tuple[int, bytes]]) -> float:
        if t.pending:
            ready = t.last_time + t.inhibit
            if now < ready:
                return ready
            t.pending = False
            data = t.build()
            if data != t.last:
                out.append((t.cob_id, data))
                t.last, t.last_time = data, now
        if t.event_timer:
            if now >= t.last_time + t.event_timer:
                data = t.build()
                out.append((t.cob_id, data))
                t.last, t.last_time = data, now
            return t.last_time + t.event_timer
        return INF
