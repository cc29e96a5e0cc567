"""The consumers' side of a run whose loop runs in another process (``ucom remote run``):
what the loop's process sends (:mod:`ucom_tools.ops.remote.feed`) turned back into the
part's structure (:class:`~ucom_tools.ops.remote.image.PartImage`) and the loop's
snapshots (:class:`~ucom_tools.ops.remote.publish.LoopSnapshot`), and the way back: writes,
stops, the view's quit, which Status reports to ask for.

:class:`Mirror` reads the pipe on a thread of its own and is, for the consumers, what
the loop's :class:`~ucom_tools.ops.remote.publish.LoopHandover` is in the loop's process
(:attr:`~ucom_tools.ops.remote.publish.Snapshots.latest`, doorbells); frames, value
changes and Status reports go to the callbacks that want them.
"""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Callable
from concurrent.futures import Future
from typing import TYPE_CHECKING, Any

from ucom_tools.ops.edges import EdgeRef
from ucom_tools.ops.remote.faults import BoardFault, LostBoard
from ucom_tools.ops.remote.feed import Unpacker, pack
from ucom_tools.ops.remote.image import PartImage
from ucom_tools.ops.remote.publish import LateChunks, LoopFigures, LoopSnapshot, Snapshots, Tail
from ucom_tools.ops.remote.report import BoardEvent, RawSnapshot, Value, WriteEvent
from ucom_tools.ops.remote.requests import Applied
from ucom_tools.protocol.traffic import SinkEntry

if TYPE_CHECKING:
    from ucom_tools.config.topology import BoardKey

FrameSink = Callable[[str, list[SinkEntry]], None]
ChangeSink = Callable[[float, EdgeRef, Value], None]
StatusSink = Callable[[str, int, bytes, float], None]
FaultSink = Callable[[BoardFault, LoopSnapshot], None]


