"""A socketcand client (raw mode) in which every wait has a deadline.

socketcand (https://github.com/linux-can/socketcand) serves SocketCAN buses over TCP, and
``ucom fleet serve`` serves the virtual fleet the same way
(:mod:`ucom_tools.virtual.serve.socketcand`).
python-can 4.6 has a client, ``can.interfaces.socketcand.SocketCanDaemonBus``, that a robot
tool cannot use because it waits forever, or far too long:

- the handshake reads with a blocking ``recv`` without timeout: a server that accepts the
  connection and says nothing hangs the program; it also compares a whole ``recv()`` with
  the expected text, so an answer split across two reads fails the handshake, and frames
  arriving in the same read as the rawmode ``< ok >`` are lost;
- ``connect`` is retried in a loop for 10 s, so a refused port costs 10 s instead of 1 ms;
- ``send`` is a ``sendall`` without timeout: it hangs when the server stops reading;
- a connection closed by the server looks like silence: ``recv`` returns ``b""`` and the
  bus answers "no frame" forever;
- Nagle's algorithm stays on unless ``tcp_tune``, which delays every small request.

:class:`SocketcandBus` waits only with deadlines:

``connect_timeout`` (3 s)
    for the TCP connection, all addresses of the host together.  Resolving the host name
    (``getaddrinfo``) is the one wait the operating system bounds, not this module.
``handshake_timeout`` (2 s)
    for each answer of the handshake, separately: ``< hi >`` after connecting, ``< ok >``
    to ``< open CHANNEL >``, ``< ok >`` to ``< rawmode >``.
``send_timeout`` (2 s)
    for writing one frame to the socket when :meth:`~SocketcandBus.send` gets no
    ``timeout`` (``send(msg, timeout)`` uses its own).
the ``timeout`` of ``recv``
    as for every python-can bus; ``None`` blocks (every caller in ucom-tools passes one).

A connection the server closed or reset, an element longer than :data:`MAX_ELEMENT`, and a
send that timed out after writing part of a frame leave the bus unusable: that call and
every later ``recv``/``send`` raise :class:`can.CanOperationError`.

Elements are cut, read and written by :mod:`ucom_tools.wire.socketcand` (one copy for
this client and the server), messages made of them by :mod:`.socketcand_frames`; the
connection and its writes within a deadline are :mod:`.tcp`'s.

Time stamps: a received frame is stamped on this machine's clock (``time.time()``), as a
sent one is, so a log of both (``--log``, ``--record``) has one time base.  The server's
stamp (when the frame was on its bus, on the server's clock) is translated by the offset
measured on the connection: the least (arrival - server stamp) seen so far, the frame
that came fastest.  A translated stamp is never later than the frame's arrival, and an
answer is never stamped before the request that caused it; the bus's own spacing of the
frames is kept.  :attr:`SocketcandBus.clock_offset` is the offset in seconds.
"""

from __future__ import annotations

import contextlib
import logging
import math
import re
import selectors
import socket
import threading
import time
from binascii import hexlify
from collections import deque
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any, Final

import can

from ucom_tools.protocol.frames import DataFrame, received_message
from ucom_tools.transport.socketcand_frames import (
    data_elements,
    parse_frame,
    send_bytes,
    shown,
    state_of_error,
)
from ucom_tools.transport.tcp import connect, reason, send_within
from ucom_tools.wire.socketcand import (
    CAN_EFF_MASK,
    CAN_SFF_MASK,
    MAX_ELEMENT,
    SEND_EMPTY,
    SEND_STD,
    ElementSplitter,
    error_frame,
    plain_frame,
)

if TYPE_CHECKING:
    from ucom_tools.protocol.buscontract import BatchingBus

__all__ = ["MAX_ELEMENT", "PINGS", "ElementSplitter", "SocketcandBus"]

log = logging.getLogger(__name__)

SERVER_ERRORS_KEPT: Final = 100
"""How many ``< error ... >`` texts :attr:`SocketcandBus.server_errors` keeps (the newest)."""
_CHUNK: Final = 65536

