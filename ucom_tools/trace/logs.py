"""CAN logs as other tools read them: the formats ucom writes (only those it reads back),
one rule for a frame's channel and the robot's bus name in both directions, reading a
trace, and the one frame writer (:class:`FrameWriter`, a :class:`can.Listener`) of both
``--log`` (:class:`FrameLog`) and ``--record`` (:mod:`ucom_tools.trace.record`), on files
opened by the writing rules of ``ucom(1)``, FILES (:mod:`ucom_tools.fileio`)."""

from __future__ import annotations

import contextlib
import copy
import importlib.util
import os
import threading
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any, Protocol

import can
from can.io.generic import MessageWriter
from can.util import channel2int

from ucom_tools.errors import InputError, WriteError
from ucom_tools.fileio import Output, reason

FORMATS: dict[str, str] = {
    ".asc": "Vector ASCII log",
    ".blf": "Vector binary log",
    ".csv": "python-can CSV (no channel or direction column: one bus only)",
    ".db": "SQLite database (no channel or direction column: one bus only)",
    ".log": "can-utils candump -l log",
    ".trc": "PEAK trace",
}
"""Extensions python-can writes (via :func:`can.Logger`) and what they are; the text
formats also gzip-compressed (``.asc.gz``, ...).  ``.mf4`` when asammdf is installed."""

INT_CHANNELS = frozenset({".asc", ".blf", ".trc", ".mf4"})
"""Formats whose channel is a number: a bus name is stored as its number (CAN0 -> 0,
i.e. channel 1 in Vector's and PEAK's counting), see :attr:`FrameWriter.channels`."""

_GZIP_OK = frozenset({".asc", ".csv", ".log", ".trc"})

ONE_BUS = frozenset({".csv", ".db", ".csv.gz"})
"""Formats without a channel (or direction) column: refused for a recording of several
buses, whose frames they could not tell apart."""

MCAP = ".mcap"
"""MCAP (:mod:`ucom_tools.trace.mcapfile`): every bus on a channel of its own, written and
read by ucom itself (python-can has no MCAP writer)."""

NOT_READABLE = {".txt": "python-can writes .txt but cannot read it back; use .log "
                        "(candump -l text) instead"}
"""Formats python-can writes that no reader takes (ucom writes only what it reads)."""


def check_buses(extension: str, buses: Iterable[str], path: str | os.PathLike[str],
                key: str) -> None:
    """InputError, before anything is recorded, when ``extension`` cannot keep apart the
    frames of ``buses`` (:data:`ONE_BUS`)."""
    names = list(buses)
    if extension in ONE_BUS and len(names) > 1:
        raise InputError(f"{os.fspath(path)}: {extension} has no channel column: the frames "
                         f"of {', '.join(names)} could not be told apart; use .asc, .blf, "
                         ".log or .trc", key=key)


def channel_number(channels: dict[str, int], name: str) -> int:
    """The number bus ``name`` is stored as in the formats of :data:`INT_CHANNELS`: its
    own (CAN0 -> 0) unless taken, else the lowest free one; kept in ``channels``."""
    number = channels.get(name)
    if number is None:
        taken = set(channels.values())
        number = channel2int(name)
        if number is None or number in taken:
            number = next(n for n in range(len(taken) + 1) if n not in taken)
        channels[name] = number
    return number


def log_writer(out: Output) -> MessageWriter:
    """python-can's writer for the log ``out`` (the format by its extension), writing to
    its temporary file but naming the final one where the format records its own name
    (a PEAK trace's header); an MCAP file's is :class:`~ucom_tools.trace.mcapfile.
    McapFrameWriter`."""
    if out.target.lower().endswith(MCAP):
        from ucom_tools.trace.mcapfile import McapFile, McapFrameWriter

        mcap = McapFrameWriter(McapFile(out.name, out.key or "log", out))
        return mcap  # type: ignore[return-value]  # what FrameWriter calls of one
    writer: MessageWriter = can.Logger(out.write_path)
    if isinstance(writer, can.TRCWriter) and out.kind != "stdout":
        writer.filepath = os.path.abspath(out.target)
    return writer