class Mirror(Snapshots):
    """The loop as its consumers' process sees it (see the module docstring): reads
    ``in_fd``, writes requests to ``out_fd``.  :meth:`start` the reader; :attr:`image`
    is there once the boards run (:meth:`wait_image`); :attr:`ended` is set at the end
    of the run (or when the loop's process is gone)."""

    def __init__(self, in_fd: int, out_fd: int) -> None:
        super().__init__(0.001)
        self.in_fd, self.out_fd = in_fd, out_fd
        self.image: PartImage | None = None
        self._image_ready = threading.Event()
        self.ended = threading.Event()
        self.lost = 0
        """The frames and value changes the loop's side could not send (its consumers did
        not keep up)."""
        self.frame_sinks: list[FrameSink] = []
        self.change_sinks: list[ChangeSink] = []
        self.status_sinks: list[StatusSink] = []
        self.fault_sinks: list[FaultSink] = []
        """Called with each board lost or rejoined, and the snapshot that brought it."""
        self.snapshot_sinks: list[Callable[[LoopSnapshot], None]] = []
        """Called with each snapshot, on the reader's thread (before the doorbells)."""
        self.error: BaseException | None = None
        """What stopped the reader (a consumer's callback that failed), if anything."""
        self._write_lock = threading.Lock()
        self._answers: dict[int, Future[Applied]] = {}
        self._number = 0
        self._events: Tail[BoardEvent] = Tail()
        self._writes: Tail[WriteEvent] = Tail()
        self._faults: Tail[BoardFault] = Tail()
        self._late = LateChunks()
        self._par: dict[EdgeRef, int] = {}
        self._by_key: dict[tuple[str, int, int, int], EdgeRef] = {}
        self._lost: dict[BoardKey, LostBoard] = {}
        self._thread = threading.Thread(target=self._run, name="ucom-mirror", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def final(self) -> LoopSnapshot | None:
        """The last snapshot (after the end: how the run ended)."""
        return self._latest

    def close(self) -> None:
        """Nothing to let go of: the pipes belong to the process."""

    def wait_image(self, timeout: float | None = None) -> PartImage | None:
        """The part's structure, once the loop's process sent it (None: not within
        ``timeout``, or the run ended first)."""
        self._image_ready.wait(timeout)
        return self.image

    # ------------------------------------------------------------------ reading
    def _run(self) -> None:
        unpacker = Unpacker()
        try:
            while True:
                try:
                    data = os.read(self.in_fd, 1 << 16)
                except InterruptedError:
                    continue
                if not data:
                    return
                for message in unpacker.feed(data):
                    if not self._handle(message):
                        return
        except BaseException as err:  # a consumer failed: the run's end says so
            self.error = err
        finally:
            self._image_ready.set()
            self.ended.set()
            for future in self._answers.values():
                if not future.done():
                    future.set_result(Applied("failed", "the loop ended"))

    def _handle(self, message: tuple[Any, ...]) -> bool:
        kind = message[0]
        if kind == "data":
            _, frames, changes, status, answers, snap = message
            if frames:
                for bus, entries in frames.items():
                    for sink in self.frame_sinks:
                        sink(bus, entries)
            if changes:
                refs = self._by_key
                for t, bus, board, kind, index, value in changes:
                    ref = refs.get((bus, board, kind, index))
                    if ref is None:  # an edge the part does not name
                        continue
                    for change in self.change_sinks:
                        change(t, ref, value)
            for bus, ident, payload, t in status:
                for status_sink in self.status_sinks:
                    status_sink(bus, ident, payload, t)
            for number, applied in answers:
                future = self._answers.pop(number, None)
                if future is not None:
                    future.set_result(applied)
            if snap is not None:
                rebuilt, new_faults = self._rebuild(snap)
                for fault in new_faults:
                    for fault_sink in self.fault_sinks:
                        fault_sink(fault, rebuilt)
                for snapshot_sink in self.snapshot_sinks:
                    snapshot_sink(rebuilt)
                self._deliver(rebuilt)
        elif kind == "image":
            self.image = message[1]
            self.period_s = self.image.period_s
            self._by_key = {(r.bus, r.board, int(r.kind), r.index): r
                            for r in self.image.refs}
            self._image_ready.set()
        elif kind == "end":
            self.lost = int(message[1])
            return False
        return True

    def _rebuild(self, wire: tuple[Any, ...]) -> tuple[LoopSnapshot, tuple[BoardFault, ...]]:
        """The snapshot the loop took, and the faults it added (a ``full`` one, sent after
        snapshots that were lost on the way, carries everything, not what it added)."""
        (number, full, clock, stamp, taken, running, v_clock, frames, stamps, ci, par,
         figures, events, events_total, writes, writes_total, faults, faults_total, lost,
         traffic) = wire
        if par is not None and self.image is not None:
            refs = self.image.refs
            self._par = {refs[i]: raw for i, raw in par.items()}
        if lost is not None:
            self._lost = lost
        period_s, cycles, missed, gap, started, ended, late = figures
        if full:
            self._late.clear()
            new_faults = tuple(faults[len(faults) - min(len(faults), max(
                0, faults_total - self._faults.total)):])
            for tail, items, total in ((self._events, events, events_total),
                                       (self._writes, writes, writes_total),
                                       (self._faults, faults, faults_total)):
                tail.items, tail.total = tuple(items), total
        else:
            new_faults = tuple(faults)
            self._events.add(events, events_total)
            self._writes.add(writes, writes_total)
            self._faults.add(faults, faults_total)
        for chunk in late:
            self._late.add(chunk)
        return LoopSnapshot(
            number, clock, stamp, taken, running,
            RawSnapshot(v_clock, frames, stamps, ci, self._par),
            LoopFigures(period_s, cycles, missed, gap, started, ended, self._late.chunks),
            self._events.items, self._events.total, self._writes.items, self._writes.total,
            self._faults.items, self._faults.total, self._lost, traffic), new_faults

    # ------------------------------------------------------------------ requests
    def _send(self, message: object) -> None:
        with self._write_lock, contextlib.suppress(OSError):  # the loop is gone: ended
            data = pack(message)
            view = memoryview(data)
            while view:
                n = os.write(self.out_fd, view)
                view = view[n:]

    def write(self, name: str, value: object, origin: str, *,
              network: bool = True) -> Future[Applied]:
        """Set a CI or PAR as a local ``--set`` does, on the loop's thread; the answer
        comes as the future's result (a write from the ``network`` is kept in the run's
        writes with its ``origin``)."""
        return self._ask(("set", name, value, origin, network))

    def drive(self, items: list[tuple[str, int]]) -> None:
        """Set edges by robot-wide name to raw values on the loop's thread, no answer
        (:class:`~ucom_tools.ops.remote.requests.DriveWrites`)."""
        self._send(("drive", items))

    def frames(self, wanted: bool) -> None:
        """Have the loop hand over every bus's frames, or no longer (``--foxglove``: only
        while a client watches a bus's frames; a recording's come whatever this says)."""
        self._send(("frames", wanted))

    def stop(self, origin: str) -> Future[Applied]:
        """Stop every board and end the loop (a stop from the network, by ``origin``)."""
        return self._ask(("stop", origin))

    def _ask(self, request: tuple[Any, ...]) -> Future[Applied]:
        future: Future[Applied] = Future()
        if self.ended.is_set():
            future.set_result(Applied("failed", "the loop ended"))
            return future
        with self._write_lock:
            self._number += 1
            number = self._number
        self._answers[number] = future
        self._send((request[0], number, *request[1:]))
        return future

    def quit(self) -> None:
        """End the run (the view was quit): the loop stops the boards."""
        self._send(("quit",))

    def poll_status(self, boards: list[BoardKey]) -> None:
        """Ask ``boards`` for their Status reports in turn (about once a second each);
        the reports come to :attr:`status_sinks`."""
        self._send(("poll", boards))

    def send_ready(self, info: dict[str, Any]) -> None:
        """Tell the loop's process this one is ready (``info``: what it opened)."""
        self._send(("ready", info))

    def finished(self, code: int, message: str, key: str | None = None,
                 stats: dict[str, Any] | None = None) -> None:
        """Tell the loop's process this one ended: ``code`` 0, or the exit code of what
        failed, its ``message`` (and the option it is about); ``stats`` for ``--json``."""
        self._send(("ended", code, message, key, stats or {}))


__all__ = ["ChangeSink", "FaultSink", "FrameSink", "Mirror", "StatusSink"]
