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
arbitration, :mod:`~ucom_tools.virtual.simbus`); the boards ignore them, the other
clients of the bus get them as ``< frame 1ABCDEF0 SEC.USEC DATA >`` (8 hex digits).
Whatever else a client sends - a malformed or unknown element, non-ASCII bytes, a
command before ``open``, a second ``open`` - is answered with ``< error ... >`` and the
client stays connected.

In raw mode that answer ends without the blank before ``>``: ``< error DLC 9 above 8>``
(:func:`error_element`).  There ``< error ... >`` is the protocol's element for an error
frame, ``< error CLASS SEC.USEC >``, and python-can's client (4.6) takes every element
that starts with ``< error `` and ends with `` >`` for one: it raises on any other text,
on that ``recv`` and on every later one that reads more (it parses its buffer again), and
the frames behind it are lost.  An element that does not end with `` >`` it logs as one
it cannot parse and goes on, so a python-can client that sends a frame the server
refuses (a remote frame with a DLC, a CAN FD frame) sees a warning and keeps working.

No client can stop the bus or another client:

* Input is read in chunks and cut into elements; an element may be at most
  :data:`MAX_ELEMENT` bytes.  A longer one gets ``< error element too long >`` and the
  client is closed.
* Output goes through a bounded queue per client (:class:`Outbox`) that the bus fills
  without ever waiting, and a writer thread per client empties it outside the bus lock.
  A client that stops reading until its queue overflows is dropped.
* Back-pressure: a client's frames wait in a transmit queue of
  :data:`~ucom_tools.virtual.simbus.TX_QUEUE` frames, like a CAN adapter's.  While it is
  full the server does not read that client's socket, so TCP slows a client that sends
  faster than the bus carries frames; the wait releases the bus lock, and a client that
  disconnects meanwhile is noticed and cleaned up.
* At most ``max_clients`` connections; one more gets ``< error too many clients (N) >``
  and is closed.

python-can's client reads ``< hi >`` and each ``< ok >`` with a single ``recv(256)``
and fails if anything arrives glued to them.  So after the rawmode ``< ok >`` the server
waits until it is written, then :data:`RAWMODE_SETTLE_S` (20 ms), and only then attaches
the client to the bus.

A connection can also start in another process: :mod:`ucom_tools.virtual.multiserve`
greets the client and reads its ``< open BUS >`` with :class:`ElementSplitter` and
:func:`check_open`, then hands the socket to the process of that bus, which goes on with
:meth:`Connection.resume`; the answers are the same as :meth:`Connection.run` gives.

Binds to 127.0.0.1 by default; every accepted connection has TCP_NODELAY set.  The
server logs to the ``ucom.serve`` logger: connections at INFO, dropped and refused
clients at WARNING; a lost client never causes a traceback.
"""

from __future__ import annotations

import binascii
import contextlib
import itertools
import logging
import random
import re
import select
import socket
import socketserver
import threading
import time
from collections import deque
from collections.abc import Callable, Collection
from typing import Any

import can

from ucom_tools.virtual.fleet import HOST_AHEAD_US, Fleet, _send
from ucom_tools.virtual.simbus import TX_QUEUE, SimBus

log = logging.getLogger("ucom.serve")

DEFAULT_PORT = 29536
MAX_CLIENTS = 16
"""Connections served at once (``FleetServer(max_clients=...)``)."""
MAX_QUEUED_FRAMES = 10_000
"""Frames and replies that may wait for one client; one more and it is dropped."""
MAX_ELEMENT = 4096
"""Longest element a client may send, ``<`` and ``>`` included, in bytes."""
RAWMODE_SETTLE_S = 0.02
"""Pause between the rawmode ``< ok >`` and the first frame (python-can compatibility)."""
ROOM_POLL_S = 0.1
"""How often a client waiting for room in its transmit queue is checked for liveness."""
FLUSH_S = 1.0
"""How long the server waits for a last reply to be written before closing a client."""
_RECV_SIZE = 4096
_WRITE_BATCH = 512
_HEX = re.compile(r"[0-9A-Fa-f]+")
CAN_EFF_FLAG = 0x80000000
"""Marks an extended frame's identifier in this module, as in SocketCAN's ``can_id``
(what socketcand passes to the kernel): :func:`parse_send` returns it, the lines of a
client's :class:`Outbox` carry it."""
CAN_EFF_MASK = 0x1FFFFFFF
_PLAIN_SEND = re.compile(rb" ?send ([0-9A-Fa-f]{1,3}) ([0-8])((?: [0-9A-Fa-f]{1,2}){0,8}) ?")
"""A ``send`` element as clients write it (single spaces), parsed in one match."""
_DONTWAIT = getattr(socket, "MSG_DONTWAIT", 0)
NO_BUS_OPEN = "no bus open: send < open BUS > first"
"""The answer to ``rawmode`` and ``send`` before a bus is open."""