DEFAULT_BUS = "CAN"
"""The bus of frames without a channel (a one-bus trace)."""


def channel_names(channels: Iterable[Any], buses: Sequence[str] = ()) -> dict[Any, str]:
    """The robot bus each channel of a trace stands for: the rule that undoes
    :func:`channel_number` and python-can's conversions, in one place.

    - no channel: the robot's only bus, else :data:`DEFAULT_BUS`;
    - a number n (the formats of :data:`INT_CHANNELS`): the bus whose name ends in n
      (CAN0 for 0), else ``CANn``;
    - a string: the bus of that name, also in another case (``can0`` from
      ``can.logconvert`` is CAN0), else the string as it is;
    - python-can counts a PEAK trace's channels from 1 and ``can.logconvert`` keeps that
      count (``can1``-``can4`` for CAN0-CAN3): when the numbered channels of a trace are
      exactly 1..n and the robot's ``buses`` are numbered 0..n-1, they are shifted.
    """
    chans = list(dict.fromkeys(channels))
    numbered = {c: channel2int(c) for c in chans if c not in (None, "")
                and not isinstance(c, bool)}
    by_number = {channel2int(b): b for b in buses if channel2int(b) is not None}
    by_folded = {b.casefold(): b for b in buses}
    shift = 0
    values = sorted(n for n in numbered.values() if n is not None)
    known = sorted(n for n in by_number if n is not None)
    if values and known and values == list(range(1, len(values) + 1)) and \
            known == list(range(len(values))):
        shift = 1
    out: dict[Any, str] = {}
    for c in chans:
        if c is None or c == "":
            out[c] = buses[0] if len(buses) == 1 else DEFAULT_BUS
            continue
        if isinstance(c, str) and c.casefold() in by_folded and not shift:
            out[c] = by_folded[c.casefold()]
            continue
        n = numbered.get(c)
        if n is not None and (isinstance(c, int) or shift or c.casefold().startswith(
                ("can", "vcan"))):
            n -= shift
            out[c] = by_number.get(n, f"CAN{n}")
            continue
        out[c] = str(c)
    return out


def supported_extensions() -> list[str]:
    """Every extension :class:`RunRecorder` accepts, as shown in messages."""
    exts = [*FORMATS, MCAP]
    if importlib.util.find_spec("asammdf") is not None:
        exts.append(".mf4")
    return sorted(exts) + sorted(f"{e}.gz" for e in _GZIP_OK)


def log_extension(path: str | os.PathLike[str], key: str = "record") -> str:
    """The format extension of ``path`` (lower case, ``.asc.gz`` for compressed ones);
    InputError (naming ``key``) listing the supported ones when python-can cannot write
    it."""
    suffixes = [s.lower() for s in Path(path).suffixes]
    ext = "".join(suffixes[-2:]) if suffixes[-1:] == [".gz"] else "".join(suffixes[-1:])
    supported = supported_extensions()
    if ext.removesuffix(".gz") in NOT_READABLE:
        raise InputError(f"{os.fspath(path)}: {NOT_READABLE[ext.removesuffix('.gz')]}",
                         key=key)
    if ext not in supported:
        shown = f"'{ext}'" if ext else "no extension"
        raise InputError(f"{os.fspath(path)}: {shown} is not a CAN log format python-can "
                         f"writes; use one of {', '.join(supported)}", key=key)
    return ext



# ============================================================================ input
def read_trace(path: str | Path) -> list[can.Message]:
    """Every frame of a python-can log (the format by the extension: .asc, .blf, .log,
    .csv, .trc, .db, ...); InputError naming the file when it cannot be read.  Channel
    numbers count from 0 as python-can's writers take them (a .trc file's PEAK channel 1
    is channel 0)."""
    file = str(path)
    if not Path(file).is_file():
        raise InputError("no such file" if not Path(file).exists() else "not a file",
                         file=file)
    if file.lower().endswith(MCAP):
        from ucom_tools.trace.mcapfile import read_frames

        return read_frames(file)
    try:
        with can.LogReader(file) as reader:
            frames = list(reader)
    except InputError:
        raise
    except Exception as err:  # python-can raises anything from ValueError to struct.error
        text = str(err).strip().splitlines()
        reason = text[0] if text else type(err).__name__
        raise InputError(f"cannot read as a CAN trace: {reason}", file=file) from None
    if file.lower().endswith((".trc", ".trc.gz")):
        # PEAK counts channels from 1: python-can writes channel n as n + 1 and reads the
        # number as it stands; back to python-can's count (CAN0 is channel 0)
        for f in frames:
            if isinstance(f.channel, int) and f.channel > 0:
                f.channel -= 1
    return frames



