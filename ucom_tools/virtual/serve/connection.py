"""One client of ``ucom fleet serve`` (socketcand's raw mode), from its greeting or its
handover to its end: reading and executing its elements (:class:`Connection`), and its
attachment to a simulated bus (:class:`ClientPort`).

The protocol, and what no client can do to the others, is described in
:mod:`ucom_tools.virtual.serve.socketcand`, which accepts the connections; the elements are
cut and read by :mod:`ucom_tools.wire.socketcand`.  A client's handler thread reads its
socket until raw mode begins on a paced fleet; from then on the fleet's driver thread
reads it (:meth:`Connection._read_by_driver`) and the handler thread waits.

Before ``< open >`` a client may also ask for an injected fault (``< ucom_fault TARGET KIND
[SECONDS] >``, :mod:`ucom_tools.wire.socketcand_fault`: ``ucom fleet fault``), which
:func:`~ucom_tools.virtual.serve.elements.inject_element` applies to the fleet and
answers.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import select
import socket
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import can

from ucom_tools.virtual.bus.loss import FrameLoss
from ucom_tools.virtual.bus.simbus import TX_QUEUE, SimBus
from ucom_tools.virtual.fleet import HOST_AHEAD_US, Fleet
from ucom_tools.virtual.serve.elements import (
    NO_BUS_OPEN,
    check_open,
    inject_element,
    peer_name,
    unsupported,
)
from ucom_tools.virtual.serve.outbox import MAX_QUEUED_FRAMES, Outbox, encode_lines
from ucom_tools.wire import socketcand_fault
from ucom_tools.wire.socketcand import (
    CAN_EFF_FLAG,
    CAN_EFF_MASK,
    CAN_ERR_ACK,
    MAX_ELEMENT,
    ElementError,
    ElementSplitter,
    ElementTooLong,
    element_words,
    error_element,
    error_frame_element,
    parse_send,
    plain_send,
)

log = logging.getLogger("ucom.serve")

RAWMODE_SETTLE_S = 0.02
"""Pause between the rawmode ``< ok >`` and the first frame (python-can compatibility)."""
ROOM_POLL_S = 0.1
"""How often a client waiting for room in its transmit queue is checked for liveness."""
UNACKED_EVERY_US = 1000.0
"""At most one error frame a millisecond for a client's frames nobody acknowledges."""
FLUSH_S = 1.0
"""How long the server waits for a last reply to be written before closing a client."""
_RECV_SIZE = 4096
_DONTWAIT = getattr(socket, "MSG_DONTWAIT", 0)


_CLIENT_NUMBERS = itertools.count()
"""Numbers the clients of this process (each one's losses are seeded with it)."""


