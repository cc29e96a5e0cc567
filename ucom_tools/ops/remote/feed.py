"""The loop's side of the run's consumers in a process of their own (``ucom remote run``
with its live view, ``--record``, ``--zenoh``).

Why another process: the loop is Python, and Python runs one thread at a time (the
GIL).  A consumer in the loop's process that holds that lock when the machine takes the
processor from it (another busy process) keeps the loop from its deadline until the
consumer runs again, whatever priority the loop has: measured on two cores beside two
busy processes, a 1 kHz loop under SCHED_FIFO was late by 0.12 to 0.94 ms (p99) with a
thread doing 30 % of a core of Python work beside it, and by less than 0.001 ms with the
same work in another process, as without it (``benchmarks/consumers.py``,
``man/ucom.1``).  As ros2_control keeps
its real-time loop apart from the rest, the consumers run apart, and the loop's process
runs the loop alone.

What goes over (one pipe each way; each message a length and a pickle, :func:`pack`):

- to the consumers: the part's structure (:class:`~ucom_tools.ops.remote.image.PartImage`,
  once the boards run), the loop's snapshots (:class:`~ucom_tools.ops.remote.publish.
  LoopSnapshot`, at the rate the consumers want, only what changed: :class:`WireSnapshots`),
  every frame of every bus where a recording wants them (the dispatchers' ``sink``), every
  value change the loop reports (``on_values``), the boards' Status reports, the answers
  to requests, and at the end the last snapshot;
- from the consumers: writes and stops (from the network or the view), the view's quit,
  which boards' Status reports to ask for, and their end.

The loop's thread does all of this in :meth:`LoopFeed.on_cycle` (``each_cycle``): it
takes what the buses' dispatchers collected, sends a message every
:data:`FLUSH_EVERY_S` or with each snapshot, reads what the consumers asked every few
cycles and applies it (as the in-process share does).  It never waits: the pipe is
non-blocking, what it does not take now waits (in the messages as they were packed, at
most :data:`WRITE_BUDGET` handed over a flush), and past :data:`PENDING_LIMIT` the frames
and value changes are counted as lost (a recording that lost frames fails rather than
keep a gap).  In virtual time the loop waits for the
consumers instead (nothing waits for the wall clock there, and nothing is lost).
The consumers' side is :mod:`ucom_tools.ops.remote.mirror`.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import pickle
import select
import struct
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from typing import TYPE_CHECKING, Any, Final

import can

from ucom_tools.errors import UcomError
from ucom_tools.ops.edges import EdgeRef
from ucom_tools.ops.remote.image import PartImage
from ucom_tools.ops.remote.publish import LoopHandover, LoopSnapshot
from ucom_tools.ops.remote.report import RemoteStop, Value
from ucom_tools.ops.remote.requests import (
    Applied,
    DriveItems,
    DriveWrites,
    StatusPoll,
    apply_write,
    is_status,
    stop_event,
)
from ucom_tools.protocol.routing import Subscription
from ucom_tools.protocol.traffic import SinkEntry

if TYPE_CHECKING:
    from ucom_tools.config.topology import BoardKey

FLUSH_EVERY_S: Final = 0.01
"""The longest frames and value changes wait on the loop's side (a snapshot goes at once)."""
REQUESTS_EVERY_S: Final = 0.005
"""How often the loop's thread looks for what the consumers asked."""
PIPE_SIZE: Final = 1 << 20
"""The pipe's buffer asked for (Linux; about a second of ARMAR-III's frames)."""
PENDING_LIMIT: Final = 16 << 20
"""What may wait on the loop's side when the consumers do not keep up; beyond, the
frames and value changes are lost (the rest, small, still goes)."""
WRITE_BUDGET: Final = 256 << 10
"""The most one flush hands to the pipe (what waits beyond goes with the next)."""
_HEADER: Final = struct.Struct(">I")


# ---------------------------------------------------------------------- the messages
def pack(message: object) -> bytes:
    """One message: its length and its pickle."""
    body = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    return _HEADER.pack(len(body)) + body


class Unpacker:
    """Messages out of a stream of bytes, however it is cut."""

    def __init__(self) -> None:
        self._buffer = bytearray()

    def feed(self, data: bytes) -> list[Any]:
        self._buffer += data
        out = []
        buffer = self._buffer
        while len(buffer) >= _HEADER.size:
            (size,) = _HEADER.unpack_from(buffer)
            end = _HEADER.size + size
            if len(buffer) < end:
                break
            out.append(pickle.loads(bytes(buffer[_HEADER.size:end])))
            del buffer[:end]
        return out