Frame = tuple[int, bytes, float]
"""A frame for a client: identifier (with :data:`CAN_EFF_FLAG` if extended), data, end
time on the bus (virtual microseconds)."""
Line = bytes | Frame
"""What a client's writer sends: an encoded reply or a frame."""


class ElementError(Exception):
    """An element the server answers with ``< error MESSAGE >``."""


class ElementTooLong(ElementError):
    """An element longer than :data:`MAX_ELEMENT`; the client is closed."""


# ---------------------------------------------------------------------- parsing
class ElementSplitter:
    """Cuts a client's byte stream into ``< ... >`` elements, holding at most ``limit``
    bytes of an unfinished one; bytes between elements are skipped."""

    def __init__(self, limit: int = MAX_ELEMENT) -> None:
        self.limit = limit
        self._buffer = bytearray()
        self._pos = 0
        """Where the unread part of the buffer starts: the elements taken are dropped at
        the next :meth:`feed`, not one at a time (a chunk of many is cut in linear time)."""

    def feed(self, chunk: bytes) -> None:
        if self._pos:
            del self._buffer[:self._pos]
            self._pos = 0
        self._buffer += chunk

    def next(self) -> bytes | None:
        """The text between ``<`` and ``>`` of the next complete element, or None;
        raises :class:`ElementTooLong` instead of holding more than ``limit`` bytes."""
        buf = self._buffer
        start = buf.find(b"<", self._pos)
        if start < 0:
            buf.clear()
            self._pos = 0
            return None
        end = buf.find(b">", start + 1)
        if end < 0:
            del buf[:start]
            self._pos = 0
            if len(buf) >= self.limit:  # its ">" would make it longer than the limit
                raise ElementTooLong("element too long")
            return None
        if end + 1 - start > self.limit:
            self._pos = start
            raise ElementTooLong("element too long")
        self._pos = end + 1
        return bytes(buf[start + 1:end])

    def rest(self) -> bytes:
        """The bytes fed and not yet returned as elements (and forget them): what a
        process that hands a connection over sends along."""
        rest = bytes(self._buffer[self._pos:])
        self._buffer.clear()
        self._pos = 0
        return rest


def element_words(element: bytes) -> list[str]:
    """The words of an element's text; non-ASCII or empty elements are errors."""
    try:
        words = element.decode("ascii").split()
    except UnicodeDecodeError:
        raise ElementError("non-ASCII bytes in element") from None
    if not words:
        raise ElementError("empty element")
    return words


def check_open(args: list[str], buses: Collection[str], fleet_name: str,
               already_open: str | None = None) -> str:
    """The bus that ``< open BUS >`` (the words after ``open``) names; ElementError with
    the server's answer when it is malformed, a bus is open already, or no such bus."""
    if len(args) != 1:
        raise ElementError("usage: open BUS")
    if already_open is not None:
        raise ElementError(f"bus {already_open} is already open")
    if args[0] not in buses:
        raise ElementError(f"no bus {_quote(args[0])} in {fleet_name}")
    return args[0]


def unsupported(verb: str) -> ElementError:
    """The answer to an element with an unknown command word."""
    return ElementError(f"unsupported command {_quote(verb)}")


def error_element(text: str, raw: bool = False) -> str:
    """The answer to a malformed element: ``< error TEXT >``, in raw mode ``< error
    TEXT>`` (no blank before ``>``: not an error frame to python-can's client, see the
    module's description)."""
    return f"< error {text}>" if raw else f"< error {text} >"