# ------------------------------------------------------------------------ --log
class Tapped(Protocol):
    """What a log taps: a bus's dispatcher, whose ``taps`` see every frame it receives
    and sends (:class:`ucom_tools.protocol.dispatch.Dispatcher`)."""

    taps: list[Callable[[can.Message], None]]


class LogError(WriteError):
    """A recording (``--log``, ``--record``) could not be written (a full disk, a lost
    directory); the partial file was removed and a file it would have replaced keeps its
    content."""


def not_kept(err: WriteError) -> LogError:
    """``err`` (a recording's file that could not be committed) as the recording's
    :class:`LogError`: nothing was kept."""
    text = err.reason if err.reason.endswith("nothing was kept") else \
        f"{err.reason}; nothing was kept"
    return LogError(text, path=err.path, key=err.key)


def check_log(path: str | os.PathLike[str], key: str = "log") -> str:
    """Check a log file (``key`` names it, the robot's ``log`` by default) before
    anything is opened: a format ucom writes, in a directory that exists, not a directory
    itself.  Returns the extension."""
    ext = log_extension(path, key=key)
    p = Path(path)
    if not p.parent.is_dir():
        raise InputError(f"{os.fspath(p)}: directory {os.fspath(p.parent)} does not exist",
                         key=key)
    if p.is_dir():
        raise InputError(f"{os.fspath(p)} is a directory", key=key)
    return ext


WRITE_EVERY_S = 0.05
"""How often a :class:`FrameWriter`'s thread writes the frames queued meanwhile."""


class FrameWriter(can.Listener):
    """The one frame writer of ``--log`` and ``--record``: frames into python-can's writer
    for ``out`` (:func:`log_writer`), each with its bus name as channel (as the bus's
    number, :func:`channel_number`, in the formats of :data:`INT_CHANNELS`).

    The thread that hands a frame in (a bus's reader, the PC's 1 kHz loop) only queues
    it: a thread of the writer's own formats and writes the queued frames every
    :data:`WRITE_EVERY_S`, so no file, disk or formatter ever keeps the loop from its
    deadline.  Thread-safe.  A writing error does not reach whoever handed in the frame:
    it is kept (:attr:`failure`), and the frames after it are dropped, so the owner
    discards the file instead of keeping a log with a gap.  :meth:`stop` writes what is
    queued, then closes.  Committing or discarding ``out`` is the owner's business."""

    def __init__(self, out: Output, extension: str) -> None:
        self._int_channels = extension.removesuffix(".gz") in INT_CHANNELS
        self.channels: dict[str, int] = {}
        """Bus name -> channel number stored in the formats of :data:`INT_CHANNELS`."""
        self.frames = 0
        """Frames written so far."""
        self.failure: BaseException | None = None
        """The first error writing met (then nothing more was written)."""
        self._lock = threading.Lock()
        """Held while frames are written (by the writer's thread, or by :meth:`stop`)."""
        self._stopped = False
        self._queue: deque[tuple[can.Message, str | None]] = deque()
        self._stopping = threading.Event()
        self._writer: MessageWriter = log_writer(out)
        self._thread = threading.Thread(target=self._run, name="ucom-frames", daemon=True)
        self._thread.start()

    def write(self, msg: can.Message, bus: str | None = None) -> None:
        """Queue one frame of bus ``bus`` (default: its ``channel``, a bus name) for the
        writer's thread; a frame handed in after :meth:`stop` is dropped."""
        if not self._stopped:
            self._queue.append((msg, bus))

    def _run(self) -> None:
        while not self._stopping.wait(WRITE_EVERY_S):
            self._write_queued()

    def _write_queued(self) -> None:
        """Write every frame queued (the writer's thread, or :meth:`stop`)."""
        queued = self._queue
        with self._lock:
            while queued:
                msg, bus = queued.popleft()
                if self.failure is not None:
                    continue
                try:
                    channel = msg.channel if bus is None else bus
                    if self._int_channels and isinstance(channel, str):
                        channel = channel_number(self.channels, channel)
                    if channel != msg.channel:
                        msg = copy.copy(msg)
                        msg.channel = channel
                    self._writer.on_message_received(msg)
                    self.frames += 1
                except Exception as err:  # the frames' source must not die of the log
                    self.failure = err

    def on_message_received(self, msg: can.Message) -> None:
        self.write(msg)

    def on_error(self, exc: Exception) -> None:
        """A bus reader's error is the reader's business; the recording goes on."""

    def stop(self) -> None:
        """Write what is queued, then flush and close python-can's writer (idempotent);
        an error doing so becomes :attr:`failure`."""
        with self._lock:
            if self._stopped:
                return
            self._stopped = True
        self._stopping.set()
        if self._thread is not threading.current_thread():
            self._thread.join()
        self._write_queued()
        with self._lock:
            try:
                self._writer.stop()
            except Exception as err:
                self.failure = self.failure or err