class Quit(UcomError):
    """The live view was quit (q, Ctrl-C or Ctrl-D there): the run ends as at its end."""

    def __init__(self) -> None:
        super().__init__("the live view was quit")


class ConsumersGone(UcomError):
    """The consumers' process ended while the loop ran (it failed: its message says why);
    the run ends, every board stopped."""


# ---------------------------------------------------------------------- snapshots
class WireSnapshots:
    """A snapshot as it goes over (the loop's side): the values' raw state with the
    PAR values by number, and of the figures, events, writes and faults only what the
    snapshot added; the PAR values and the lost boards only when they changed.  A
    ``full`` one carries all of it (after snapshots that could not be sent)."""

    def __init__(self, image: PartImage, handover: LoopHandover) -> None:
        self.handover = handover
        self._par_index = {ref: i for i, ref in enumerate(image.refs)}
        self._par: dict[Any, int] | None = None
        self._lost: Any = None

    def wire(self, snap: LoopSnapshot, *, full: bool = False) -> tuple[Any, ...]:
        v = snap.values
        par = None
        if full or v.par != self._par:
            self._par = v.par
            index = self._par_index
            par = {index[ref]: raw for ref, raw in v.par.items() if ref in index}
        lost = None
        if full or snap.lost != self._lost:
            self._lost = snap.lost
            lost = dict(snap.lost)
        f = snap.figures
        h = self.handover
        late = f.late if full else (h.new_late,)
        events, writes, faults = ((snap.events, snap.writes, snap.faults) if full
                                  else (h.new_events, h.new_writes, h.new_faults))
        return (snap.number, full, snap.clock, snap.stamp, snap.taken, snap.running,
                v.clock, v.frames, v.stamps, v.ci, par,
                (f.period_s, f.cycles, f.missed, f.longest_gap_s, f.started_clock,
                 f.ended_clock, late),
                events, snap.events_total, writes, snap.writes_total, faults,
                snap.faults_total, lost, dict(snap.traffic))