def parse_send(args: list[str]) -> tuple[int, bytes]:
    """Identifier and data of ``< send ID DLC B0 B1 .. >`` from the words after ``send``;
    an extended frame's identifier (8 hex digits) carries :data:`CAN_EFF_FLAG`."""
    if len(args) < 2:
        raise ElementError("usage: send ID DLC DATA...")
    ident, dlc_text, *byte_words = args
    arbitration_id = _identifier(ident)
    dlc = _dlc(dlc_text)
    if len(byte_words) != dlc:
        raise ElementError(f"DLC {dlc} but {len(byte_words)} data bytes")
    return arbitration_id, bytes(_data_byte(w) for w in byte_words)


def _identifier(text: str) -> int:
    """A standard identifier (1-3 hex digits) or an extended one (8, with the flag)."""
    if not _HEX.fullmatch(text) or len(text) not in (1, 2, 3, 8):
        raise ElementError(f"bad identifier {_quote(text)}: 1-3 hex digits (11 bit) "
                           "or 8 (29 bit)")
    value = int(text, 16)
    if len(text) == 8:
        if value > CAN_EFF_MASK:
            raise ElementError(f"extended identifier {text} above 1FFFFFFF")
        return value | CAN_EFF_FLAG
    if value > 0x7FF:
        raise ElementError(f"identifier {text} above 7FF")
    return value


def _dlc(text: str) -> int:
    if len(text) != 1 or not _HEX.fullmatch(text):
        raise ElementError(f"bad DLC {_quote(text)}: one hex digit 0..8")
    value = int(text, 16)
    if value > 8:
        raise ElementError(f"DLC {text} above 8")
    return value


def _data_byte(text: str) -> int:
    if len(text) > 2 or not _HEX.fullmatch(text):
        raise ElementError(f"bad data byte {_quote(text)}: 1-2 hex digits")
    return int(text, 16)


def _plain_send(element: bytes) -> tuple[int, bytes] | None:
    """Identifier and data of a well-formed ``send`` element in the form clients write
    (``send 280 2 01 00``, single spaces), or None: then the general way decides,
    :func:`element_words` and :func:`parse_send`, which accept the same frames."""
    m = _PLAIN_SEND.fullmatch(element)
    if m is None:
        return None
    arbitration_id = int(m[1], 16)
    if arbitration_id > 0x7FF:
        return None
    dlc = int(m[2])
    text = m[3]
    if len(text) == 3 * dlc and text.count(b" ") == dlc:  # every byte two digits
        return arbitration_id, bytes.fromhex(text.decode("ascii"))
    words = text.split()
    if len(words) != dlc:
        return None
    return arbitration_id, bytes([int(w, 16) for w in words])


def _quote(text: str, limit: int = 16) -> str:
    """``text`` safe to echo inside an element: printable ASCII, no ``<``, short."""
    shown = "".join(c if "!" <= c <= "~" and c != "<" else "?" for c in text[:limit])
    return shown + ("..." if len(text) > limit else "")


def _peer(address: Any) -> str:
    """A client's address as people write it: ``127.0.0.1:40000``, ``[::1]:40000``."""
    if isinstance(address, tuple) and len(address) >= 2:
        host = str(address[0])
        return f"[{host}]:{address[1]}" if ":" in host else f"{host}:{address[1]}"
    return str(address)


