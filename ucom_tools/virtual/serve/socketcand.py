"""Serve a virtual fleet with the socketcand protocol (raw mode), so that python-can's
``socketcand`` interface - and any socketcand client - reaches the boards from another
process.  One TCP connection opens one bus; frames a client sends go onto the simulated
bus in real time, every frame on the bus goes to every other client of that bus::

    server  < hi >
    client  < open CAN0 >               server  < ok >
    client  < rawmode >                 server  < ok >      (then 20 ms, see below)
    client  < send 280 2 1 0 >          server  < frame 0C1 1700000000.000345 01... >
    client  < echo >                    server  < echo >

``send`` takes an identifier of 1-3 hex digits (0..7FF, a standard frame) or of exactly
8 (0..1FFFFFFF, an extended frame, as socketcand decides), a DLC of one hex digit 0..8
and exactly DLC data bytes of 1-2 hex digits each (python-can sends them unpadded).
Extended frames go onto the simulated bus like any other (their own length and
arbitration, :mod:`~ucom_tools.virtual.bus.simbus`); the boards ignore them, the other
clients of the bus get them as ``< frame 1ABCDEF0 SEC.USEC DATA >`` (8 hex digits).
Whatever else a client sends - a malformed or unknown element, non-ASCII bytes, a
command before ``open``, a second ``open`` - is answered with ``< error ... >`` and the
client stays connected.

In raw mode that answer ends without the blank before ``>``: ``< error DLC 9 above 8>``
(:func:`~ucom_tools.wire.socketcand.error_element`).  There ``< error ... >`` is the
protocol's element for an error frame, ``< error CLASS SEC.USEC >``, and python-can's
client (4.6) takes every element that starts with ``< error `` and ends with `` >`` for
one: it raises on any other text, on that ``recv`` and on every later one that reads more
(it parses its buffer again), and the frames behind it are lost.  An element that does
not end with `` >`` it logs as one it cannot parse and goes on, so a python-can client
that sends a frame the server refuses (a remote frame with a DLC, a CAN FD frame) sees a
warning and keeps working.

No client can stop the bus or another client:

* Input is read in chunks and cut into elements; an element may be at most
  :data:`~ucom_tools.wire.socketcand.MAX_ELEMENT` bytes.  A longer one gets
  ``< error element too long >`` and the client is closed.  Bytes outside elements, and
  an unfinished element that a new ``<`` interrupts, are skipped.
* Output goes through a bounded queue per client
  (:class:`~ucom_tools.virtual.serve.outbox.Outbox`) that the bus fills
  without ever waiting, and a writer thread per client empties it outside the bus lock.
  A client that stops reading until its queue overflows is dropped.
* Back-pressure: a client's frames wait in a transmit queue of
  :data:`~ucom_tools.virtual.bus.simbus.TX_QUEUE` frames, like a CAN adapter's.  While it is
  full the server does not read that client's socket, so TCP slows a client that sends
  faster than the bus carries frames; the wait releases the bus lock, and a client that
  disconnects meanwhile is noticed and cleaned up.
* At most ``max_clients`` connections; one more gets ``< error too many clients (N) >``
  and is closed.

python-can's client reads ``< hi >`` and each ``< ok >`` with a single ``recv(256)``
and fails if anything arrives glued to them.  So after the rawmode ``< ok >`` the server
waits until it is written, then
:data:`~ucom_tools.virtual.serve.connection.RAWMODE_SETTLE_S` (20 ms), and only then
attaches the client to the bus.  From then on ``< echo >`` is answered after the fleet's
next step (behind the frames of that step), as the answer to a frame would come: the
client's measured round trip holds the server's step latency.

A connection can also start in another process: :mod:`ucom_tools.virtual.serve.multiserve`
greets the client and reads its ``< open BUS >`` with
:class:`~ucom_tools.wire.socketcand.ElementSplitter` and
:func:`~ucom_tools.virtual.serve.elements.check_open`, then hands the socket to the
process of that bus, which goes on with :meth:`Connection.resume`; the answers are the
same as :meth:`Connection.run` gives.

The server is in modules by job: this one accepts connections (:class:`ClientServer`,
:class:`FleetServer`); :mod:`~ucom_tools.virtual.serve.connection` serves one client
(:class:`~ucom_tools.virtual.serve.connection.Connection`);
:mod:`~ucom_tools.virtual.serve.outbox` queues what is written to it;
:class:`~ucom_tools.virtual.bus.loss.FrameLoss` loses frames for ``--loss``; the elements
themselves are :mod:`ucom_tools.wire.socketcand`, shared with the client.

Binds to 127.0.0.1 by default; every accepted connection has TCP_NODELAY set.  The
server logs to the ``ucom.serve`` logger: connections at INFO, dropped and refused
clients at WARNING; a lost client never causes a traceback.
"""