# ---------------------------------------------------------------------- the loop's side
class LoopFeed:
    """The loop's end of the pipes to the consumers' process (see the module docstring):
    ``out_fd`` to them, ``in_fd`` from them.  :meth:`attach` before the loop runs;
    :meth:`send_image` once the boards run; :meth:`end` after the boards' stop."""

    def __init__(self, part: Any, out_fd: int, in_fd: int, *, frames: bool,
                 rate_hz: float, wait: bool | None = None) -> None:
        self.part = part
        self.out_fd, self.in_fd = out_fd, in_fd
        self.frames_wanted = frames
        self.frames_kept = frames
        """Every frame goes over whatever the consumers ask (a recording's)."""
        self.wait = bool(part.virtual) if wait is None else wait
        """Whether the loop waits for the consumers (in virtual time: nothing waits for
        the wall clock there, and nothing is lost); on the wall clock it never does."""
        self.handover = LoopHandover.of(part, rate_hz)
        self._wire: WireSnapshots | None = None
        self._pending: deque[memoryview] = deque()
        """Messages (or the rest of one) the pipe did not take yet, in order."""
        self._pending_bytes = 0
        self.lost = 0
        """Frames and value changes the consumers could not be sent (they did not keep
        up: more than :data:`PENDING_LIMIT` waited)."""
        self._unpacker = Unpacker()
        self._changes: list[tuple[float, str, int, int, int, Value]] = []
        self._status: list[tuple[str, int, bytes, float]] = []
        self._answers: list[tuple[Any, ...]] = []
        self._snap: LoopSnapshot | None = None
        self._resync = False
        """Snapshots could not be sent: the next goes whole."""
        self._flush_every = max(1, round(FLUSH_EVERY_S / part.period_s))
        self._requests_every = max(1, round(REQUESTS_EVERY_S / part.period_s))
        self._flush_in = self._flush_every
        self._requests_in = self._requests_every
        self._status_subs: list[tuple[Any, Subscription]] = []
        self._poll: StatusPoll | None = None
        self.gone: str | None = None
        """Why the consumers' process is gone (it ended, or said it failed)."""
        self.ended: tuple[int, str, str | None] | None = None
        """(exit code, message, option) the consumers' process ended with, once it said
        so; :attr:`stats` what it reported (``--json``'s ``network``)."""
        self.stats: dict[str, Any] = {}
        self.drive = DriveWrites(part)
        """The consumers' raw writes (the CANopen gateway's)."""
        self._waiting: dict[str, tuple[Any, ...]] = {}
        self._on_values: Callable[[float, EdgeRef, Value], None] | None = None
        if not self.wait:
            os.set_blocking(out_fd, False)
            with contextlib.suppress(OSError, AttributeError):
                fcntl.fcntl(out_fd, fcntl.F_SETPIPE_SZ, PIPE_SIZE)
        os.set_blocking(in_fd, False)

    # ------------------------------------------------------------------ set up
    def attach_frames(self) -> None:
        """Collect every frame of every bus from now on, where a recording wants them
        (they go over with the first cycles)."""
        if self.frames_wanted:
            for h in self.part.robot.buses.values():
                h.link.dispatcher.sink = []

    def _want_frames(self, wanted: bool) -> None:
        """The consumers want the frames from now on, or no longer (a recording's are
        kept)."""
        if self.frames_kept or wanted == self.frames_wanted:
            return
        self.frames_wanted = wanted
        for h in self.part.robot.buses.values():
            h.link.dispatcher.sink = [] if wanted else None

    def attach(self) -> None:
        """Collect value changes (beside the part's own ``on_values``, which is called as
        before) and snapshots, and look after the consumers every cycle; before the
        start."""
        part = self.part
        self._on_values = part.on_values
        part.on_values = self._value
        self.handover.taken.append(self._taken)
        part.each_cycle.append(self.on_cycle)

    def send_image(self) -> None:
        """The part's structure (the boards run: their edges are final); from now on
        value changes and snapshots go over."""
        image = PartImage.of(self.part)
        self._wire = WireSnapshots(image, self.handover)
        self._send(("image", image))

    def _value(self, t: float, ref: EdgeRef, value: Value) -> None:
        """``on_values``: the part's own callback, then the change for the consumers."""
        if self._on_values is not None:
            self._on_values(t, ref, value)
        self._changes.append((t, ref.bus, ref.board, int(ref.kind), ref.index, value))

    def _taken(self, snap: LoopSnapshot) -> None:
        if self._wire is not None:
            if self._snap is not None:
                self._resync = True  # one not sent: the next goes whole
            self._snap = snap
            self._flush_in = 0

    def _status_frame(self, bus: str) -> Callable[[can.Message], None]:
        def take(msg: can.Message) -> None:
            self._status.append((bus, msg.arbitration_id, bytes(msg.data), msg.timestamp))
            self._flush_in = min(self._flush_in, 1)
        return take

    # ------------------------------------------------------------------ every cycle
    def on_cycle(self) -> None:
        """The loop's thread, every cycle (``each_cycle``); never waits (but in virtual
        time).  Raises what the consumers asked for that ends the run: a stop from the
        network (:class:`RemoteStop`), the view's quit (:class:`Quit`), or
        :class:`ConsumersGone`."""
        if self._poll is not None:
            self._poll.on_cycle()
        self._requests_in -= 1
        if self._requests_in <= 0:
            self._requests_in = self._requests_every
            self._read_requests()
        self._flush_in -= 1
        if self._flush_in <= 0:
            self._flush_in = self._flush_every
            self.flush()

    def flush(self) -> None:
        """Send what was collected (frames, changes, Status reports, answers, the latest
        snapshot) as one message (once the structure went over: :meth:`send_image`)."""
        if self._wire is None:
            return
        frames: dict[str, list[SinkEntry]] | None = None
        if self.frames_wanted:
            frames = {}
            for name, h in self.part.robot.buses.items():
                d = h.link.dispatcher
                taken = d.sink
                if taken:
                    d.sink = []
                    frames[name] = taken
        if not (frames or self._changes or self._status or self._answers or self._snap):
            return
        snap = None
        if self._pending_bytes > PENDING_LIMIT:  # they do not keep up: lost but the
            self.lost += len(self._changes) + sum(  # answers (the next snapshot whole)
                len(f) for f in (frames or {}).values())
            frames, self._changes, self._status = None, [], []
            self._resync = self._resync or self._snap is not None
        elif self._snap is not None and self._wire is not None:
            snap = self._wire.wire(self._snap, full=self._resync)
            self._resync = False
        self._snap = None
        if not (frames or self._changes or self._status or self._answers or snap):
            return
        message = ("data", frames, self._changes, self._status, self._answers, snap)
        self._changes, self._status, self._answers = [], [], []
        self._send(message)

    def _send(self, message: object) -> None:
        if self.gone is not None:
            return
        data = pack(message)
        if self.wait:  # nothing waits for the wall: the loop waits for the consumers
            try:
                _write_all(self.out_fd, data)
            except OSError as err:
                self.gone = f"the consumers' process is gone ({err.strerror or err})"
            return
        pending = self._pending
        pending.append(memoryview(data))
        self._pending_bytes += len(data)
        budget = WRITE_BUDGET
        try:
            while pending and budget > 0:
                chunk = pending[0]
                sent = os.write(self.out_fd, chunk[:budget])
                budget -= sent
                self._pending_bytes -= sent
                if sent < len(chunk):
                    pending[0] = chunk[sent:]
                    break
                pending.popleft()
        except BlockingIOError:
            pass  # the pipe is full: the rest waits for the next flush
        except OSError as err:
            self.gone = f"the consumers' process is gone ({err.strerror or err})"

    # ------------------------------------------------------------------ requests
    def _read_requests(self) -> None:
        try:
            data = os.read(self.in_fd, 65536)
        except BlockingIOError:
            return
        except OSError as err:
            data, self.gone = b"", f"the consumers' process is gone ({err})"
        if not data:
            if self.ended is None and self.gone is None:
                self.gone = "the consumers' process ended"
                raise ConsumersGone(self.gone)
            return
        for request in self._unpacker.feed(data):
            self._handle(request)

    def _handle(self, request: tuple[Any, ...]) -> None:
        kind = request[0]
        part = self.part
        if kind == "drive":
            self.drive.apply(request[1])
        elif kind == "set":
            _, number, name, value, origin, network = request
            self._answers.append((number, apply_write(part, name, value, origin,
                                                      network=network)))
            self._flush_in = 0
        elif kind == "stop":
            _, number, origin = request
            event = stop_event(part, origin)
            self._answers.append((number, Applied(None, "stopping", event=event)))
            self.flush()
            raise RemoteStop(origin)
        elif kind == "frames":
            self._want_frames(bool(request[1]))
        elif kind == "quit":
            raise Quit()
        elif kind == "poll":
            self._poll = StatusPoll(part, [tuple(b) for b in request[1]])
            for name, h in part.robot.buses.items():
                d = h.link.dispatcher
                self._status_subs.append((d, d.subscribe(
                    is_status, "consumers' status", on_frame=self._status_frame(name))))
        elif kind == "ended":  # the consumers' process says it ended (and how)
            self._ended(request)
            if self.ended is not None and self.ended[0]:
                self.gone = self.ended[1]
                raise ConsumersGone(self.ended[1])
        else:
            self._waiting[kind] = request

    def _ended(self, request: tuple[Any, ...]) -> None:
        self.ended = (int(request[1]), str(request[2]), request[3])
        self.stats = dict(request[4])

    # ------------------------------------------------------------------ the end
    def end(self) -> None:
        """After the boards' stop (the loop ended): the last snapshot and everything
        collected, then the end; the pipes stay open for :meth:`wait_for`."""
        part = self.part
        for d, sub in self._status_subs:
            d.unsubscribe(sub)
        self._status_subs = []
        if part.on_values == self._value:
            part.on_values = self._on_values
        with contextlib.suppress(ValueError):
            part.each_cycle.remove(self.on_cycle)
        with contextlib.suppress(ValueError):
            self.handover.taken.remove(self._taken)
        final = self.handover.final()
        if final is not None and self._wire is not None:
            self._snap = final
            self._resync = True  # the last one whole
        self.flush()
        for h in part.robot.buses.values():
            h.link.dispatcher.sink = None
        if self.gone is None:
            os.set_blocking(self.out_fd, True)
            try:
                while self._pending:
                    _write_all(self.out_fd, self._pending.popleft())
                self._pending_bytes = 0
                _write_all(self.out_fd, pack(("end", self.lost)))
            except OSError as err:
                self.gone = f"the consumers' process is gone ({err.strerror or err})"

    def wait_for(self, kind: str, timeout: float) -> tuple[Any, ...] | None:
        """The message ``kind`` ('ready', 'ended') from the consumers' process, waited for
        at most ``timeout`` seconds (not on the loop's thread while it runs); None where
        it did not come (:attr:`ended` says whether the process ended instead)."""
        deadline = time.monotonic() + timeout
        while True:
            if kind == "ended" and self.ended is not None:
                return ("ended", *self.ended)
            if kind in self._waiting:
                return self._waiting.pop(kind)
            if kind != "ended" and self.ended is not None:
                return None
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            ready, _, _ = select.select([self.in_fd], [], [], remaining)
            if not ready:
                continue
            try:
                data = os.read(self.in_fd, 65536)
            except BlockingIOError:
                continue
            except OSError:
                return None
            if not data:
                if self.ended is None:
                    self.gone = "the consumers' process ended"
                return None if kind != "ended" or self.ended is None else (
                    "ended", *self.ended)
            for message in self._unpacker.feed(data):
                if message[0] == "ended":
                    self._ended(message)
                else:
                    self._waiting[message[0]] = message