# ---------------------------------------------------------------------- output
class Outbox:
    """Lines waiting for one client.  Bounded, and :meth:`put` never blocks, so the bus
    thread hands each frame to every client without waiting for any.

    Replies (:meth:`put`) go to the client's writer thread, woken only when a line arrives
    in an empty queue (it waits only then).  Frames of a paced fleet (:meth:`put_quiet`)
    wake nobody: after the driver's step, :meth:`flush` writes every line waiting in one
    non-blocking send from the driver's thread; what the socket does not take then goes
    to the writer thread, which waits until it can write it."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self._lines: deque[Line] = deque()
        self._cond = threading.Condition(threading.Lock())
        self._closed = False
        self._writing = False
        self._flushing = False
        self._watchers = 0
        """Threads in :meth:`wait_written`."""
        self.deferred = False
        """A :meth:`flush` after the running step is asked for (the bus thread's flag)."""

    def put(self, line: Line) -> bool:
        """Queue ``line``; false if the queue is full (a closed outbox drops lines)."""
        with self._cond:
            lines = self._lines
            if self._closed:
                return True
            if len(lines) >= self.limit:
                return False
            lines.append(line)
            if len(lines) == 1:  # the writer may be waiting (it waits only when empty)
                self._cond.notify_all()
            return True

    def put_quiet(self, line: Line) -> bool:
        """Queue ``line`` without waking the writer (:meth:`flush` or :meth:`wake`
        follows); false if the queue is full.  One deque operation: no lock."""
        lines = self._lines
        if len(lines) >= self.limit:
            return self._closed
        lines.append(line)
        return True

    def wake(self) -> None:
        """Wake the writer for the lines :meth:`put_quiet` queued."""
        with self._cond:
            self.deferred = False
            if self._lines:
                self._cond.notify_all()

    def flush(self, send: Callable[[bytes], int], epoch: float) -> None:
        """Write every line waiting with one call of ``send`` (non-blocking: it returns
        how many bytes the socket took), unless the writer is busy (then it takes them);
        the rest goes to the writer.  ``OSError`` from ``send`` passes through."""
        with self._cond:
            self.deferred = False
            lines = self._lines
            if self._closed or self._writing or self._flushing or not lines:
                return
            batch = [lines.popleft() for _ in range(len(lines))]
            self._flushing = True
        data = b"".join([encode_line(line, epoch) for line in batch])
        sent = 0
        try:
            sent = send(data)
        finally:
            with self._cond:
                self._flushing = False
                if sent < len(data) and not self._closed:
                    self._lines.appendleft(data[sent:])
                if self._lines or self._watchers:
                    self._cond.notify_all()

    def take(self) -> list[Line] | None:
        """The writer's next batch (waits for one); None once the outbox is closed."""
        with self._cond:
            self._writing = False
            if self._watchers:
                self._cond.notify_all()
            while (not self._lines or self._flushing) and not self._closed:
                self._cond.wait()
            if self._closed:
                return None
            n = min(len(self._lines), _WRITE_BATCH)
            self._writing = True
            return [self._lines.popleft() for _ in range(n)]

    def wait_written(self, timeout: float) -> bool:
        """Wait until everything queued so far is written or the outbox is closed."""
        with self._cond:
            self._watchers += 1
            try:
                return self._cond.wait_for(
                    lambda: self._closed or not (self._lines or self._writing
                                                 or self._flushing), timeout)
            finally:
                self._watchers -= 1

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._lines.clear()
            self._cond.notify_all()


def encode_line(line: Line, epoch: float) -> bytes:
    """A reply as is; a frame as ``< frame ID SEC.USEC HEXDATA >``, ID of 3 hex digits
    (standard) or 8 (extended), as socketcand writes them."""
    if isinstance(line, bytes):
        return line
    arbitration_id, data, t_end = line
    if arbitration_id & CAN_EFF_FLAG:
        return b"< frame %08X %.6f %s >" % (arbitration_id & CAN_EFF_MASK,
                                            epoch + t_end / 1e6,
                                            binascii.hexlify(data).upper())
    return b"< frame %03X %.6f %s >" % (arbitration_id, epoch + t_end / 1e6,
                                        binascii.hexlify(data).upper())


_CLIENT_NUMBERS = itertools.count()
"""Numbers the clients of this process (each one's losses are seeded with it)."""


class ClientPort:
    """A client's attachment to one simulated bus (a node of the bus and the sender of
    the client's frames).  ``on_frame`` runs in the bus thread under the bus lock: it only
    queues the frame, and reports an overflowing queue."""

    def __init__(self, sim: SimBus, outbox: Outbox, on_overflow: Callable[[], None],
                 loss: Loss | None = None, *,
                 later: Callable[[Callable[[], None]], bool] | None = None,
                 flush: Callable[[], None] | None = None) -> None:
        self.sim = sim
        self.outbox = outbox
        self.on_overflow = on_overflow
        self.loss = loss
        self.later = later
        """Asks for a call after the paced driver's step (:meth:`Fleet.after_step`; false:
        not paced); with ``flush`` the frames of a step are written together."""
        self.flush = flush

    def on_frame(self, arbitration_id: int, data: bytes, t_end: float) -> None:
        if self.loss is not None and self.loss.lost("to"):
            return
        outbox = self.outbox
        later, flush = self.later, self.flush
        if later is None or flush is None:
            if not outbox.put((arbitration_id, data, t_end)):
                self.on_overflow()
            return
        if not outbox.put_quiet((arbitration_id, data, t_end)):
            self.on_overflow()
            return
        if not outbox.deferred:
            outbox.deferred = True
            if not later(flush):  # the fleet stopped pacing (closing)
                outbox.wake()

    def on_extended_frame(self, arbitration_id: int, data: bytes, t_end: float) -> None:
        """A frame with a 29-bit identifier: to the client as socketcand writes it."""
        self.on_frame(arbitration_id | CAN_EFF_FLAG, data, t_end)


class Loss:
    """``fleet serve --loss``: frames lost between one client and its bus, a share
    ``share`` each way, from a generator seeded per client: the serve's seed, the bus and
    the client's number on this process (the same run loses the same frames)."""

    def __init__(self, share: float, seed: str) -> None:
        self.share = share
        self._rng = random.Random(seed)
        self.counts = {"to": 0, "from": 0}
        """Frames lost on their way to the client and from it."""

    def lost(self, direction: str) -> bool:
        if self._rng.random() < self.share:
            self.counts[direction] += 1
            return True
        return False


# ---------------------------------------------------------------------- one client
class Connection:
    """One socketcand client: the handler thread reads and executes its elements, a
    writer thread sends it replies and frames.  Ends without raising, however the
    client leaves."""

    def __init__(self, sock: socket.socket, address: Any, fleet: Fleet,
                 max_queued_frames: int = MAX_QUEUED_FRAMES) -> None:
        self.sock = sock
        self.peer = _peer(address)
        self.fleet = fleet
        self.outbox = Outbox(max_queued_frames)
        self.loss: Loss | None = None
        """Frames lost between this client and its bus (``fleet serve --loss``)."""
        self.port: ClientPort | None = None
        self.raw = False
        self._splitter = ElementSplitter()
        self._lock = threading.Lock()
        self._reason: str | None = None
        self._dropped = False
        self._writer = threading.Thread(target=self._write_loop, daemon=True,
                                        name=f"ucom-serve-writer-{self.peer}")
        self._want_driver = False
        """Raw mode began: the paced driver shall read the socket from now on."""
        self._handed = False
        """The driver reads the socket (:meth:`_read_by_driver`): elements run in its
        thread."""
        self._handback = threading.Event()
        """Set when the driver gives the socket back, or the connection ends."""
        self._returned: BaseException | None = None
        """Why the driver gave the socket back: EOF (:class:`EOFError`), a lost
        connection, an element too long; None: the driver stopped."""
        self._backlog: deque[tuple[int, bytes]] = deque()
        """Frames read by the driver while this client's transmit queue was full."""
        self._room_checked = 0.0
        self._commands: dict[str, Callable[[list[str]], None]] = {
            "open": self._open, "rawmode": self._rawmode, "send": self._send,
            "echo": self._echo}

    @property
    def alive(self) -> bool:
        return self._reason is None

    def run(self) -> None:
        """Serve the client until it leaves or is dropped."""
        log.info("client %s connected", self.peer)
        self._serve(lambda: self.reply("< hi >"))

    def resume(self, bus: str, pending: bytes = b"") -> None:
        """Serve a client that another process greeted and that sent ``< open BUS >``
        there (:mod:`ucom_tools.virtual.multiserve`): answer that open as :meth:`run`
        would, go on with ``pending`` (what the client sent after it), then the socket."""
        def start() -> None:
            self._execute(b"open " + bus.encode("ascii", "replace"))
            self._splitter.feed(pending)
        self._serve(start)

    def _serve(self, start: Callable[[], None]) -> None:
        self._writer.start()
        reason = "disconnected"
        try:
            self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            start()
            self._read_loop()
            self.outbox.wait_written(FLUSH_S)
        except ElementTooLong:
            self.reply(error_element("element too long", self.raw))
            self.outbox.wait_written(FLUSH_S)
            self.drop(f"sent an element longer than {MAX_ELEMENT} bytes")
        except OSError as err:
            reason = f"connection lost ({type(err).__name__})"
        finally:
            self._detach()
            self._end(reason, dropped=False)
            self._writer.join(FLUSH_S)

    def drop(self, reason: str) -> None:
        """Close a misbehaving client (any thread, idempotent; logged as a warning)."""
        self._end(reason, dropped=True)

    def close(self) -> None:
        """Close the connection because the server stops (any thread, idempotent)."""
        self._end("server closed", dropped=False)

    def reply(self, text: str) -> None:
        if not self.outbox.put(text.encode("ascii", "replace")):
            self._overflow()

    # ------------------------------------------------------------------ reading
    def _read_loop(self) -> None:
        while self.alive:
            while self.alive and (element := self._splitter.next()) is not None:
                self._execute(element)
            if not self.alive:
                return
            if self._want_driver:
                self._want_driver = False
                if self._read_by_driver():
                    return
                continue
            chunk = self.sock.recv(_RECV_SIZE)
            if not chunk:
                return
            self._splitter.feed(chunk)

    # ------------------------------------------------------------------ read by the driver
    def _read_by_driver(self) -> bool:
        """In raw mode on a paced fleet the driver's thread reads the socket
        (:meth:`RealtimeDriver.watch`) and runs the elements, while this thread waits;
        True when the client is done (EOF, dropped), False when the driver gave the socket
        back because it stopped (then this thread reads on).  Raises what made the driver
        give it back (a lost connection, an element too long)."""
        fleet = self.fleet
        self._handback.clear()
        self._returned = None
        self._handed = True  # before the driver may read: its elements run as its own
        if not _DONTWAIT or not fleet.watch(self.sock, self._on_readable,
                                            self._handback.set):
            self._handed = False
            return False
        try:
            while not self._handback.wait(ROOM_POLL_S):
                driver = fleet.driver
                if driver is None or not driver.running:
                    break
        finally:
            fleet.unwatch(self.sock)
            self._handed = False
        returned, self._returned = self._returned, None
        if isinstance(returned, EOFError):
            return True
        if returned is not None:
            raise returned
        if not self.alive:
            return True
        port = self.port
        while self._backlog and port is not None and self.alive:  # the driver stopped
            self._transmit(port, *self._backlog.popleft(), lossy=False)
        self._backlog.clear()
        return False

    def _give_back(self, why: BaseException) -> None:
        """In the driver's thread: stop reading, wake the connection's thread."""
        self._returned = why
        driver = self.fleet.driver
        if driver is not None:
            driver.unwatch(self.sock)
        self._handback.set()

    def _on_readable(self) -> None:
        """In the driver's thread, holding the lock: read what came, run its elements."""
        if not self.alive:
            self._give_back(EOFError())
            return
        try:
            chunk = self.sock.recv(_RECV_SIZE, _DONTWAIT)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as err:
            self._give_back(err)
            return
        if not chunk:
            self._give_back(EOFError())
            return
        self._splitter.feed(chunk)
        self._run_elements()
        driver = self.fleet.driver
        if self._backlog and driver is not None:
            driver.unwatch(self.sock)  # TCP slows the client meanwhile (back-pressure)
            self._room_checked = time.monotonic()
            driver.wait_for_room(self._room)

    def _run_elements(self) -> None:
        """In the driver's thread: the elements fed, until the transmit queue is full."""
        try:
            while self.alive and not self._backlog and \
                    (element := self._splitter.next()) is not None:
                self._execute(element)
        except ElementTooLong as err:
            self._give_back(err)

    def _room(self) -> bool:
        """In the driver's thread, every step while frames wait for the transmit queue:
        queue them as room comes, then read on; True when done waiting."""
        port = self.port
        driver = self.fleet.driver
        if not self.alive or not self._handed or port is None or driver is None:
            return True
        sim = port.sim
        backlog = self._backlog
        while backlog and sim.queued.get(port, 0) < TX_QUEUE:
            self._put_on_bus(port, *backlog.popleft())
        if not backlog:
            self._run_elements()
        if backlog:
            now = time.monotonic()
            if now - self._room_checked >= ROOM_POLL_S:
                self._room_checked = now
                if _peer_gone(self.sock):
                    self._end("disconnected while waiting for the bus", dropped=False)
                    return True
            return False
        if self.alive and self._returned is None:
            driver.watch(self.sock, self._on_readable, self._handback.set)
        return True

    def _queue_now(self, port: ClientPort, arbitration_id: int, data: bytes) -> None:
        """In the driver's thread: a frame onto the bus, ready now (a lagging fleet takes
        it in its own present, as :meth:`Fleet.send_paced` does), or into the backlog."""
        if self._backlog or port.sim.queued.get(port, 0) >= TX_QUEUE:
            self._backlog.append((arbitration_id, data))
            return
        self._put_on_bus(port, arbitration_id, data)

    def _put_on_bus(self, port: ClientPort, arbitration_id: int, data: bytes) -> None:
        sim = port.sim
        driver = self.fleet.driver
        clock = sim.clock
        t = clock.now if driver is None else driver.now_us()
        if clock.quiet_until(t):
            clock.advance_to(t)  # an idle fleet's clock stands still: bring it to now
        _send(sim, port, min(t, clock.now + HOST_AHEAD_US), arbitration_id & CAN_EFF_MASK,
              data, bool(arbitration_id & CAN_EFF_FLAG))

    def _execute(self, element: bytes) -> None:
        port = self.port
        if port is not None and (frame := _plain_send(element)) is not None:
            self._transmit(port, *frame)  # the common case, without the general parsing
            return
        try:
            verb, *args = element_words(element)
            command = self._commands.get(verb)
            if command is None:
                raise unsupported(verb)
            command(args)
        except ElementError as err:
            self.reply(error_element(str(err), self.raw))

    def _open(self, args: list[str]) -> None:
        sim = self.fleet.buses[check_open(
            args, self.fleet.buses, self.fleet.name,
            None if self.port is None else self.port.sim.name)]
        if self.fleet.client_loss and self.loss is None:
            self.loss = Loss(self.fleet.client_loss,
                             f"{self.fleet.seed}/{sim.name}/{next(_CLIENT_NUMBERS)}")
        self.port = ClientPort(sim, self.outbox, self._overflow, self.loss,
                               later=self.fleet.after_step, flush=self._flush)
        self.reply("< ok >")
        log.info("client %s opened %s", self.peer, sim.name)

    def _rawmode(self, args: list[str]) -> None:
        port = self._require_open()
        if args:
            raise ElementError("usage: rawmode")
        if self.raw:
            raise ElementError("already in raw mode")
        self.raw = True
        self.reply("< ok >")
        # python-can reads this "< ok >" with one recv(): let it arrive alone
        self.outbox.wait_written(FLUSH_S)
        time.sleep(RAWMODE_SETTLE_S)
        if self.alive:
            port.sim.attach(port)
            self._want_driver = True

    def _send(self, args: list[str]) -> None:
        port = self._require_open()
        arbitration_id, data = parse_send(args)
        self._transmit(port, arbitration_id, data)

    def _echo(self, args: list[str]) -> None:
        self.reply("< echo >")

    def _require_open(self) -> ClientPort:
        if self.port is None:
            raise ElementError(NO_BUS_OPEN)
        return self.port

    def _transmit(self, port: ClientPort, arbitration_id: int, data: bytes, *,
                  lossy: bool = True) -> None:
        """Queue a frame (identifier with :data:`CAN_EFF_FLAG` if extended) once the
        client's transmit queue has room.  Meanwhile this client's socket is not read
        (back-pressure); the wait releases the bus lock.  In the driver's thread the
        frame goes onto the bus at once, or waits in the backlog."""
        if lossy and self.loss is not None and self.loss.lost("from"):
            return  # lost on the way (--loss): the client cannot tell
        if self._handed:
            self._queue_now(port, arbitration_id, data)
            return
        extended = bool(arbitration_id & CAN_EFF_FLAG)
        arbitration_id &= CAN_EFF_MASK
        sim = port.sim
        while self.alive:
            try:
                self.fleet.send_paced(sim, port, arbitration_id, data, timeout=ROOM_POLL_S,
                                      alive=lambda: self.alive, extended=extended)
                return
            except can.CanOperationError:
                pass  # no room yet: still there?
            if _peer_gone(self.sock):
                self._end("disconnected while waiting for the bus", dropped=False)

    # ------------------------------------------------------------------ writing
    def _write_loop(self) -> None:
        epoch = self.fleet.epoch
        try:
            while (batch := self.outbox.take()) is not None:
                self.sock.sendall(b"".join([encode_line(line, epoch) for line in batch]))
        except OSError as err:
            self._end(f"connection lost ({type(err).__name__})", dropped=False)
        except Exception:
            log.exception("client %s: writer failed", self.peer)
            self.drop("writer failed")

    def _flush(self) -> None:
        """After a step of the paced fleet: the frames it queued, in one write from the
        driver's thread (:meth:`Outbox.flush`); without ``MSG_DONTWAIT`` the writer
        thread writes them."""
        if not _DONTWAIT:
            self.outbox.wake()
            return
        try:
            self.outbox.flush(self._send_now, self.fleet.epoch)
        except OSError as err:
            self._end(f"connection lost ({type(err).__name__})", dropped=False)

    def _send_now(self, data: bytes) -> int:
        """What of ``data`` the socket takes without waiting."""
        try:
            return self.sock.send(data, _DONTWAIT)
        except (BlockingIOError, InterruptedError):
            return 0

    def _overflow(self) -> None:
        self.drop(f"stopped reading ({self.outbox.limit} frames waiting)")

    # ------------------------------------------------------------------ ending
    def _end(self, reason: str, *, dropped: bool) -> None:
        with self._lock:
            if self._reason is not None:
                return
            self._reason, self._dropped = reason, dropped
        self._handback.set()
        self.outbox.close()
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)  # wakes a blocked recv and sendall

    def _detach(self) -> None:
        port = self.port
        if port is None:
            return
        sim = port.sim
        with sim.lock:
            sim.detach(port)
            if sim.queued.get(port, 0) <= 0:
                sim.queued.pop(port, None)

    def log_end(self) -> None:
        """Say how the client went (once its connection is closed and its slot free)."""
        if self.loss is not None:
            log.info("client %s: %d frames lost on their way to it, %d from it (--loss)",
                     self.peer, self.loss.counts["to"], self.loss.counts["from"])
        if self._dropped:
            log.warning("dropped client %s: %s", self.peer, self._reason)
        else:
            log.info("client %s left: %s", self.peer, self._reason or "disconnected")


def _peer_gone(sock: socket.socket) -> bool:
    """Has the client closed its end?  Looks without taking any of its input."""
    try:
        if not _DONTWAIT and not select.select([sock], [], [], 0)[0]:
            return False
        return sock.recv(1, socket.MSG_PEEK | _DONTWAIT) == b""
    except (BlockingIOError, InterruptedError):
        return False
    except OSError:
        return True


# ---------------------------------------------------------------------- the server
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
        log.warning("refused client %s: too many clients (%d)", _peer(client_address),
                    self.max_clients)
        with contextlib.suppress(OSError):
            request.sendall(f"< error too many clients ({self.max_clients}) >".encode())
        self.shutdown_request(request)

    def handle_error(self, request: Any, client_address: Any) -> None:
        log.error("unexpected error serving %s", _peer(client_address), exc_info=True)


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
    """Serve in a thread until Ctrl-C, then shut the server down and close its clients."""
    thread = threading.Thread(target=server.serve_forever, name="ucom-socketcand", daemon=True)
    thread.start()
    with contextlib.suppress(KeyboardInterrupt):
        while thread.is_alive():
            thread.join(0.2)
    server.shutdown()
    server.server_close()
