"""The gateway's CANopen node runtime: N slave nodes on one python-can bus, each on
canopen's ``LocalNode`` (``ucom_tools.gateway.slave``), driven by one thread that reads
the bus and keeps time.  It knows nothing of UCoM: it takes one
``canopen.ObjectDictionary`` per node and calls the application back
(:class:`NodeCallbacks`); ``docs-gateway-node.md`` describes the behaviour.

One thread does everything, in arrival order: it waits for a frame at most one cycle
(default 1 ms) or until the next timer (heartbeat, inhibit time, event timer, EMCY,
master watch), dispatches the frame by its identifier (NMT, SYNC, SDO, RPDO, heartbeats
of a master), then runs the timers that are due.  An SDO request waits at most for the
SYNC work ahead of it, never for a second thread to be handed the interpreter lock (5
ms at worst in CPython).  Frames produced together (a SYNC's TPDOs of every node, a
broadcast NMT's boot-ups) go to the bus in one call where the bus has one
(``send_data_many``, as ucom's socketcand bus does), else one by one.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import partial
from typing import Any

import can
import canopen
from canopen import ObjectDictionary

from ucom_tools.errors import InputError
from ucom_tools.gateway.codes import Cob, NmtCommand, NmtState, StateChange
from ucom_tools.gateway.slave import SlaveNode
from ucom_tools.gateway.watch import MasterWatch

log = logging.getLogger("ucom.gateway")

INF = float("inf")
DRAIN = 64  # frames taken without waiting before the timers run
Handler = Callable[[bytes], None]


@dataclass(frozen=True)
class NodeCallbacks:
    """What the runtime tells the application; each runs on the runtime's thread and
    should return quickly (an exception is logged, the runtime goes on).

    - ``on_write(node_id, index, subindex, value)``: a master wrote an application
      object (0x2000 and up) by SDO (before it is stored: raise
      ``canopen.SdoAbortedError(code)`` to refuse it) or by RPDO (after it is stored);
    - ``on_state(change)``: a node's NMT state changed (:class:`StateChange`);
    - ``on_sync(counter)``: a SYNC (its counter, or ``None``), after the synchronous
      RPDOs received before it were applied and before the TPDOs are built;
    - ``master_lost(reason)`` / ``master_back(reason)``: the master watch
      (``ucom_tools.gateway.watch``), once each way;
    - ``on_tick(now)``: once a cycle (at most), after the timers: the application's
      periodic work (``now``: ``time.monotonic()``); frames it queues with the nodes'
      values (an event-driven TPDO, an EMCY) go out with the cycle's.  It may return
      when it wants its next turn (None: a cycle on); the runtime then sleeps until that
      time, its timers or a frame (each wake-up of an idle thread costs some 60 us of CPU
      on a virtual machine).
    """

    on_write: Callable[[int, int, int, Any], None] | None = None
    on_state: Callable[[StateChange], None] | None = None
    on_sync: Callable[[int | None], None] | None = None
    master_lost: Callable[[str], None] | None = None
    master_back: Callable[[str], None] | None = None
    on_tick: Callable[[float], float | None] | None = None


@dataclass(frozen=True)
class RuntimeStats:
    """Counters since the start; ``sync_cpu_s`` is the runtime thread's CPU time spent
    on SYNCs (RPDOs applied, ``on_sync``, TPDOs built and sent), ``thread_cpu_s`` all of
    its CPU time."""

    frames_in: int
    frames_out: int
    syncs: int
    send_errors: int
    rpdo_errors: int
    sync_cpu_s: float
    thread_cpu_s: float


class _Network(canopen.Network):
    """canopen's network object for the nodes' SDO servers, sending through the
    runtime; nothing is received through it (the runtime dispatches)."""

    def __init__(self, send: Callable[[int, bytes], None]) -> None:
        super().__init__(None)
        self._send = send

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        self._send(can_id, bytes(data))


class NodeRuntime:
    """CANopen slave nodes on one bus: ``NodeRuntime(bus, {node_id: dictionary, ...},
    callbacks).start()``; :meth:`close` stops the thread (the bus stays open: it is the
    caller's)."""

    def __init__(self, bus: can.BusABC, dictionaries: Mapping[int, ObjectDictionary],
                 callbacks: NodeCallbacks | None = None, *, cycle: float = 0.001) -> None:
        if not dictionaries:
            raise InputError("a CANopen bus needs at least one node")
        for node_id in dictionaries:
            if not 1 <= node_id <= 127:
                raise InputError(f"CANopen node ID {node_id}: 1..127")
        if not 0 < cycle <= 0.1:
            raise InputError(f"cycle {cycle} s: above 0, at most 0.1 s")
        self.bus = bus
        self.cycle = cycle
        self.callbacks = callbacks or NodeCallbacks()
        self._send_many = getattr(bus, "send_data_many", None)
        self._send_data = getattr(bus, "send_data", None)
        self._network = _Network(self._send_now)
        self._out: list[tuple[int, bytes]] = []
        self._kicked = False
        self._next_due = INF
        self._table: dict[int, tuple[Handler, ...]] = {}
        self._slaves = {node_id: SlaveNode(node_id, od, self._network, self._state_changed,
                                           self.callbacks.on_write, self._kick)
                        for node_id, od in sorted(dictionaries.items())}
        self._order = tuple(self._slaves.values())
        self._watch = MasterWatch(self._lost, self._back)
        self._stop = threading.Event()
        self._ready = threading.Event()
        self._thread: threading.Thread | None = None
        self._failure: BaseException | None = None
        self._frames_in = self._frames_out = self._syncs = self._send_errors = 0
        self._tick_errors = 0
        self._sync_cpu = self._thread_cpu = 0.0

    # ------------------------------------------------------------ public API
    def start(self, timeout: float = 2.0) -> NodeRuntime:
        """Start the thread; every node sends its boot-up and is PRE-OPERATIONAL when
        this returns."""
        if self._thread is not None:
            raise InputError("the CANopen node runtime is already started")
        self._thread = threading.Thread(target=self._run, name="canopen-nodes", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout):
            self.close()
            raise InputError(f"the CANopen node runtime did not start within {timeout} s")
        if self._failure is not None:
            raise InputError(f"the CANopen node runtime failed: {self._failure}") \
                from self._failure
        return self

    def close(self, timeout: float = 2.0) -> None:
        """Stop the thread (within ``timeout``); the bus is left open."""
        self._stop.set()
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout)

    def __enter__(self) -> NodeRuntime:
        return self.start() if self._thread is None else self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def node_ids(self) -> tuple[int, ...]:
        return tuple(self._slaves)

    def node(self, node_id: int) -> SlaveNode:
        """The node ``node_id`` (its ``local`` is canopen's ``LocalNode``)."""
        try:
            return self._slaves[node_id]
        except KeyError:
            raise InputError(f"no CANopen node {node_id} on this bus (nodes: "
                             f"{', '.join(map(str, self._slaves))})") from None

    def state(self, node_id: int) -> NmtState:
        return self.node(node_id).state

    def set(self, node_id: int, index: int, subindex: int, value: Any) -> None:
        """Store an application value of a node (SDO reads it, TPDOs carry it)."""
        self.node(node_id).set(index, subindex, value)

    def get(self, node_id: int, index: int, subindex: int = 0) -> Any:
        """A node's value as SDO reads it."""
        return self.node(node_id).get(index, subindex)

    def emcy(self, node_id: int, code: int, register: int = 0, data: bytes = b"") -> None:
        """Send an EMCY of ``node_id`` (0x1001 takes ``register`` with its generic bit,
        0x1003 the code); code 0 is the error reset."""
        self.node(node_id).emcy(code, register, data)

    @property
    def master_lost(self) -> bool:
        """Whether the master is gone now (as last reported)."""
        return self._watch.lost

    def stats(self) -> RuntimeStats:
        return RuntimeStats(self._frames_in, self._frames_out, self._syncs,
                            self._send_errors, sum(s.rpdo_errors for s in self._order),
                            self._sync_cpu, self._thread_cpu)

    # ------------------------------------------------------------ the thread
    def _run(self) -> None:
        cpu0 = time.thread_time()
        try:
            now = time.monotonic()
            for slave in self._order:
                slave.boot(now, self._out)
            self._rebuild()
            self._flush()
        except BaseException as err:  # reported by start()
            self._failure = err
            self._ready.set()
            raise
        self._ready.set()
        try:
            self._loop()
        finally:
            self._thread_cpu = time.thread_time() - cpu0

    def _loop(self) -> None:
        bus, cycle, stop = self.bus, self.cycle, self._stop
        on_tick = self.callbacks.on_tick
        watch_due = INF
        next_tick = 0.0
        while not stop.is_set():
            now = time.monotonic()
            timeout = min(cycle if on_tick is None else next_tick - now,
                          self._next_due - now, watch_due - now)
            try:
                msg = bus.recv(timeout if timeout > 0 else 0.0)
                if msg is not None:
                    self._watch.bus_ok()
                    self._dispatch(msg)
                    for _ in range(DRAIN):
                        msg = bus.recv(0.0)
                        if msg is None:
                            break
                        self._dispatch(msg)
            except (can.CanError, OSError) as err:
                self._watch.bus_failed(f"CAN bus failed: {err}")
                stop.wait(cycle)
            try:
                now = time.monotonic()
                if on_tick is not None and now >= next_tick:
                    next_tick = now + cycle
                    try:
                        wanted = on_tick(now)
                        if wanted is not None:
                            next_tick = max(now + cycle, wanted)
                    except Exception:  # the application's: logged, the timers run on
                        self._tick_errors += 1
                        if self._tick_errors % 1000 == 1:
                            log.exception("the application's cycle callback failed (%d "
                                          "times so far)", self._tick_errors)
                if self._kicked or now >= self._next_due:
                    self._tick(now)
                watch_due = self._watch.check(now)
                if self._out:
                    self._flush()
            except Exception:  # a fault of this runtime's own: logged, the loop goes on
                log.exception("CANopen node runtime: timers failed")
                stop.wait(cycle)

    def _dispatch(self, msg: can.Message) -> None:
        self._frames_in += 1
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            return
        handlers = self._table.get(msg.arbitration_id)
        if handlers is None:
            return
        data = bytes(msg.data)
        for handler in handlers:
            try:
                handler(data)
            except Exception:
                log.exception("frame 0x%03X %s: handling failed", msg.arbitration_id,
                              bytes(data).hex())
        if self._out:
            self._flush()

    def _tick(self, now: float) -> None:
        self._kicked = False
        out = self._out
        due = INF
        for slave in self._order:
            d = slave.tick(now, out)
            if d < due:
                due = d
        self._next_due = due

    def _kick(self) -> None:
        self._kicked = True

    def _rebuild(self) -> None:
        """The dispatch table from the nodes' configuration; the master watch's."""
        table: dict[int, list[Handler]] = {int(Cob.NMT): [self._on_nmt]}
        syncs: dict[int, list[SlaveNode]] = {}
        consumers: dict[int, float] = {}
        periods = []
        for s in self._order:
            table.setdefault(Cob.SDO_RX + s.id, []).append(partial(self._on_sdo, s))
            syncs.setdefault(s.sync_cob, []).append(s)
            for r in s.rpdos:
                table.setdefault(r.cob_id, []).append(partial(s.on_rpdo, r))
            for producer, timeout in s.consumers.items():
                consumers[producer] = min(timeout, consumers.get(producer, INF))
            if s.cycle_period:
                periods.append(s.cycle_period)
        for cob, group in syncs.items():
            table.setdefault(cob, []).append(partial(self._on_sync, tuple(group)))
        self._watch.configure(consumers, min(periods, default=0.0))
        for producer in consumers:
            table.setdefault(Cob.HEARTBEAT + producer, []).append(
                partial(self._on_heartbeat, producer))
        self._table = {cob: tuple(handlers) for cob, handlers in table.items()}
        self._next_due = min(s.next_due for s in self._order)

    # ------------------------------------------------------------ handlers
    def _on_nmt(self, data: bytes) -> None:
        if len(data) != 2:
            return
        try:
            command = NmtCommand(data[0])
        except ValueError:
            return
        target = data[1]
        now = time.monotonic()
        for s in self._order:
            if target in (0, s.id):
                s.command(command, now, self._out)
        if command in (NmtCommand.RESET_NODE, NmtCommand.RESET_COMMUNICATION):
            self._rebuild()
        self._kicked = True

    def _on_sdo(self, slave: SlaveNode, data: bytes) -> None:
        if slave.state is not NmtState.PRE_OPERATIONAL and \
                slave.state is not NmtState.OPERATIONAL:
            return
        slave.local.sdo.on_request(Cob.SDO_RX + slave.id, data, 0.0)
        if slave.dirty_pdo or slave.dirty_comm:  # stored now: re-read
            slave.configure(time.monotonic(), slave.dirty_pdo, slave.dirty_comm)
            self._rebuild()
            self._kicked = True

    def _on_sync(self, group: tuple[SlaveNode, ...], data: bytes) -> None:
        cpu = time.thread_time()
        now = time.monotonic()
        self._syncs += 1
        self._watch.sync(now)
        for s in group:
            if s.pending_rpdos:
                s.apply_sync_rpdos()
        counter = data[0] if data else None
        on_sync = self.callbacks.on_sync
        if on_sync is not None:
            try:
                on_sync(counter)
            except Exception:
                log.exception("the application's SYNC callback failed")
        out = self._out
        for s in group:
            if s.state is NmtState.OPERATIONAL:
                s.run_sync(counter, now, out)
        self._flush()
        self._sync_cpu += time.thread_time() - cpu

    def _on_heartbeat(self, producer: int, data: bytes) -> None:
        self._watch.heartbeat(producer, time.monotonic())

    # ------------------------------------------------------------ callbacks, sending
    def _state_changed(self, change: StateChange) -> None:
        self._call(self.callbacks.on_state, change)

    def _lost(self, reason: str) -> None:
        log.debug("CANopen master lost: %s", reason)
        self._call(self.callbacks.master_lost, reason)

    def _back(self, reason: str) -> None:
        log.debug("CANopen master back: %s", reason)
        self._call(self.callbacks.master_back, reason)

    @staticmethod
    def _call(callback: Callable[[Any], None] | None, arg: Any) -> None:
        if callback is not None:
            try:
                callback(arg)
            except Exception:
                log.exception("the application's callback %r failed", callback)

    def _flush(self) -> None:
        frames, self._out = self._out, []
        if not frames:
            return
        if self._send_many is not None:
            try:
                self._send_many(frames)
                self._frames_out += len(frames)
                return
            except can.CanError as err:
                self._send_failed(err, len(frames))
                return
        if self._send_data is not None:
            for ident, data in frames:
                self._send_now(ident, data)
            return
        send, message = self.bus.send, can.Message
        for ident, data in frames:  # python-can's own buses: a message each
            try:
                send(message(arbitration_id=ident, data=data, is_extended_id=False,
                             check=False))
                self._frames_out += 1
            except can.CanError as err:
                self._send_failed(err, 1)

    def _send_now(self, ident: int, data: bytes) -> None:
        try:
            if self._send_data is not None:
                self._send_data(ident, data)
            else:
                self.bus.send(can.Message(arbitration_id=ident, data=data,
                                          is_extended_id=False, check=False))
            self._frames_out += 1
        except can.CanError as err:
            self._send_failed(err, 1)

    def _send_failed(self, err: can.CanError, frames: int) -> None:
        if self._send_errors % 1000 == 0:
            log.warning("CANopen frames not sent (%d so far): %s", self._send_errors + 1, err)
        self._send_errors += frames