def _write_all(fd: int, data: bytes | memoryview) -> None:
    view = memoryview(data)
    while view:
        n = os.write(fd, view)
        view = view[n:]


# ---------------------------------------------------------------------- in the same process
class LocalRun:
    """A part's run for consumers in the loop's own process (a Python program's
    ``share(part)``): the same face as the consumers' process has of it
    (:class:`~ucom_tools.ops.remote.mirror.Mirror`): the hand-over's snapshots, the
    part's image once it is checked, writes and stops applied on the loop's thread
    (:meth:`on_cycle`, in ``each_cycle``), Status reports asked for."""

    def __init__(self, part: Any, rate_hz: float) -> None:
        import queue

        self.part = part
        self.handover = LoopHandover.of(part, rate_hz)
        self._image: PartImage | None = None
        self._requests: queue.SimpleQueue[tuple[Any, ...]] = queue.SimpleQueue()
        self.status_sinks: list[Callable[[str, int, bytes, float], None]] = []
        self._poll: StatusPoll | None = None
        self._subs: list[tuple[Any, Subscription]] = []
        self.drives = DriveWrites(part)
        """What came of :meth:`drive`'s writes."""
        part.each_cycle.append(self.on_cycle)

    @property
    def image(self) -> PartImage | None:
        """The part's structure once it is checked (None before)."""
        if self._image is None and self.part.report is not None:
            self._image = PartImage.of(self.part)
        return self._image

    @property
    def latest(self) -> LoopSnapshot | None:
        return self.handover.latest

    def subscribe(self, rate_hz: float | None = None, into: Any = None) -> Any:
        return self.handover.subscribe(rate_hz, into)

    def next_deadline(self) -> float | None:
        return self.handover.next_deadline()

    def final(self) -> LoopSnapshot | None:
        """The last snapshot (taken now where the loop has ended)."""
        return self.handover.final()

    # ------------------------------------------------------------------ requests
    def write(self, name: str, value: object, origin: str, *,
              network: bool = True) -> Future[Applied]:
        future: Future[Applied] = Future()
        self._requests.put(("set", future, name, value, origin, network))
        return future

    def stop(self, origin: str) -> Future[Applied]:
        future: Future[Applied] = Future()
        self._requests.put(("stop", future, origin))
        return future

    def drive(self, items: DriveItems) -> None:
        """Set edges by robot-wide name to raw values on the loop's thread, no answer
        (:class:`~ucom_tools.ops.remote.requests.DriveWrites`)."""
        self._requests.put(("drive", items))

    def poll_status(self, boards: list[BoardKey]) -> None:
        """Ask ``boards`` for their Status reports in turn; they come to
        :attr:`status_sinks` (on the loop's thread: a sink only keeps them)."""
        self._poll = StatusPoll(self.part, boards)
        for name, h in self.part.robot.buses.items():
            d = h.link.dispatcher
            self._subs.append((d, d.subscribe(is_status, "status", on_frame=self._taker(name))))

    def _taker(self, bus: str) -> Callable[[can.Message], None]:
        def take(msg: can.Message) -> None:
            for sink in self.status_sinks:
                sink(bus, msg.arbitration_id, bytes(msg.data), msg.timestamp)
        return take

    def on_cycle(self) -> None:
        """The loop's thread, every cycle: apply what was asked; raises
        :class:`RemoteStop` for a stop."""
        if not self._requests.empty():
            while not self._requests.empty():
                r = self._requests.get_nowait()
                if r[0] == "drive":
                    self.drives.apply(r[1])
                    continue
                if r[0] == "stop":
                    event = stop_event(self.part, r[2])
                    r[1].set_result(Applied(None, "stopping", event=event))
                    raise RemoteStop(r[2])
                _, future, name, value, origin, network = r
                future.set_result(apply_write(self.part, name, value, origin,
                                              network=network))
        if self._poll is not None:
            self._poll.on_cycle()

    def close(self) -> None:
        """No more Status reports; what is still asked is answered as refused."""
        for d, sub in self._subs:
            d.unsubscribe(sub)
        self._subs = []
        with contextlib.suppress(ValueError):
            self.part.each_cycle.remove(self.on_cycle)
        while not self._requests.empty():
            r = self._requests.get_nowait()
            if r[0] != "drive":
                r[1].set_result(Applied("stopped", "the loop is not running"))


__all__ = ["FLUSH_EVERY_S", "PENDING_LIMIT", "ConsumersGone", "LocalRun", "LoopFeed", "Quit",
           "Unpacker", "WireSnapshots", "pack"]
