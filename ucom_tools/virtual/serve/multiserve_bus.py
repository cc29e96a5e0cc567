"""One bus process of a multi-process ``ucom fleet serve``
(:mod:`ucom_tools.virtual.serve.multiserve`, which says why and how): what it is given
(:class:`BusConfig`), the main process's handle that starts, feeds and stops it
(:class:`BusProcess`), and the process itself (:func:`bus_process_main`,
:class:`BusServer`), which serves the clients handed over to it from their open on.
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

from ucom_tools.config.scenario import InjectedFault, Scenario
from ucom_tools.config.topology import Topology
from ucom_tools.errors import BusError, InputError, UcomError
from ucom_tools.virtual.fleet import Fleet
from ucom_tools.virtual.serve.connection import FLUSH_S, Connection
from ucom_tools.virtual.serve.outbox import MAX_QUEUED_FRAMES

log = logging.getLogger("ucom.serve")

LOG_FORMAT = "ucom fleet serve: %(message)s"
"""How ``ucom fleet serve`` logs, in every process."""
_MESSAGE_MAX = 1 << 17
"""Largest control message (a handover: a few hundred bytes plus at most two chunks)."""


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
        self._faults: dict[int, tuple[threading.Event, list[tuple[str, str]]]] = {}
        """Faults sent to the process and not yet answered: done, and (kind, text)."""
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

    def send_fault(self, fault: InjectedFault) -> Callable[[float], str]:
        """Ask the process to apply ``fault`` (to its fleet: its buses); returns the wait
        for its answer, ``wait(timeout)``: what was done, or InputError / BusError."""
        key = next(self._ids)
        done = threading.Event()
        answer: list[tuple[str, str]] = []
        with self._lock:
            ended = self.ended.is_set()
            if not ended:
                self._faults[key] = (done, answer)
        if not ended:
            try:
                with self._send_lock:
                    self._channel.send(pickle.dumps(("fault", key, fault)))
            except OSError:
                ended = True
        label = self.label

        def wait(timeout: float) -> str:
            if ended:
                raise BusError(f"the process of {label} has ended: no fault applied")
            if not done.wait(timeout):
                with self._lock:
                    self._faults.pop(key, None)
                raise BusError(f"the process of {label} did not apply the fault in "
                               f"{timeout:g} s")
            if not answer:
                raise BusError(f"the process of {label} ended before it applied the fault")
            kind, text = answer[0]
            if kind == "ok":
                return text
            raise InputError(text) if kind == "input" else BusError(text)
        return wait

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
                asked = [done for done, _ in self._faults.values()]
                self._faults.clear()
            for done in handed + asked:
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
        elif kind == "fault-done":
            _, key, outcome, text = message
            with self._lock:
                waiting = self._faults.pop(key, None)
            if waiting is not None:
                waiting[1].append((outcome, text))
                waiting[0].set()
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


class _Terminated(Exception):
    """SIGTERM in a bus process: stop as when asked."""


def bus_process_main(channel: socket.socket, config: BusConfig) -> None:
    """The entry point of a bus process (spawned)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    logging.basicConfig(level=config.log_level, format=LOG_FORMAT, stream=sys.stderr)
    logging.getLogger("ucom.fleet").setLevel(logging.INFO)  # a scenario's faults, as they
    # happen
    if config.switch_interval is not None:
        sys.setswitchinterval(config.switch_interval)
    BusServer(channel, config).run()


class BusServer:
    """The buses of a fleet in their process: a fleet of those buses, paced, and the
    clients the main process hands over, each served by a
    :class:`~ucom_tools.virtual.serve.connection.Connection` from its open on."""

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
        options = dict(config.fleet_options)
        scenario = options.get("scenario")
        if isinstance(scenario, Scenario):  # this process's buses' faults and the robot's
            options["scenario"] = scenario.only(config.buses)
        try:
            fleet = Fleet(replace(config.topology, buses=tuple(
                              config.topology.bus(name) for name in config.buses)),
                          state_dir=config.state_dir, realtime=True, **options)
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
            if request[0] == "fault" and not fds:
                threading.Thread(target=self._fault, args=(fleet, request[1], request[2]),
                                 daemon=True, name="ucom-serve-fault").start()
                continue
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

    def _fault(self, fleet: Fleet, key: int, fault: InjectedFault) -> None:
        """Apply a fault the main process was asked for; answer it (in a thread of its
        own: the control channel keeps taking clients meanwhile)."""
        try:
            outcome, text = "ok", fleet.inject(fault)
        except UcomError as err:
            outcome, text = ("input" if isinstance(err, InputError) else "bus"), str(err)
        except Exception as err:
            log.exception("applying a fault failed")
            outcome, text = "bus", f"{type(err).__name__}: {err}"
        self._send(("fault-done", key, outcome, text))

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