_CHANNEL: Final = re.compile(r"[^\s<>]+")


CONNECT_TIMEOUT_S = 3.0
"""The default ``connect_timeout`` (the module docstring)."""
HANDSHAKE_TIMEOUT_S = 2.0
"""The default ``handshake_timeout``."""
SEND_TIMEOUT_S = 2.0
"""The default ``send_timeout``.  (Named constants rather than literals: see
compiled.py.)"""

PINGS: Final = 4
"""``< echo >`` round trips measured after the handshake.  The first does not count: a
server may answer it only once its switch to raw mode is done (``ucom fleet serve``
attaches a client to its bus 20 ms after the rawmode ``< ok >``, for python-can's
client)."""
PING_WAIT_S: Final = 0.1
"""The least an echo is waited for (more on a slow connection: 20 rawmode round trips)."""


def _skipped(junk: bytes) -> None:
    if junk.strip():
        log.warning("socketcand: skipped %r outside an element", junk[:80])


class SocketcandBus(can.BusABC):
    """One CAN bus of a socketcand server, in raw mode, with a deadline on every wait.

    ``send`` may run on another thread than ``recv`` (sends are serialised by a lock);
    ``recv`` is for one thread at a time, as on every python-can bus.
    ``server_errors`` keeps the texts of the last :data:`SERVER_ERRORS_KEPT`
    ``< error ... >`` elements the server sent (they are also logged).
    """

    def __init__(self, channel: str, host: str, port: int, *,
                 connect_timeout: float = CONNECT_TIMEOUT_S,
                 handshake_timeout: float = HANDSHAKE_TIMEOUT_S,
                 send_timeout: float = SEND_TIMEOUT_S,
                 receive_own_messages: bool = False, **kwargs: Any) -> None:
        if not isinstance(channel, str) or not _CHANNEL.fullmatch(channel):
            raise can.CanInitializationError(
                f"socketcand channel must be a name without blanks or <>, got {channel!r}")
        self.channel = channel
        self.host = host
        self.port = port
        self.handshake_timeout = handshake_timeout
        self.send_timeout = send_timeout
        self.receive_own_messages = receive_own_messages
        self.server_errors: deque[str] = deque(maxlen=SERVER_ERRORS_KEPT)
        self.error_frames = 0
        """Error frames the server passed on (``< error CLASS SEC.USEC >``)."""
        self._error_state = can.BusState.ACTIVE
        """The state the last error frame said (:attr:`state`)."""
        self._frames_in = 0
        """Data frames taken so far."""
        self._error_mark = 0
        """:attr:`_frames_in` when that error frame came."""
        self._where = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
        self._splitter = ElementSplitter(on_skip=_skipped)
        self._arrival = 0.0
        """When the last data came (``time.time()``)."""
        self.clock_offset = math.inf
        """This machine's clock minus the server's, as measured (seconds; inf until the
        first frame)."""
        self._into = bytearray(_CHUNK)
        """What :meth:`_poll` reads into."""
        self._pending: deque[can.Message | DataFrame] = deque()
        """What arrived and was not yet taken: standard data frames as
        :data:`~ucom_tools.protocol.frames.DataFrame` s, others as messages."""
        self.round_trip_s: float | None = None
        """The longest of the round trips measured while connecting (``< rawmode >`` and
        the :data:`PINGS` ``< echo >`` but the first): what the deadlines of a network bus
        add; None when the server answered no echo."""
        self._send_lock = threading.Lock()
        self._batch: list[bytes] | None = None
        self._batch_thread: int | None = None
        self._broken: str | None = None
        self._closed = False
        with contextlib.ExitStack() as on_failure:
            self._sock = on_failure.enter_context(connect(host, port, connect_timeout,
                                                          self._where))
            self._readable = on_failure.enter_context(selectors.DefaultSelector())
            self._writable = on_failure.enter_context(selectors.DefaultSelector())
            self._readable.register(self._sock, selectors.EVENT_READ)
            self._writable.register(self._sock, selectors.EVENT_WRITE)
            self._handshake()
            on_failure.pop_all()
        self.channel_info = f"socketcand {host}:{port} {channel}"
        super().__init__(channel=channel, **kwargs)

    # ------------------------------------------------------------------ handshake
    def _handshake(self) -> None:
        self._expect("hi", "the connection")
        command = f"< open {self.channel} >"
        self._handshake_send(command)
        self._expect("ok", command)
        sent = time.monotonic()
        self._handshake_send("< rawmode >")
        self._expect("ok", "< rawmode >")
        rawmode = time.monotonic() - sent
        echoes: list[float] = []
        for _ in range(PINGS):  # a server that does not echo costs at most this much
            trip = self._ping(min(self.handshake_timeout, max(PING_WAIT_S, 20 * rawmode)))
            if trip is None:
                break
            echoes.append(trip)
        # the first echo may have waited for the server's switch to raw mode; a server
        # that answers none leaves the round trip unknown (the fixed margin)
        self.round_trip_s = max([rawmode, *(echoes[1:] or echoes)]) if echoes else None

    def _ping(self, wait: float) -> float | None:
        """One ``< echo >`` round trip in seconds, or None when the server does not answer
        it within ``wait`` seconds (frames that come meanwhile are kept)."""
        sent = time.monotonic()
        deadline = sent + wait
        try:
            self._write(b"< echo >", wait)
        except can.CanOperationError:
            return None
        while (element := self._next_element(deadline)) is not None:
            if element.split() == [b"echo"]:
                return time.monotonic() - sent
            self._take(element)
        return None

    def _handshake_send(self, command: str) -> None:
        try:
            self._write(command.encode("ascii"), self.handshake_timeout)
        except can.CanOperationError as err:
            raise can.CanInitializationError(f"{err} during the handshake") from err

    def _expect(self, word: str, what: str) -> None:
        """Wait for the answer ``< word >`` to ``what``, within the handshake deadline."""
        try:
            element = self._next_element(time.monotonic() + self.handshake_timeout)
        except can.CanOperationError as err:
            raise can.CanInitializationError(
                f"{err} during the handshake, before answering {what}") from err
        if element is None:
            raise can.CanInitializationError(
                f"socketcand {self._where} did not answer {what} "
                f"within {self.handshake_timeout:g} s")
        words = element.decode("ascii", "replace").split()
        if words == [word]:
            return
        if words and words[0] == "error":
            self.server_errors.append(" ".join(words[1:]))
            if what.startswith("< open"):
                raise can.CanInitializationError(
                    f"socketcand {self._where} refused to open channel {self.channel}: "
                    f"{shown(element)}")
        raise can.CanInitializationError(
            f"socketcand {self._where} answered {what} with {shown(element)}, expected < {word} >")

    def _next_element(self, deadline: float) -> bytes | None:
        while True:
            element = self._pop_element()
            if element is not None:
                return element
            if not self._read_more(max(deadline - time.monotonic(), 0.0)):
                return None

    # ------------------------------------------------------------------ receive
    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            if self._closed:
                raise self._shut_down()
            if self._pending:
                item = self._pending.popleft()
                return (self.message_of(item) if isinstance(item, tuple) else item), False
            self._check_usable()
            self._take_buffered()
            if self._pending:
                continue
            remaining = None if deadline is None else max(deadline - time.monotonic(), 0.0)
            if not self._read_more(remaining):
                return None, False

    def recv_ready_frames(self, limit: int = 1000) -> list[can.Message | DataFrame] | None:
        """Every frame that has arrived, without waiting (at most about ``limit``): what
        a loop that polls its buses takes in one call, not one ``recv`` per frame; a
        standard data frame as a :data:`~ucom_tools.protocol.frames.DataFrame`
        (:meth:`message_of` is the message ``recv`` would give), any other as a message.
        None when the bus has filters (then ``recv`` applies them).

        A read that returns less than it could have emptied the socket's buffer: what
        comes after it came after this call, and the next one takes it (no second read
        that finds nothing: at 1 kHz on four buses that was a system call and an
        exception 4000 times a second)."""
        if self._filters:
            return None
        if self._closed:
            raise self._shut_down()
        pending = self._pending
        self._take_buffered()
        while len(pending) < limit:
            got = self._poll()
            if not got:
                break
            self._take_buffered()
            if got < _CHUNK:
                break
        out = list(pending)
        pending.clear()
        return out

    def message_of(self, frame: DataFrame) -> can.Message:
        """The message :meth:`recv` gives for a frame :meth:`recv_ready_frames` handed
        over as a :data:`~ucom_tools.protocol.frames.DataFrame`."""
        return received_message(frame, self.channel)

    def _take_buffered(self) -> None:
        """Every complete element buffered, taken: runs of standard frame elements in the
        usual form at once (:meth:`ElementSplitter.plain_data`, as
        :data:`~ucom_tools.protocol.frames.DataFrame` s stamped on this machine's clock:
        what :meth:`_take` and :meth:`_local` give, without a message), any other
        element by :meth:`_take`."""
        splitter = self._splitter
        pending = self._pending
        while splitter.unread():
            frames, self.clock_offset = splitter.plain_data(self._arrival, self.clock_offset)
            if frames:
                pending.extend(frames)
                self._frames_in += len(frames)
                if not splitter.unread():
                    return
            element = self._pop_element()
            if element is None:
                return
            self._take(element)

    def _take(self, element: bytes) -> None:
        """One element between its brackets: a frame to :attr:`_pending`, an error noted."""
        frame = plain_frame(element)
        if frame is not None:
            self._frames_in += 1
            can_id, stamp, data = frame
            self._pending.append(self._local(can.Message(
                timestamp=stamp, arbitration_id=can_id & CAN_EFF_MASK, data=data,
                is_extended_id=can_id > CAN_EFF_MASK, is_rx=True, channel=self.channel)))
            return
        words = element.decode("ascii", "replace").split()
        kind = words[0] if words else ""
        if kind == "frame":
            try:
                self._pending.append(self._local(parse_frame(words, self.channel)))
            except ValueError as err:
                log.warning("socketcand %s: ignored %s: %s", self._where, shown(element), err)
        elif kind == "error":
            error = error_frame(element)
            if error is not None:
                self._error_frame(error[0])
                return
            text = " ".join(words[1:])
            self.server_errors.append(text)
            log.warning("socketcand %s reports an error: %s", self._where, text)
        else:
            log.debug("socketcand %s: ignored %s", self._where, shown(element))

    def _error_frame(self, error_class: int) -> None:
        """An error frame of the server's bus: what it says of this node's state."""
        self.error_frames += 1
        state = state_of_error(error_class)
        if state is not None:
            self._error_state = state
            self._error_mark = self._frames_in

    @property
    def state(self) -> can.BusState:
        """python-can's controller state, as the server's error frames tell it:
        ``PASSIVE`` (error-passive) after an acknowledgement error (a frame of this
        node that no other node took: a cut cable, every board off), ``ERROR`` after
        bus-off, each until the bus works again (a frame arrives, or the controller
        restarted); ``ACTIVE`` otherwise.  Error frames are kept here, not handed out
        by :meth:`recv` (they would look like data frames of identifier CLASS to the
        protocol's readers; ``error_frames`` counts them)."""
        if self._error_state is not can.BusState.ACTIVE and self._frames_in > self._error_mark:
            self._error_state = can.BusState.ACTIVE
        return self._error_state

    @state.setter
    def state(self, new_state: can.BusState) -> None:
        raise NotImplementedError("a socketcand bus's state is the server's bus's: it "
                                  "cannot be set from here")

    def _local(self, msg: can.Message) -> can.Message:
        """``msg`` stamped on this machine's clock (the module docstring, Time stamps)."""
        offset = self._arrival - msg.timestamp
        if offset < self.clock_offset:
            self.clock_offset = offset
        else:
            offset = self.clock_offset
        msg.timestamp += offset
        return msg

    def _pop_element(self) -> bytes | None:
        try:
            return self._splitter.next()
        except ValueError as err:
            raise self._fail(f"socketcand {self._where} protocol error: {err}") from err

    def _poll(self) -> int:
        """Buffer what the socket has, without waiting: the bytes read (0: none)."""
        if self._closed:
            raise self._shut_down()
        if self._broken is not None:
            raise can.CanOperationError(self._broken)
        into = self._into
        try:  # into a buffer of the bus's own: recv(_CHUNK) would allocate 64 KiB a call
            got = self._sock.recv_into(into)
        except BlockingIOError:
            return 0
        except (OSError, ValueError) as err:  # ValueError: closed by shutdown() meanwhile
            raise self._lost(err) from err
        if not got:
            raise self._fail(f"socketcand {self._where} closed the connection")
        self._arrival = time.time()
        self._splitter.feed(memoryview(into)[:got])
        return got

    def _read_more(self, timeout: float | None) -> bool:
        """Wait up to ``timeout`` for data and buffer it; False if none came in time."""
        self._check_usable()
        try:
            if timeout == 0:  # a poll (a loop draining its buses): no select needed
                try:
                    chunk = self._sock.recv(_CHUNK)
                except BlockingIOError:
                    return False
            elif not self._readable.select(timeout):
                return False
            else:
                chunk = self._sock.recv(_CHUNK)
        except BlockingIOError:
            return True
        except (OSError, ValueError) as err:  # ValueError: closed by shutdown() meanwhile
            raise self._lost(err) from err
        self._buffer(chunk)
        return True

    def _buffer(self, chunk: bytes) -> None:
        """What a read returned, for the splitter (nothing: the server closed)."""
        if not chunk:
            raise self._fail(f"socketcand {self._where} closed the connection")
        self._arrival = time.time()
        self._splitter.feed(chunk)

    # ------------------------------------------------------------------ send
    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send one data frame; the write must complete within ``timeout`` (default
        ``send_timeout``), otherwise :class:`can.CanOperationError`."""
        try:
            data = send_bytes(msg)
        except ValueError as err:
            raise can.CanOperationError(f"socketcand {self._where} cannot send {err}") from err
        self._put(data, timeout)
        if self.receive_own_messages:
            self._pending.append(can.Message(
                timestamp=time.time(), arbitration_id=msg.arbitration_id,
                is_extended_id=msg.is_extended_id, data=bytes(msg.data[:msg.dlc]),
                is_rx=False, channel=self.channel))

    def send_data(self, arbitration_id: int, data: bytes, timeout: float | None = None,
                  ) -> None:
        """:meth:`send` of a standard data frame given by its identifier and data, without
        a ``can.Message`` (:meth:`~ucom_tools.protocol.dispatch.Dispatcher.send_data`:
        the run time's cyclic frames); the same element, the same errors."""
        n = len(data)
        if not 0 <= arbitration_id <= CAN_SFF_MASK or n > 8:
            self.send(can.Message(arbitration_id=arbitration_id, data=data,
                                  is_extended_id=False, check=False), timeout)
            return
        element = SEND_STD % (arbitration_id, n, hexlify(data, b" ").upper()) if n \
            else SEND_EMPTY % arbitration_id
        self._put(element, timeout)
        if self.receive_own_messages:
            self._pending.append(can.Message(
                timestamp=time.time(), arbitration_id=arbitration_id, is_extended_id=False,
                data=bytes(data), is_rx=False, channel=self.channel))

    def send_data_many(self, frames: list[tuple[int, bytes]], timeout: float | None = None,
                       ) -> None:
        """:meth:`send_data` of each frame, in one write (or one piece of the batch held:
        :meth:`hold`) within ``timeout``: all of them or none (a frame that is not a
        standard data frame of at most 8 bytes: none, refused as :meth:`send` refuses
        it)."""
        try:
            elements = data_elements(frames)
        except ValueError as err:
            raise can.CanOperationError(f"socketcand {self._where} cannot send {err}") from err
        self._put(elements, timeout)
        if self.receive_own_messages:
            now = time.time()
            for ident, data in frames:
                self._pending.append(can.Message(
                    timestamp=now, arbitration_id=ident, is_extended_id=False,
                    data=bytes(data), is_rx=False, channel=self.channel))

    def _put(self, element: bytes, timeout: float | None) -> None:
        """Collect ``element`` when this thread holds a batch (:meth:`hold`), else write it
        within ``timeout`` (default ``send_timeout``)."""
        if self._batch is not None and self._batch_thread == threading.get_ident():
            self._batch.append(element)
        else:
            self._write(element, self.send_timeout if timeout is None else timeout)

    def hold(self) -> None:
        """From now on the frames this thread sends are collected, not written, until
        :meth:`release` writes them in one go: a cyclic loop's frames of one cycle cost
        one system call, not one each.  Frames of other threads are written at once."""
        if self._batch is None:
            self._batch, self._batch_thread = [], threading.get_ident()

    def release(self, write: bool = True, timeout: float | None = None) -> None:
        """Write what :meth:`hold` collected (within ``timeout``, default
        ``send_timeout``; a failure raises :class:`can.CanOperationError` as :meth:`send`
        would), or drop it (``write`` false); sends are written at once again."""
        frames, self._batch, self._batch_thread = self._batch, None, None
        if write and frames:
            self._write(b"".join(frames), self.send_timeout if timeout is None else timeout)

    @contextlib.contextmanager
    def batch(self, timeout: float | None = None) -> Iterator[None]:
        """:meth:`hold` ... :meth:`release` as a context (dropped when the block raises)."""
        if self._batch is not None:  # nested: the outer batch writes
            yield
            return
        self.hold()
        try:
            yield
        except BaseException:
            self.release(write=False)
            raise
        self.release(timeout=timeout)

    def _write(self, data: bytes, limit: float) -> None:
        """Write all of ``data`` within ``limit`` seconds, or nothing, or break the bus."""
        limit = max(limit, 0.0)
        deadline = time.monotonic() + limit
        if not self._send_lock.acquire(timeout=limit):
            raise can.CanOperationError(f"socketcand {self._where} took no data for {limit:g} s")
        try:
            self._check_usable()
            try:
                sent = send_within(self._sock, self._writable, data, deadline)
            except (OSError, ValueError) as err:
                raise self._lost(err) from err
            if sent == len(data):
                return
            if sent:
                self._fail(f"socketcand {self._where} is unusable: a send timed out after "
                           f"writing {sent} of the {len(data)} bytes of {data.decode()}")
            raise can.CanOperationError(f"socketcand {self._where} took no data for {limit:g} s")
        finally:
            self._send_lock.release()

    # ------------------------------------------------------------------ state
    def _check_usable(self) -> None:
        if self._closed:
            raise self._shut_down()
        if self._broken is not None:
            raise can.CanOperationError(self._broken)

    def _fail(self, message: str) -> can.CanOperationError:
        """Mark the connection broken (first reason wins); the error to raise now."""
        if self._broken is None:
            self._broken = message
            log.warning("%s", message)
        return can.CanOperationError(message)

    def _lost(self, err: Exception) -> can.CanOperationError:
        if self._closed:
            return self._shut_down()
        return self._fail(f"socketcand {self._where} connection lost: {reason(err)}")

    def _shut_down(self) -> can.CanOperationError:
        return can.CanOperationError(f"socketcand {self._where} bus is shut down")

    def fileno(self) -> int:
        """The connection's socket, for a loop that waits on several buses with select():
        readable when a frame (or part of one) has come that :meth:`recv` has not taken."""
        return self._sock.fileno()

    def shutdown(self) -> None:
        """Close the connection; safe to call again, and after the server vanished."""
        super().shutdown()
        if self._closed:
            return
        self._closed = True
        with contextlib.suppress(OSError):
            self._sock.shutdown(socket.SHUT_RDWR)  # wakes a thread waiting in recv
        self._readable.close()
        self._writable.close()
        self._sock.close()


if TYPE_CHECKING:  # mypy checks that the bus keeps the contract the dispatcher relies on
    def _keeps_the_bus_contract(bus: SocketcandBus) -> BatchingBus:
        return bus
