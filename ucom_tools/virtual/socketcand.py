"""Serve a virtual fleet with the socketcand protocol (raw mode), so that python-can's
``socketcand`` interface - and any socketcand client - reaches the boards from another
process.  One TCP connection opens one bus (``< open CAN0 >``); frames a client sends go
onto the simulated bus in real time, every frame on the bus goes to every other client.

Binds to 127.0.0.1 by default.
"""

from __future__ import annotations

import contextlib
import socket
import socketserver
import threading
import time

from ucom_tools.virtual.canbus import wait_for_room
from ucom_tools.virtual.fleet import Fleet
from ucom_tools.virtual.simbus import SimBus

DEFAULT_PORT = 29536


class ClientPort:
    """A socketcand client's attachment to one simulated bus."""

    def __init__(self, sock: socket.socket, fleet: Fleet, sim: SimBus) -> None:
        self.sock = sock
        self.fleet = fleet
        self.sim = sim
        self.lock = threading.Lock()
        self.alive = True

    def on_frame(self, arbitration_id: int, data: bytes, t_end: float) -> None:
        ts = self.fleet.epoch + t_end / 1e6
        line = f"< frame {arbitration_id:03X} {ts:.6f} {data.hex().upper()} >"
        self.write(line)

    def write(self, text: str) -> None:
        if not self.alive:
            return
        try:
            with self.lock:
                self.sock.sendall(text.encode("ascii"))
        except OSError:
            self.alive = False


class _Handler(socketserver.BaseRequestHandler):
    server: FleetServer

    def handle(self) -> None:
        sock: socket.socket = self.request
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        fleet = self.server.fleet
        sock.sendall(b"< hi >")
        port: ClientPort | None = None
        buffer = ""
        try:
            while True:
                chunk = sock.recv(65536)
                if not chunk:
                    return
                buffer += chunk.decode("ascii", "replace")
                while True:
                    start = buffer.find("<")
                    end = buffer.find(">", start + 1)
                    if start < 0 or end < 0:
                        if start < 0:
                            buffer = ""
                        break
                    command = buffer[start + 1:end].split()
                    buffer = buffer[end + 1:]
                    port = self._command(sock, fleet, port, command)
        finally:
            if port is not None:
                port.alive = False
                port.sim.detach(port)

    def _command(self, sock: socket.socket, fleet: Fleet, port: ClientPort | None,
                 words: list[str]) -> ClientPort | None:
        if not words:
            return port
        verb = words[0]
        if verb == "open" and port is None and len(words) == 2:
            if words[1] not in fleet.buses:
                sock.sendall(f"< error no bus {words[1]} in {fleet.name} >".encode())
                return None
            port = ClientPort(sock, fleet, fleet.buses[words[1]])
            sock.sendall(b"< ok >")
            return port
        if verb == "rawmode" and port is not None:
            port.write("< ok >")
            # Clients such as python-can read the "< ok >" with one recv(); give it time to
            # arrive alone before bus traffic starts flowing to this client.
            time.sleep(0.02)
            port.sim.attach(port)
            return port
        if verb == "send" and port is not None and len(words) >= 3:
            try:
                arb = int(words[1], 16)
                dlc = int(words[2], 16)
                data = bytes(int(x, 16) for x in words[3:3 + dlc])
            except ValueError:
                port.write("< error malformed send >")
                return port
            if arb > 0x7FF or dlc > 8 or len(data) != dlc or len(words[1]) > 3:
                port.write("< error only CAN 2.0A frames (11-bit id, DLC <= 8) >")
                return port
            sim = port.sim
            with sim.changed:
                # Back-pressure: the next command is read only when there is room, so TCP
                # throttles a client that sends faster than the bus carries frames.
                wait_for_room(sim, port, None)
                sim.send(port, fleet.now_us(sim), arb, data)
                sim.changed.notify_all()
            return port
        if verb == "echo" and port is not None:
            port.write("< echo >")
            return port
        if port is not None:
            port.write(f"< error unsupported command {verb} >")
        return port


class FleetServer(socketserver.ThreadingTCPServer):
    """A threaded TCP server speaking socketcand's raw mode for one fleet."""

    daemon_threads = True
    allow_reuse_address = True

    def __init__(self, fleet: Fleet, host: str = "127.0.0.1", port: int = DEFAULT_PORT) -> None:
        self.fleet = fleet
        super().__init__((host, port), _Handler)

    @property
    def address(self) -> tuple[str, int]:
        host, port = self.server_address[:2]
        return str(host), int(port)


def serve_until_interrupted(server: FleetServer) -> None:
    """Serve in a thread until Ctrl-C, then shut the server down."""
    thread = threading.Thread(target=server.serve_forever, name="ucom-socketcand", daemon=True)
    thread.start()
    with contextlib.suppress(KeyboardInterrupt):
        while thread.is_alive():
            thread.join(0.2)
    server.shutdown()