class ClientPort:
    """A client's attachment to one simulated bus (a node of the bus and the sender of
    the client's frames).  ``on_frame`` runs in the bus thread under the bus lock: it only
    queues the frame, and reports an overflowing queue."""

    def __init__(self, sim: SimBus, outbox: Outbox, on_overflow: Callable[[], None],
                 loss: FrameLoss | None = None, *,
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



class Connection:
    """One socketcand client: the handler thread reads and executes its elements, a
    writer thread sends it replies and frames.  Ends without raising, however the
    client leaves."""

    def __init__(self, sock: socket.socket, address: Any, fleet: Fleet,
                 max_queued_frames: int = MAX_QUEUED_FRAMES) -> None:
        self.sock = sock
        self.peer = peer_name(address)
        self.fleet = fleet
        self.outbox = Outbox(max_queued_frames)
        self.loss: FrameLoss | None = None
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
        self._unacked_next = -1.0
        """Before this fleet time (microseconds) no further error frame is sent for a frame
        of this client's that nobody acknowledged (:meth:`_unacknowledged`)."""
        self._commands: dict[str, Callable[[list[str]], None]] = {
            "open": self._open, "rawmode": self._rawmode, "send": self._send,
            "echo": self._echo, socketcand_fault.COMMAND: self._fault}

    @property
    def alive(self) -> bool:
        return self._reason is None

    def run(self) -> None:
        """Serve the client until it leaves or is dropped."""
        log.info("client %s connected", self.peer)
        self._serve(lambda: self.reply("< hi >"))

    def resume(self, bus: str, pending: bytes = b"") -> None:
        """Serve a client that another process greeted and that sent ``< open BUS >``
        there (:mod:`ucom_tools.virtual.serve.multiserve`): answer that open as :meth:`run`
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
        returned = self._take_returned()
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

    def _take_returned(self) -> BaseException | None:
        """What :meth:`_give_back` left, cleared (a method of its own: read where the field
        was just set to None, it would be taken for None still, although the driver's
        thread set it meanwhile: see compiled.py)."""
        returned, self._returned = self._returned, None
        return returned

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
        if not self._backlog:
            return
        driver = self.fleet.driver
        if driver is not None:
            driver.unwatch(self.sock)  # TCP slows the client meanwhile (back-pressure)
            self._room_checked = time.monotonic()
            driver.wait_for_room(self._room)

    def _run_elements(self) -> None:
        """In the driver's thread: the elements fed, until the transmit queue is full.
        The frames of one call are ready at the same time, now (they came together)."""
        splitter = self._splitter
        backlog = self._backlog
        t = -1.0
        try:
            while self.alive and not backlog and (element := splitter.next()) is not None:
                port = self.port
                frame = None if port is None else plain_send(element)
                if port is None or frame is None:
                    self._command(element)
                    continue
                if t < 0.0:
                    t = self._now_us(port)
                self._transmit(port, frame[0], frame[1], t=t)
        except ElementTooLong as err:
            self._give_back(err)

    def _now_us(self, port: ClientPort) -> float:
        """The fleet's time now: the wall clock's (the paced driver's), else its clock's."""
        driver = self.fleet.driver
        return port.sim.clock.now if driver is None else driver.now_us()

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

    def _queue_now(self, port: ClientPort, arbitration_id: int, data: bytes,
                   t: float = -1.0) -> None:
        """In the driver's thread: a frame onto the bus, ready at ``t`` (negative: now; a
        lagging fleet takes it in its own present, as :meth:`Fleet.send_paced` does), or
        into the backlog (then it is ready when it leaves it)."""
        if self._backlog or port.sim.queued.get(port, 0) >= TX_QUEUE:
            self._backlog.append((arbitration_id, data))
            return
        self._put_on_bus(port, arbitration_id, data, t)

    def _put_on_bus(self, port: ClientPort, arbitration_id: int, data: bytes,
                    t: float = -1.0) -> None:
        sim = port.sim
        clock = sim.clock
        if t < 0.0:
            t = self._now_us(port)
        if clock.quiet_until(t):
            clock.advance_to(t)  # an idle fleet's clock stands still: bring it to now
        ready = min(t, clock.now + HOST_AHEAD_US)
        if arbitration_id & CAN_EFF_FLAG:  # as Fleet.send_paced queues it (fleet._send)
            sim.send(port, ready, arbitration_id & CAN_EFF_MASK, data, extended=True)
        else:
            sim.send(port, ready, arbitration_id, data)

    def _execute(self, element: bytes) -> None:
        port = self.port
        if port is not None and (frame := plain_send(element)) is not None:
            self._transmit(port, *frame)  # the common case, without the general parsing
            return
        self._command(element)

    def _command(self, element: bytes) -> None:
        """An element that is not a ``send`` in the usual form (:func:`plain_send`)."""
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
            self.loss = FrameLoss(self.fleet.client_loss,
                             f"{self.fleet.seed}/{sim.name}/{next(_CLIENT_NUMBERS)}")
        self.port = ClientPort(sim, self.outbox, self._overflow, self.loss,
                               later=self.fleet.after_step, flush=self._flush)
        self.reply("< ok >")
        log.info("client %s opened %s", self.peer, sim.name)

    def _fault(self, args: list[str]) -> None:
        """``< ucom_fault ... >``: an injected fault, applied at once (before ``< open >``
        only: a bus's client does not steer the fleet)."""
        if self.port is not None:
            raise ElementError(socketcand_fault.refusal(
                "send it on a connection of its own, before any open"))
        answer = inject_element(args, self.fleet.inject)
        self.reply(answer)
        log.warning("client %s injected a fault: %s", self.peer, answer[len("< ok "):-2])

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
        """``< echo >``: in raw mode on a paced fleet (read by the driver) answered after
        the fleet's next step, as the answer to a frame would come, behind the frames
        the bus carried before it; so the client's round trip holds the step latency
        that its frames' answers see (a busy machine's driver wakes late).  Otherwise at
        once."""
        driver = self.fleet.driver
        port = self.port
        if self._handed and driver is not None and port is not None:
            port.sim.clock.at(driver.now_us(), self._echo_due, driver.steps)
            return
        self.reply("< echo >")

    def _echo_due(self, t: float, read_in: int) -> None:
        """(a fleet clock event, holding the lock) the echo read in step ``read_in``:
        answered after this step if it is a later one, else due again in the next."""
        driver = self.fleet.driver
        port = self.port
        if driver is not None and port is not None and driver.steps == read_in:
            port.sim.clock.at(driver.now_us(), self._echo_due, read_in)
        elif not self.fleet.after_step(self._echo_now):
            self._echo_now()

    def _echo_now(self) -> None:
        if self.alive:
            self.reply("< echo >")

    def _require_open(self) -> ClientPort:
        if self.port is None:
            raise ElementError(NO_BUS_OPEN)
        return self.port

    def _transmit(self, port: ClientPort, arbitration_id: int, data: bytes, *,
                  lossy: bool = True, t: float = -1.0) -> None:
        """Queue a frame (identifier with :data:`CAN_EFF_FLAG` if extended) once the
        client's transmit queue has room.  Meanwhile this client's socket is not read
        (back-pressure); the wait releases the bus lock.  In the driver's thread the
        frame goes onto the bus at once (ready at ``t``, negative: now), or waits in the
        backlog."""
        if lossy and self.loss is not None and self.loss.lost("from"):
            return  # lost on the way (--loss): the client cannot tell
        if not port.sim.acknowledged(port):
            self._unacknowledged(port)
        if self._handed:
            self._queue_now(port, arbitration_id, data, t)
            return
        self._transmit_paced(port, arbitration_id, data)

    def _unacknowledged(self, port: ClientPort) -> None:
        """A frame of this client that no node of its bus acknowledges (a cut cable, every
        board off or bus-off): the error frame its controller would report,
        ``< error 020 SEC.USEC >`` (CAN_ERR_ACK), at most one every
        :data:`UNACKED_EVERY_US` (a controller retransmits such a frame without end and
        reports each failure; one a millisecond says it as soon, at a fraction of the
        cost); the frame goes on as before (the cable's far side may still hear it)."""
        t = self._now_us(port)
        if t < self._unacked_next:
            return
        self._unacked_next = t + UNACKED_EVERY_US
        self.outbox.put(error_frame_element(CAN_ERR_ACK, self.fleet.epoch + t / 1e6))

    def _transmit_paced(self, port: ClientPort, arbitration_id: int, data: bytes) -> None:
        """:meth:`_transmit` from the connection's thread: through
        :meth:`Fleet.send_paced`, waiting for room."""
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
                self.sock.sendall(encode_lines(batch, epoch))
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
            log.info("client %s: %d frames lost on their way to it, %d from it (as asked)",
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