class FrameLog:
    """``--log FILE``: every frame of the robot's buses, received and sent, into a
    python-can log (:func:`can.Logger`, the format by the extension).

    Written by the rules of ``ucom(1)``, FILES (:class:`ucom_tools.fileio.Output`): a
    regular FILE under a temporary name beside it, renamed into place by :meth:`close`, so
    it is a complete recording or keeps what it had (and its permissions); a device or FIFO
    is written through.  Each frame carries its bus name as channel (as the bus's number in
    the formats of :data:`INT_CHANNELS`) and its time on the bus's time base: a received
    frame its own timestamp, a sent frame the time it was handed to the bus, on the same
    base (the virtual fleet's virtual time in virtual time).  Thread-safe: the bus readers
    record from their threads."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.extension = check_log(self.path)
        self._taps: dict[str, Callable[[can.Message], None]] = {}
        self._lock = threading.Lock()
        self._closed = False
        self._out = Output(self.path, key="log", suffix=self.extension)
        try:
            self._frames = FrameWriter(self._out, self.extension)
        except Exception as err:
            self._out.discard()
            raise InputError(f"cannot write {os.fspath(self.path)}: {reason(err)}",
                             key="log") from None

    @property
    def frames(self) -> int:
        """Frames recorded so far."""
        return self._frames.frames

    @property
    def channels(self) -> dict[str, int]:
        """Bus name -> channel number stored in the formats of :data:`INT_CHANNELS`."""
        return self._frames.channels

    def attach(self, name: str, dispatcher: Tapped) -> None:
        """Record every frame ``dispatcher`` (bus ``name``'s) receives or sends from now
        on, with the bus's name as its channel."""

        def tap(msg: can.Message) -> None:  # sent frames come stamped on the same base
            self._frames.write(msg, name)

        self._taps[name] = tap
        dispatcher.taps.append(tap)

    def detach(self, name: str, dispatcher: Tapped) -> None:
        """Stop recording bus ``name``'s frames."""
        tap = self._taps.pop(name, None)
        if tap is not None:
            with contextlib.suppress(ValueError):
                dispatcher.taps.remove(tap)

    def close(self) -> None:
        """Flush the log and rename it into place (idempotent); :class:`LogError`, and no
        file (the old one, if any, as it was), when writing failed."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._frames.stop()
            failure = self._frames.failure
            if failure is None:
                try:
                    self._out.commit()
                    return
                except WriteError as err:
                    raise not_kept(err) from None
            self._out.discard()
            raise LogError(f"{os.fspath(self.path)}: {reason(failure)}; nothing was kept",
                           path=os.fspath(self.path), key="log")

    def discard(self) -> None:
        """End the recording and keep nothing (idempotent; after :meth:`close` the file
        stays)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._frames.stop()
            self._out.discard()