from __future__ import annotations

import contextlib
import logging
import socket
import socketserver
import threading
from typing import Any

from ucom_tools.virtual.fleet import Fleet
from ucom_tools.virtual.serve.connection import Connection
from ucom_tools.virtual.serve.elements import peer_name
from ucom_tools.virtual.serve.outbox import MAX_QUEUED_FRAMES

log = logging.getLogger("ucom.serve")

DEFAULT_PORT = 29536
MAX_CLIENTS = 16
"""Connections served at once (``FleetServer(max_clients=...)``)."""


class _Handler(socketserver.BaseRequestHandler):
    server: ClientServer

    def handle(self) -> None:
        self.server.serve_client(self.request, self.client_address)


class ClientServer(socketserver.ThreadingTCPServer):
    """A threaded TCP server for socketcand clients, at most ``max_clients`` at once: one
    more is told ``< error too many clients (N) >`` and closed.  Subclasses serve a client
    in :meth:`serve_client` (its handler thread) and may note its end in
    :meth:`client_ended`."""

    daemon_threads = True
    allow_reuse_address = True
    request_queue_size = 32

    def __init__(self, host: str, port: int, *, max_clients: int = MAX_CLIENTS) -> None:
        if max_clients < 1:
            raise ValueError("max_clients must be at least 1")
        self.max_clients = max_clients
        self._slots = threading.BoundedSemaphore(max_clients)
        super().__init__((host, port), _Handler)

    @property
    def address(self) -> tuple[str, int]:
        host, port = self.server_address[:2]
        return str(host), int(port)

    def serve_client(self, sock: socket.socket, address: Any) -> None:
        raise NotImplementedError

    def client_ended(self, sock: socket.socket) -> None:
        """After a client's connection is closed and its slot is free again."""

    def process_request(self, request: Any, client_address: Any) -> None:
        if not self._slots.acquire(blocking=False):
            self._refuse(request, client_address)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            self._slots.release()
            raise

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)  # closes the socket
        finally:
            self._slots.release()
            self.client_ended(request)

    def _refuse(self, request: socket.socket, client_address: Any) -> None:
        log.warning("refused client %s: too many clients (%d)", peer_name(client_address),
                    self.max_clients)
        with contextlib.suppress(OSError):
            request.sendall(f"< error too many clients ({self.max_clients}) >".encode())
        self.shutdown_request(request)

    def handle_error(self, request: Any, client_address: Any) -> None:
        log.error("unexpected error serving %s", peer_name(client_address), exc_info=True)


class FleetServer(ClientServer):
    """socketcand's raw mode for every bus of one fleet, in this process."""

    def __init__(self, fleet: Fleet, host: str = "127.0.0.1", port: int = DEFAULT_PORT, *,
                 max_clients: int = MAX_CLIENTS,
                 max_queued_frames: int = MAX_QUEUED_FRAMES) -> None:
        if max_queued_frames < 1:
            raise ValueError("max_queued_frames must be at least 1")
        self.fleet = fleet
        self.max_queued_frames = max_queued_frames
        self._connections: dict[socket.socket, Connection] = {}
        self._connections_lock = threading.Lock()
        super().__init__(host, port, max_clients=max_clients)

    def connections(self) -> list[Connection]:
        """The clients being served now."""
        with self._connections_lock:
            return list(self._connections.values())

    def serve_client(self, sock: socket.socket, address: Any) -> None:
        """Serve one accepted client (in its handler thread)."""
        conn = Connection(sock, address, self.fleet, self.max_queued_frames)
        with self._connections_lock:
            self._connections[sock] = conn
        conn.run()

    def client_ended(self, sock: socket.socket) -> None:
        with self._connections_lock:
            conn = self._connections.pop(sock, None)
        if conn is not None:
            conn.log_end()

    def server_close(self) -> None:
        """Stop listening and close every client."""
        super().server_close()
        for conn in self.connections():
            conn.close()


def serve_until_interrupted(server: FleetServer) -> None:
    """Serve in a thread until Ctrl-C, then shut the server down, close its clients and
    raise the interrupt on (the command's exit code says how it ended)."""
    thread = threading.Thread(target=server.serve_forever, name="ucom-socketcand", daemon=True)
    thread.start()
    try:
        while thread.is_alive():
            thread.join(0.2)
    finally:
        server.shutdown()
        server.server_close()
