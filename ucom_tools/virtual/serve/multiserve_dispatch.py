"""The main process of a multi-process ``ucom fleet serve``
(:mod:`ucom_tools.virtual.serve.multiserve`): its TCP server (:class:`ClientRouter`) greets each
client, answers its elements up to ``< open BUS >`` as one process would
(:class:`Reception`), then hands the connection to the process of that bus.  A fault a
client asks for (``< ucom_fault ... >``, before any open) goes to the process of its bus,
a fault of the whole robot to every process at once (:meth:`ClientRouter.inject`).
"""

from __future__ import annotations

import contextlib
import logging
import socket
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from ucom_tools.config.scenario import InjectedFault
from ucom_tools.config.topology import Topology
from ucom_tools.virtual.serve.elements import (
    NO_BUS_OPEN,
    check_open,
    inject_element,
    peer_name,
    unsupported,
)
from ucom_tools.virtual.serve.socketcand import MAX_CLIENTS, ClientServer
from ucom_tools.wire import socketcand_fault
from ucom_tools.wire.socketcand import (
    MAX_ELEMENT,
    ElementError,
    ElementSplitter,
    ElementTooLong,
    element_words,
    error_element,
)

if TYPE_CHECKING:
    from ucom_tools.virtual.serve.multiserve_bus import BusProcess

log = logging.getLogger("ucom.serve")

FAULT_TIMEOUT_S = 10.0
"""How long the main process waits for the bus processes to apply a fault."""
REPLY_TIMEOUT_S = 5.0
"""How long the main process waits to write one answer to a client that has not opened a
bus yet; a client that does not read it meanwhile is dropped."""
_RECV_SIZE = 4096


class _Dropped(Exception):
    """A client the main process closes before it opened a bus (logged as a warning)."""


class Reception:
    """A client of the main process from its greeting to its ``< open BUS >``: answers the
    elements before (as :class:`~ucom_tools.virtual.serve.connection.Connection` does) and
    returns the bus to open and the bytes the client sent after the open."""

    def __init__(self, sock: socket.socket, address: Any, buses: dict[str, BusProcess],
                 fleet_name: str, inject: Callable[[InjectedFault], str] | None = None,
                 ) -> None:
        self.sock = sock
        self.peer = peer_name(address)
        self.buses = buses
        self.fleet_name = fleet_name
        self.inject = inject
        """Applies a fault a client asks for (:meth:`ClientRouter.inject`)."""
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
            if verb == socketcand_fault.COMMAND and self.inject is not None:
                answer = inject_element(args, self.inject)
                self._reply(answer)
                log.warning("client %s injected a fault: %s", self.peer,
                            answer[len("< ok "):-2])
                return None
            if verb in ("rawmode", "send"):
                raise ElementError(NO_BUS_OPEN)
            raise unsupported(verb)
        except ElementError as err:
            self._reply(error_element(str(err)))
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


class ClientRouter(ClientServer):
    """The main process's TCP server: greets each client, reads up to its open and hands
    it to the process of that bus; counts the connections of every bus."""

    def __init__(self, host: str, port: int, buses: dict[str, BusProcess], fleet_name: str,
                 *, max_clients: int = MAX_CLIENTS, topology: Topology | None = None) -> None:
        self.buses = buses
        self.fleet_name = fleet_name
        self.topology = topology
        """The whole fleet's topology (faults are checked against it); None: this server
        takes no faults."""
        self._receptions: set[Reception] = set()
        self._lock = threading.Lock()
        self._closed = False
        super().__init__(host, port, max_clients=max_clients)

    def serve_client(self, sock: socket.socket, address: Any) -> None:
        """One accepted client, in its handler thread: until it opened a bus here, then
        until its bus process is done with it (the slot stays taken meanwhile)."""
        reception = Reception(sock, address, self.buses, self.fleet_name,
                              self.inject if self.topology is not None else None)
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

    def inject(self, fault: InjectedFault) -> str:
        """Apply ``fault`` in the process of its bus, or (the whole robot) in every process
        at once, and say what was done; InputError for a bus or board the fleet lacks,
        BusError when a process does not apply it within :data:`FAULT_TIMEOUT_S`."""
        topology = self.topology
        assert topology is not None
        fault.check(topology)
        if fault.bus is not None:
            workers = [self.buses[fault.bus]]
        else:
            workers = list(dict.fromkeys(self.buses.values()))  # each process once
        waits = [worker.send_fault(fault) for worker in workers]  # all asked, then waited
        texts = [wait(FAULT_TIMEOUT_S) for wait in waits]
        if fault.bus is None:
            return fault.describe(topology, topology.timing.reset_us / 1e6)
        return texts[0]

    def server_close(self) -> None:
        """Stop listening and close the clients that have not opened a bus."""
        super().server_close()
        with self._lock:
            self._closed = True
            receptions = list(self._receptions)
        for reception in receptions:
            reception.close()
