"""Serve each bus of a fleet from a process of its own (``ucom fleet serve``, the default
``--processes auto`` for a topology with more than one bus).

Why: a served fleet is paced to the wall clock by one driver thread per process
(:class:`~ucom_tools.virtual.clock.RealtimeDriver`), and Python runs one thread at a time
per process.  ARMAR-III has 11 boards on 4 buses, each board running its exchange at
1 kHz; in one process that is more than one core's work, the fleet falls behind real time
and the boards' watchdogs fire.  Served from one process per bus, the buses run on as
many cores as there are.

Why it is the same fleet: within a bus nothing changes - its boards and clients share
one simulated bus in one process, as before.  Buses never interact (each board is on
exactly one bus).  And the project's rule "one fleet clock" (every bus and board of a
fleet on one time base) holds across the processes: paced, a fleet's time base is the
wall clock, ``time.monotonic()``, which is the same clock in every process of the system;
each process steps its bus at the pace of that clock, so the buses stay in step by
construction, as they do in one process.  The frame timestamps clients get are the wall
clock's (``time.time()`` at the frame's end) on every bus alike: each process sets its
fleet's epoch so that virtual time maps to the wall clock.  Only the virtual time's
origin (when a process powered its boards) differs between buses, and nothing compares
virtual times of two buses.

How::

    main process                                  one process per bus (spawned)
    listens on HOST:PORT, counts clients          a Fleet of its bus only, paced
    accepts, greets  < hi >                       serves handed-over clients with
    reads up to the client's  < open BUS >  --->  Connection.resume: < ok >, rawmode,
    (errors answered as Connection does)   socket  frames ... exactly as in one process
                                           + bytes
                                           read after
    slot free again  <------------------ "done"

The main process hands the connected socket itself over (``SCM_RIGHTS`` on a Unix
``SOCK_SEQPACKET`` pair, one long-lived control channel per process, one message per
connection together with the bytes the client sent after its open), so frames go
straight between client and bus process.  Elements before the open get the same answers
as from one process (:func:`~ucom_tools.virtual.socketcand.check_open` and the texts of
:mod:`~ucom_tools.virtual.socketcand`); ``--max-clients`` counts the connections of every
bus: a slot is taken at accept and freed when the client leaves before opening, or when
its bus process reports the connection ended.

The processes are started with ``spawn`` (never ``fork`` after threads exist), with SIGINT
ignored: Ctrl-C reaches the whole process group, and the main process stops them in
order (closing the clients, stopping the driver, so the boards' state files are complete;
they are written atomically anyway).  SIGTERM to the main process does the same.  A bus
process stops by itself when the main process is gone (its control channel closes), and
on SIGTERM.  One that ends while serving makes the whole serve stop with
:class:`~ucom_tools.errors.BusError` naming its bus (exit code 4).  Bus processes log to
stderr with the main process's format and level.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import multiprocessing
import os
import pickle
import signal
import socket
import sys
import threading
import time
import traceback
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from ucom_tools.config.topology import Topology
from ucom_tools.errors import BusError, InputError, UcomError
from ucom_tools.virtual.fleet import Fleet
from ucom_tools.virtual.socketcand import (
    FLUSH_S,
    MAX_CLIENTS,
    MAX_ELEMENT,
    MAX_QUEUED_FRAMES,
    NO_BUS_OPEN,
    ClientServer,
    Connection,
    ElementError,
    ElementSplitter,
    ElementTooLong,
    _peer,
    check_open,
    element_words,
    unsupported,
)

log = logging.getLogger("ucom.serve")

LOG_FORMAT = "ucom fleet serve: %(message)s"
"""How ``ucom fleet serve`` logs, in every process."""
START_TIMEOUT_S = 60.0
"""How long a bus process may take from its start to serving (imports, its boards)."""
STOP_TIMEOUT_S = 5.0
"""How long a bus process may take to stop once asked; then it is killed."""
REPLY_TIMEOUT_S = 5.0
"""How long the main process waits to write one answer to a client that has not opened a
bus yet; a client that does not read it meanwhile is dropped."""
_RECV_SIZE = 4096
_MESSAGE_MAX = 1 << 17
"""Largest control message (a handover: a few hundred bytes plus at most two chunks)."""


# ---------------------------------------------------------------------- the main process
class _Dropped(Exception):
    """A client the main process closes before it opened a bus (logged as a warning)."""


class Reception:
    """A client of the main process from its greeting to its ``< open BUS >``: answers the
    elements before (as :class:`~ucom_tools.virtual.socketcand.Connection` does) and
    returns the bus to open and the bytes the client sent after the open."""

    def __init__(self, sock: socket.socket, address: Any, buses: dict[str, BusProcess],
                 fleet_name: str) -> None:
        self.sock = sock
        self.peer = _peer(address)
        self.buses = buses
        self.fleet_name = fleet_name
        self.reason = "disconnected"
        self.dropped = False
        self._closing = False
        self._splitter = ElementSplitter()

    def run(self) -> tuple[str, bytes] | None:
        """The bus the client opened and what it sent after, or None when it left (or was
        dropped, or the server stops) before."""
        log.info("client %s connected", self.peer)
        sock = self.sock
        try:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.settimeout(REPLY_TIMEOUT_S)
            self._reply("< hi >")
            while True:
                while (element := self._splitter.next()) is not None:
                    bus = self._execute(element)
                    if bus is not None:
                        sock.settimeout(None)  # the bus process reads it blocking
                        return bus, self._splitter.rest()
                chunk = self._receive()
                if not chunk:
                    if self._closing:
                        self.reason = "server closed"
                    return None
                self._splitter.feed(chunk)
        except ElementTooLong:
            with contextlib.suppress(_Dropped):
                self._reply("< error element too long >")
            self._drop(f"sent an element longer than {MAX_ELEMENT} bytes")
        except _Dropped as drop:
            self._drop(str(drop))
        except OSError as err:
            self.reason = ("server closed" if self._closing
                           else f"connection lost ({type(err).__name__})")
        return None

    def close(self) -> None:
        """The server stops: end :meth:`run` (any thread)."""
        self._closing = True
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)

    def log_end(self) -> None:
        if self.dropped:
            log.warning("dropped client %s: %s", self.peer, self.reason)
        else:
            log.info("client %s left: %s", self.peer, self.reason)

    def _receive(self) -> bytes:
        while True:
            try:
                return self.sock.recv(_RECV_SIZE)
            except TimeoutError:  # the timeout is for replies; a client may think long
                if self._closing:
                    return b""

    def _execute(self, element: bytes) -> str | None:
        try:
            verb, *args = element_words(element)
            if verb == "open":
                return check_open(args, self.buses, self.fleet_name)
            if verb == "echo":
                self._reply("< echo >")
                return None
            if verb in ("rawmode", "send"):
                raise ElementError(NO_BUS_OPEN)
            raise unsupported(verb)
        except ElementError as err:
            self._reply(f"< error {err} >")
        return None

    def _reply(self, text: str) -> None:
        try:
            self.sock.sendall(text.encode("ascii", "replace"))
        except TimeoutError:
            raise _Dropped(f"stopped reading (no answer written in {REPLY_TIMEOUT_S:g} s)") \
                from None

    def _drop(self, reason: str) -> None:
        self.reason, self.dropped = reason, True
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)


class Dispatcher(ClientServer):
    """The main process's TCP server: greets each client, reads up to its open and hands
    it to the process of that bus; counts the connections of every bus."""

    def __init__(self, host: str, port: int, buses: dict[str, BusProcess], fleet_name: str,
                 *, max_clients: int = MAX_CLIENTS) -> None:
        self.buses = buses
        self.fleet_name = fleet_name
        self._receptions: set[Reception] = set()
        self._lock = threading.Lock()
        self._closed = False
        super().__init__(host, port, max_clients=max_clients)

    def serve_client(self, sock: socket.socket, address: Any) -> None:
        """One accepted client, in its handler thread: until it opened a bus here, then
        until its bus process is done with it (the slot stays taken meanwhile)."""
        reception = Reception(sock, address, self.buses, self.fleet_name)
        with self._lock:
            if self._closed:
                reception.close()
            self._receptions.add(reception)
        try:
            opened = reception.run()
        finally:
            with self._lock:
                self._receptions.discard(reception)
        if opened is None:
            reception.log_end()
            return
        bus, pending = opened
        done = self.buses[bus].hand_over(sock, address, bus, pending)
        sock.close()  # the bus process has its own descriptor now (close, never shutdown)
        if done is None:
            log.warning("dropped client %s: the process of %s has ended", reception.peer, bus)
            return
        done.wait()

    def server_close(self) -> None:
        """Stop listening and close the clients that have not opened a bus."""
        super().server_close()
        with self._lock:
            self._closed = True
            receptions = list(self._receptions)
        for reception in receptions:
            reception.close()


@dataclass(frozen=True)
class BusConfig:
    """What a bus process needs to build and serve its buses (pickled to it)."""

    topology: Topology
    buses: tuple[str, ...]
    """The buses of ``topology`` that the process serves (one, unless fewer processes
    than buses were asked for)."""
    state_dir: Path | None
    max_queued_frames: int = MAX_QUEUED_FRAMES
    log_level: int = logging.WARNING
    switch_interval: float | None = None
    """``sys.setswitchinterval`` in the process (None: Python's default)."""
    fleet_options: Mapping[str, Any] = field(default_factory=dict)
    """More keyword arguments for the process's :class:`~ucom_tools.virtual.fleet.Fleet`."""


class BusProcess:
    """The main process's handle of one bus process: starts it, hands it clients, hears
    what it reports on the control channel, stops it."""

    def __init__(self, config: BusConfig,
                 on_end: Callable[[BusProcess], None] = lambda _worker: None) -> None:
        self.config = config
        self.buses = config.buses
        self.label = ", ".join(config.buses)
        """The buses in words: ``CAN1`` (or ``CAN0, CAN1``)."""
        self.on_end = on_end
        self.ready = threading.Event()
        """Set when the process serves its bus, or has ended (see :attr:`error`)."""
        self.ended = threading.Event()
        self.error: UcomError | None = None
        """Why the process could not serve (set before :attr:`ready`)."""
        self.stopping = False
        self._channel, self._child_channel = socket.socketpair(socket.AF_UNIX,
                                                               socket.SOCK_SEQPACKET)
        context = multiprocessing.get_context("spawn")
        self.process = context.Process(target=bus_process_main,
                                       name=f"ucom-serve-{'+'.join(self.buses)}",
                                       args=(self._child_channel, config), daemon=True)
        self._handed: dict[int, threading.Event] = {}
        self._ids = itertools.count(1)
        self._lock = threading.Lock()
        self._send_lock = threading.Lock()
        self._listener = threading.Thread(target=self._listen, daemon=True,
                                          name=f"ucom-serve-{'+'.join(self.buses)}-channel")

    @property
    def pid(self) -> int | None:
        return self.process.pid

    def start(self) -> None:
        with _sigint_ignored():  # the process starts with SIGINT ignored (Ctrl-C: see above)
            self.process.start()
        self._child_channel.close()  # EOF on the channel once the process is gone
        self._listener.start()

    def hand_over(self, sock: socket.socket, address: Any, bus: str,
                  pending: bytes) -> threading.Event | None:
        """Give the process a client that sent ``< open BUS >`` (and then ``pending``);
        the event is set when the process is done with it, or has ended.  None: the
        process is gone and did not take the client."""
        with self._lock:
            if self.ended.is_set():
                return None
            key = next(self._ids)
            done = self._handed[key] = threading.Event()
        try:
            message = pickle.dumps(("client", key, address, bus, pending))
            with self._send_lock:
                socket.send_fds(self._channel, [message], [sock.fileno()])
        except OSError:
            with self._lock:
                self._handed.pop(key, None)
            return None
        return done

    def stop(self) -> None:
        """Ask the process to close its clients and stop (it also stops on EOF)."""
        self.stopping = True
        with contextlib.suppress(OSError), self._send_lock:
            self._channel.send(pickle.dumps(("stop",)))

    def join(self, timeout: float) -> None:
        """Wait for the process to end; kill it when it takes longer than ``timeout``."""
        if self.process.pid is not None:
            self.process.join(timeout)
            if self.process.exitcode is None:
                log.warning("the process of %s (pid %s) did not stop in %g s: killed",
                            self.label, self.pid, timeout)
                self.process.kill()
                self.process.join(2.0)
        if self._listener.is_alive():
            self._listener.join(2.0)
        with contextlib.suppress(OSError):
            self._channel.close()
        with contextlib.suppress(OSError):
            self._child_channel.close()

    def how_it_ended(self) -> str:
        """The end of the process in words: 'killed by SIGKILL', 'exit code 1'."""
        self.process.join(1.0)
        code = self.process.exitcode
        if code is None:
            return "it stopped answering"
        if code < 0:
            with contextlib.suppress(ValueError):
                return f"killed by {signal.Signals(-code).name}"
            return f"killed by signal {-code}"
        return f"exit code {code}"

    def _listen(self) -> None:
        """Read the process's reports until its channel closes (it ended)."""
        try:
            while True:
                message = self._channel.recv(_MESSAGE_MAX)
                if not message:
                    break
                self._report(pickle.loads(message))
        except (OSError, pickle.UnpicklingError, EOFError):
            pass
        finally:
            with self._lock:
                self.ended.set()
                handed = list(self._handed.values())
                self._handed.clear()
            for done in handed:
                done.set()
            if not self.ready.is_set() and self.error is None:
                self.error = BusError(f"the process of {self.label} ended before serving "
                                      f"({self.how_it_ended()})")
            self.ready.set()
            self.on_end(self)

    def _report(self, message: tuple[Any, ...]) -> None:
        kind = message[0]
        if kind == "done":
            with self._lock:
                done = self._handed.pop(message[1], None)
            if done is not None:
                done.set()
        elif kind == "ready":
            for bus in self.buses:
                log.info("%s is served by process %d", bus, message[1])
            self.ready.set()
        elif kind == "error":
            _, error_kind, text = message
            self.error = (InputError(text) if error_kind == "input" else
                          BusError(text) if error_kind == "bus" else UcomError(text))
            self.ready.set()
        elif kind == "crash":
            log.error("the process of %s failed:\n%s", self.label, message[1].rstrip())
            self.error = BusError(f"the process of {self.label} failed: {message[2]}")
            self.ready.set()


@contextlib.contextmanager
def _sigint_ignored() -> Iterator[None]:
    """SIGINT ignored meanwhile (when called in the main thread, where handlers live)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


class MultiServer:
    """Every bus of a topology served from a process of its own, behind one TCP port.

    ``MultiServer(...)`` listens (``OSError`` when it cannot), :meth:`start` starts the
    bus processes and waits until each serves its bus (raising the first one's error,
    e.g. :class:`~ucom_tools.errors.InputError` for an unusable state file), and
    :meth:`serve_until_interrupted` serves until Ctrl-C or SIGTERM; it raises
    :class:`~ucom_tools.errors.BusError` naming the bus when a bus process ended."""

    def __init__(self, topology: Topology, host: str = "127.0.0.1", port: int = 0, *,
                 state_dir: Path | None = None, max_clients: int = MAX_CLIENTS,
                 max_queued_frames: int = MAX_QUEUED_FRAMES,
                 log_level: int = logging.WARNING,
                 switch_interval: float | None = None,
                 fleet_options: Mapping[str, Any] | None = None,
                 processes: int | None = None) -> None:
        self.topology = topology
        self._failed = threading.Event()
        self.failure: str | None = None
        self.buses: dict[str, BusProcess] = {}
        """The process of each bus."""
        self.processes: list[BusProcess] = []
        self.dispatcher = Dispatcher(host, port, self.buses, topology.name,
                                     max_clients=max_clients)
        for group in bus_groups(topology, processes):
            worker = BusProcess(BusConfig(topology, group, state_dir, max_queued_frames,
                                          log_level, switch_interval,
                                          dict(fleet_options or {})), self._ended)
            self.processes.append(worker)
            self.buses.update(dict.fromkeys(group, worker))
        self._thread: threading.Thread | None = None
        self._closed = False

    @property
    def address(self) -> tuple[str, int]:
        return self.dispatcher.address

    def pids(self) -> dict[str, int | None]:
        """The process of each bus."""
        return {bus: worker.pid for bus, worker in self.buses.items()}

    def start(self, timeout: float = START_TIMEOUT_S) -> None:
        """Start the bus processes and wait until every one serves its buses."""
        for worker in self.processes:
            worker.start()
        deadline = time.monotonic() + timeout
        for worker in self.processes:
            if not worker.ready.wait(max(0.0, deadline - time.monotonic())):
                raise BusError(f"the process of {worker.label} did not start serving in "
                               f"{timeout:g} s")
            if worker.error is not None:
                raise worker.error
        self._thread = threading.Thread(target=self.dispatcher.serve_forever, args=(0.2,),
                                        name="ucom-socketcand", daemon=True)
        self._thread.start()

    def serve_until_interrupted(self) -> None:
        """Serve until Ctrl-C or SIGTERM, then stop everything; BusError when a bus
        process ended meanwhile."""
        with contextlib.suppress(KeyboardInterrupt), sigterm_interrupts():
            while not self._failed.wait(0.2):
                pass
        self.close()
        if self.failure is not None:
            raise BusError(self.failure)

    def close(self) -> None:
        """Stop listening, stop every bus process (their clients are closed), wait for
        them (idempotent)."""
        if self._closed:
            return
        self._closed = True
        if self._thread is not None:
            self.dispatcher.shutdown()
            self._thread.join(2.0)
        self.dispatcher.server_close()
        for worker in self.processes:
            worker.stop()
        for worker in self.processes:
            worker.join(STOP_TIMEOUT_S)

    def __enter__(self) -> MultiServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _ended(self, worker: BusProcess) -> None:
        if worker.stopping or not worker.ready.is_set() or worker.error is not None:
            return  # asked to stop, or failed to start (start() reports that)
        if self.failure is None:
            whose = (f"bus {worker.label}: its" if len(worker.buses) == 1 else
                     f"buses {worker.label}: their")
            self.failure = (f"{whose} process (pid {worker.pid}) ended "
                            f"({worker.how_it_ended()}); stopped serving {self.topology.name}")
        self._failed.set()


def usable_cores() -> int:
    """The cores this process may run on: its CPU affinity where the system keeps one
    (``os.sched_getaffinity``, Linux), else ``os.cpu_count()``; at least 1."""
    affinity = getattr(os, "sched_getaffinity", None)
    if affinity is not None:
        with contextlib.suppress(OSError):
            return max(1, len(affinity(0)))
    return max(1, os.cpu_count() or 1)


def auto_processes(topology: Topology) -> int:
    """``--processes auto``: one process per bus, but no more than there are cores to
    run them (a process per bus beyond that only adds switching)."""
    return max(1, min(len(topology.buses), usable_cores()))


def bus_groups(topology: Topology, processes: int | None = None) -> list[tuple[str, ...]]:
    """The buses of each process: one bus each (``processes`` None), else ``processes``
    groups (at most one per bus) with as even a share of the boards as can be, each
    group's buses in topology order."""
    specs = list(topology.buses)
    count = len(specs) if processes is None else max(1, min(processes, len(specs)))
    groups: list[list[int]] = [[] for _ in range(count)]
    boards = [0] * count
    for index in sorted(range(len(specs)), key=lambda i: -len(specs[i].boards)):
        lightest = min(range(count), key=lambda g: (boards[g], len(groups[g]), g))
        groups[lightest].append(index)
        boards[lightest] += len(specs[index].boards)
    return sorted((tuple(specs[i].name for i in sorted(group)) for group in groups),
                  key=lambda names: [s.name for s in specs].index(names[0]))


@contextlib.contextmanager
def sigterm_interrupts() -> Iterator[None]:
    """SIGTERM raises KeyboardInterrupt meanwhile, as Ctrl-C does (in the main thread)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)



# ---------------------------------------------------------------------- a bus process
class _Terminated(Exception):
    """SIGTERM in a bus process: stop as when asked."""


def bus_process_main(channel: socket.socket, config: BusConfig) -> None:
    """The entry point of a bus process (spawned)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    logging.basicConfig(level=config.log_level, format=LOG_FORMAT, stream=sys.stderr)
    if config.switch_interval is not None:
        sys.setswitchinterval(config.switch_interval)
    BusServer(channel, config).run()


class BusServer:
    """The buses of a fleet in their process: a fleet of those buses, paced, and the
    clients the main process hands over, each served by a
    :class:`~ucom_tools.virtual.socketcand.Connection` from its open on."""

    def __init__(self, channel: socket.socket, config: BusConfig) -> None:
        self.channel = channel
        self.config = config
        self._connections: dict[int, Connection] = {}
        self._threads: dict[int, threading.Thread] = {}
        self._lock = threading.Lock()
        self._send_lock = threading.Lock()

    def run(self) -> None:
        def terminated(signum: int, frame: Any) -> None:
            raise _Terminated

        signal.signal(signal.SIGTERM, terminated)
        config = self.config
        try:
            fleet = Fleet(replace(config.topology, buses=tuple(
                              config.topology.bus(name) for name in config.buses)),
                          state_dir=config.state_dir, realtime=True, **config.fleet_options)
        except _Terminated:
            return
        except UcomError as err:
            kind = ("input" if isinstance(err, InputError) else
                    "bus" if isinstance(err, BusError) else "other")
            self._send(("error", kind, str(err)))
            return
        except Exception as err:
            self._send(("crash", traceback.format_exc(), f"{type(err).__name__}: {err}"))
            return
        try:
            # frame timestamps: the wall clock's, like every other bus process's
            fleet.epoch = time.time() - fleet.now_us() / 1e6
            self._send(("ready", os.getpid()))
            self._serve(fleet)
        except _Terminated:
            pass
        finally:
            signal.signal(signal.SIGTERM, signal.SIG_IGN)
            self._close(fleet)

    def _serve(self, fleet: Fleet) -> None:
        """Take clients from the main process until it says stop or is gone."""
        while True:
            try:
                message, fds, _flags, _address = socket.recv_fds(self.channel, _MESSAGE_MAX, 1)
            except OSError:
                return
            if not message:
                return
            request = pickle.loads(message)
            if request[0] == "stop":
                for fd in fds:
                    os.close(fd)
                return
            if request[0] == "client" and len(fds) == 1:
                _, key, address, bus, pending = request
                self._start_client(fleet, key, socket.socket(fileno=fds[0]), address, bus,
                                   pending)
            else:  # e.g. no descriptor came along (the process has too many open)
                for fd in fds:
                    os.close(fd)
                log.error("unexpected control message %r with %d descriptors", request[0],
                          len(fds))
                if request[0] == "client":
                    self._send(("done", request[1]))  # its slot is free again

    def _start_client(self, fleet: Fleet, key: int, sock: socket.socket, address: Any,
                      bus: str, pending: bytes) -> None:
        sock.settimeout(None)
        conn = Connection(sock, address, fleet, self.config.max_queued_frames)
        thread = threading.Thread(target=self._serve_client, args=(key, conn, bus, pending),
                                  daemon=True, name=f"ucom-serve-{conn.peer}")
        with self._lock:
            self._connections[key] = conn
            self._threads[key] = thread
        thread.start()

    def _serve_client(self, key: int, conn: Connection, bus: str, pending: bytes) -> None:
        try:
            conn.resume(bus, pending)
        except Exception:
            log.error("unexpected error serving %s", conn.peer, exc_info=True)
        finally:
            with contextlib.suppress(OSError):
                conn.sock.shutdown(socket.SHUT_WR)
            conn.sock.close()
            with self._lock:
                self._connections.pop(key, None)
                self._threads.pop(key, None)
            self._send(("done", key))
            conn.log_end()

    def _send(self, message: tuple[Any, ...]) -> None:
        with contextlib.suppress(OSError), self._send_lock:
            self.channel.send(pickle.dumps(message))

    def _close(self, fleet: Fleet) -> None:
        """Close every client, wait for their threads, stop the fleet."""
        with self._lock:
            connections = list(self._connections.values())
            threads = list(self._threads.values())
        for conn in connections:
            conn.close()
        deadline = time.monotonic() + 2 * FLUSH_S
        for thread in threads:
            thread.join(max(0.0, deadline - time.monotonic()))
        fleet.close()
        with contextlib.suppress(OSError):
            self.channel.close()
