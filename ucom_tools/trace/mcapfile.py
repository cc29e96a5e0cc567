"""MCAP files (``.mcap``, the format of ROS 2 bags, opened by Foxglove and Lichtblick):
the channels and schemas ucom writes (``ucom(1)``, MCAP RECORDINGS), the writer under
them, and reading the frames and values back.

Writing: :class:`McapFile` is one file written by the rules of ``ucom(1)``, FILES
(:class:`~ucom_tools.fileio.Output`: under a temporary name, renamed into place by
:meth:`McapFile.commit`), through foxglove-sdk's MCAP writer (its Rust core: 1.5 us a
message with zstd, against 4.6-6.6 us for the ``mcap`` package's Python writer) in a
:class:`foxglove.Context` of its own, so that a live server in the same process never
gets the recording's channels (nor the recording the server's).  The SDK only prints a
write error (for every message after it) and raises it at the end; it writes here
through a Python file object that keeps the first error (:attr:`McapFile.failure`) and
swallows the rest, so the owner can end a failed recording at once and quietly.
Everything logged goes as JSON (``jsonschema`` schemas: the Raw Messages and Plot panels
show every field; ``mcap cat --json`` prints them).

Channels (topics):

- ``/CAN0/frames`` ... one per bus, schema :data:`FRAME_SCHEMA` (``ucom.CanFrame``):
  ``time`` (the frame's time on its bus's time base, seconds), ``id``, ``extended``,
  ``remote``, ``error``, ``direction`` (``rx``: from the bus, ``tx``: sent by this host),
  ``dlc`` and ``data`` (base64);
- ``/<Prefix>/values`` ... one per board (:mod:`ucom_tools.trace.mcap_record`);
- ``/joints`` (``foxglove.JointStates``) and ``/events`` (``foxglove.Log``).

Reading back (:func:`read_frames`, :func:`read_values`) uses the ``mcap`` package's
reader with its CRC checks on: a file that is cut short or damaged is bad input.
"""

from __future__ import annotations

import base64
import binascii
import contextlib
import json
import os
import threading
from collections.abc import Iterator
from decimal import Decimal
from pathlib import Path
from typing import IO, Any, Final

import can

from ucom_tools import fileio
from ucom_tools.errors import InputError, WriteError
from ucom_tools.fileio import Output, reason
from ucom_tools.protocol.traffic import ERROR, EXTENDED, REMOTE, SENT, SinkEntry

EXTENSION = ".mcap"

MCAP_LIMIT = 1 << 34
"""The largest MCAP file read back (16 GiB)."""

FRAME_SCHEMA_NAME = "ucom.CanFrame"
FRAME_SCHEMA: dict[str, Any] = {
    "title": FRAME_SCHEMA_NAME,
    "description": "One CAN frame of one bus, as the PC saw it (ucom(1), MCAP RECORDINGS)",
    "type": "object",
    "properties": {
        "time": {"type": "number",
                 "description": "seconds on the bus's time base (the frame's own stamp; the "
                                "message's log time is this mapped to the wall clock)"},
        "id": {"type": "integer", "minimum": 0, "description": "arbitration ID"},
        "extended": {"type": "boolean", "description": "29-bit identifier"},
        "remote": {"type": "boolean"},
        "error": {"type": "boolean"},
        "direction": {"type": "string", "enum": ["rx", "tx"],
                      "description": "rx: received from the bus; tx: sent by this host"},
        "dlc": {"type": "integer", "minimum": 0, "maximum": 8},
        "data": {"type": "string", "contentEncoding": "base64"},
    },
    "required": ["time", "id", "extended", "remote", "error", "direction", "dlc", "data"],
}
"""The JSON Schema of a frame (:func:`frame_json`)."""

_TIME = {"type": "object", "title": "time",
         "properties": {"sec": {"type": "integer", "minimum": 0},
                        "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999}}}

JOINTS_SCHEMA: dict[str, Any] = {
    "title": "foxglove.JointStates", "type": "object",
    "description": "The state of a set of joints at a given time",
    "properties": {
        "timestamp": _TIME,
        "joints": {"type": "array", "items": {
            "type": "object", "title": "foxglove.JointState",
            "properties": {"name": {"type": "string"}, "position": {"type": "number"},
                           "velocity": {"type": "number"},
                           "acceleration": {"type": "number"},
                           "effort": {"type": "number"}}}},
    },
}
"""Foxglove's ``foxglove.JointStates`` as JSON Schema (the panels know it by its name)."""

LOG_LEVELS = {"debug": 1, "info": 2, "warning": 3, "error": 4, "fatal": 5}
"""``foxglove.Log``'s levels (0 is UNKNOWN)."""

LOG_SCHEMA: dict[str, Any] = {
    "title": "foxglove.Log", "type": "object", "description": "A log message",
    "properties": {
        "timestamp": _TIME,
        "level": {"type": "integer", "enum": [0, *LOG_LEVELS.values()],
                  "description": "0 UNKNOWN, 1 DEBUG, 2 INFO, 3 WARNING, 4 ERROR, 5 FATAL"},
        "message": {"type": "string"}, "name": {"type": "string"},
        "file": {"type": "string"}, "line": {"type": "integer", "minimum": 0},
    },
}
"""Foxglove's ``foxglove.Log`` as JSON Schema."""

FRAMES_SUFFIX = "/frames"
JOINTS_TOPIC = "/joints"
EVENTS_TOPIC = "/events"
ROBOT_METADATA = "ucom.robot"
"""The name of the metadata record that holds the robot's structure."""


def is_mcap(path: str | os.PathLike[str]) -> bool:
    """Does ``path`` name an MCAP file (by its extension)?"""
    return os.fspath(path).lower().endswith(EXTENSION)


def frames_topic(bus: str) -> str:
    """The topic of bus ``bus``'s frames (``/CAN0/frames``)."""
    return f"/{bus}{FRAMES_SUFFIX}"


def _flags_json(flags: int) -> bytes:
    """The fields between a frame's ``id`` and its ``dlc`` for the hand-over's flags."""
    def word(on: bool) -> str:
        return "true" if on else "false"
    return (f',"extended":{word(bool(flags & EXTENDED))},"remote":{word(bool(flags & REMOTE))},'
            f'"error":{word(bool(flags & ERROR))},'
            f'"direction":"{"tx" if flags & SENT else "rx"}","dlc":').encode("ascii")


_FLAGS_JSON: Final = tuple(_flags_json(f) for f in range(16))
_FRAME_JSON: Final = b'{"time":%r,"id":%d%b%d,"data":"%b"}'


def frame_json(stamp: float, ident: int, data: bytes, *, extended: bool, remote: bool,
               error: bool, rx: bool, dlc: int | None = None) -> bytes:
    """One frame as :data:`FRAME_SCHEMA` says (formatted by hand: ``json.dumps`` costs
    several times as much)."""
    flags = ((EXTENDED if extended else 0) | (REMOTE if remote else 0)
             | (ERROR if error else 0) | (0 if rx else SENT))
    return _FRAME_JSON % (stamp, ident, _FLAGS_JSON[flags],
                          len(data) if dlc is None else dlc,
                          binascii.b2a_base64(data, newline=False))


def entry_json(entry: SinkEntry) -> bytes:
    """A frame the loop handed over (identifier, data, stamp, flags) as
    :func:`frame_json` writes it, in half its time: 25,000 frames a second of ARMAR-III
    pass here twice with ``--record run.mcap --foxglove``."""
    ident, data, stamp, flags = entry
    return _FRAME_JSON % (stamp, ident, _FLAGS_JSON[flags & 15], len(data),
                          binascii.b2a_base64(data, newline=False))


def stamp_json(ns: int) -> str:
    """A Foxglove time (``{"sec", "nsec"}``) of nanoseconds since the Unix epoch."""
    sec, nsec = divmod(ns, 1_000_000_000)
    return f'{{"sec":{sec},"nsec":{nsec}}}'


# ---------------------------------------------------------------------- the clock
WALL_SLACK_S = 1.0
"""A bus time base within this of the wall clock is taken as the wall clock itself."""


def wall_offset(stamp: float, wall: float) -> float:
    """What is added to the bus time ``stamp`` (taken at the wall clock's ``wall``) to
    make a log time, once for a whole recording: nothing where the bus's time base is
    the wall clock already (python-can's Unix time stamps, the virtual fleet paced to
    the wall), else the difference (an adapter counting from its own start, a virtual
    fleet ahead of the wall)."""
    offset = wall - stamp
    return 0.0 if abs(offset) < WALL_SLACK_S else offset


# ---------------------------------------------------------------------- writing
class _Sink:
    """The file object the SDK writes through: the first OSError is kept, and the rest
    of the recording goes nowhere (the owner discards the file)."""

    def __init__(self, stream: IO[bytes]) -> None:
        self.stream = stream
        self.failure: BaseException | None = None
        self._position = 0

    def write(self, data: bytes | bytearray) -> int:
        if self.failure is None:
            try:
                self.stream.write(data)
            except Exception as err:
                self.failure = err
        self._position += len(data)
        return len(data)

    def seek(self, offset: int, whence: int = 0) -> int:
        if self.failure is None:
            try:
                self._position = self.stream.seek(offset, whence)
            except Exception as err:
                self.failure = err
        elif whence == os.SEEK_SET:
            self._position = offset
        return self._position

    def tell(self) -> int:
        return self._position

    def flush(self) -> None:
        if self.failure is None:
            try:
                self.stream.flush()
            except Exception as err:
                self.failure = err


class McapFile:
    """One MCAP file being written (see the module docstring): :meth:`channel` makes a
    JSON channel, :meth:`log` writes a message, :meth:`metadata` a metadata record;
    :meth:`commit` or :meth:`discard` ends it.  Its methods are called from one thread
    at a time (the owner's writer thread); :attr:`failure` may be read from any.

    InputError (exit 3, nothing written) when ``path`` cannot be written: its
    directory missing, a directory, a device or FIFO that cannot seek (the writer goes
    back to complete each chunk's header)."""

    def __init__(self, path: str | os.PathLike[str], key: str,
                 out: Output | None = None) -> None:
        import foxglove
        from foxglove.mcap import MCAPWriteOptions

        self.path = Path(path)
        self.key = key
        self._own = out is None
        """Whether :meth:`commit` renames the file into place (else its owner does, after
        :meth:`finish`)."""
        self._out = out if out is not None else Output(self.path, key=key,
                                                        suffix=EXTENSION)
        self._lock = threading.Lock()
        try:
            stream = self._out.open("wb")
            stream.seek(0, os.SEEK_CUR)
        except OSError:
            with contextlib.suppress(Exception):
                stream.close()
            self._out.discard()
            raise InputError(f"cannot write {os.fspath(self.path)}: an MCAP file is "
                             "written to a regular file or a device that can seek (its "
                             "writer goes back to complete each chunk)", key=key) from None
        except WriteError as err:  # cannot even be opened: bad input, nothing written
            self._out.discard()
            raise InputError(f"cannot write {os.fspath(self.path)}: {reason(err)}",
                             key=key) from None
        self._stream = stream
        self._sink = _Sink(stream)
        self._context = foxglove.Context()
        self._channels: dict[str, Any] = {}
        self._closed = False
        try:  # one compression thread: the consumers' process is niced, not greedy
            self._writer = foxglove.open_mcap(
                self._sink, context=self._context,
                writer_options=MCAPWriteOptions(compression_threads=0))
        except Exception as err:
            stream.close()
            self._out.discard()
            raise InputError(f"cannot write {os.fspath(self.path)}: {reason(err)}",
                             key=key) from None

    @property
    def failure(self) -> BaseException | None:
        """The first error writing met (then nothing more was written)."""
        return self._sink.failure

    def channel(self, topic: str, schema: dict[str, Any],
                metadata: dict[str, str] | None = None) -> Any:
        """A JSON channel on ``topic`` with the JSON Schema ``schema`` (its ``title`` is
        the schema's name)."""
        import foxglove

        got = self._channels.get(topic)
        if got is None:
            got = self._channels[topic] = foxglove.Channel(
                topic, message_encoding="json",
                schema=foxglove.Schema(name=str(schema["title"]), encoding="jsonschema",
                                       data=json.dumps(schema).encode()),
                metadata=metadata or {}, context=self._context)
        return got

    def metadata(self, name: str, values: dict[str, str]) -> None:
        self._writer.write_metadata(name, values)

    def finish(self) -> None:
        """Write the file's summary and close it (idempotent); the error writing met,
        if any, is raised (as :meth:`Output.failed`: WriteError, exit 5)."""
        with self._lock:
            if not self._closed:
                self._closed = True
                try:
                    self._writer.close()
                except Exception as err:  # the sink keeps the cause where it was a write
                    if self._sink.failure is None:
                        self._sink.failure = err
                self._sink.flush()
                with contextlib.suppress(Exception):
                    self._stream.close()
        if self._sink.failure is not None:
            raise self._out.failed(self._sink.failure)

    def commit(self) -> None:
        """:meth:`finish`, then rename the file into place; WriteError (exit 5) and
        nothing kept where writing failed."""
        try:
            self.finish()
        except BaseException:
            self._out.discard()
            raise
        if self._own:
            self._out.commit()

    def discard(self) -> None:
        """Keep nothing (idempotent; after :meth:`commit` the file stays)."""
        with self._lock:
            if not self._closed:
                self._closed = True
                with contextlib.suppress(Exception):
                    self._writer.close()
                with contextlib.suppress(Exception):
                    self._stream.close()
        self._out.discard()


class McapFrameWriter:
    """python-can's face of an MCAP frame log (``--log FILE.mcap``, and ``ucom decode
    --to FILE.mcap``): what :class:`~ucom_tools.trace.logs.FrameWriter` hands frames to.
    Each frame goes to its bus's channel (:func:`frames_topic`; the frame's ``channel``
    is the bus name, ``CAN`` where it has none), log time its stamp mapped once to the
    wall clock (:func:`wall_offset`); a write error is raised here (the FrameWriter
    keeps it and drops the rest)."""

    def __init__(self, out: McapFile) -> None:
        self.out = out
        self._offset_ns: int | None = None
        self._last: dict[str, int] = {}

    def on_message_received(self, msg: can.Message) -> None:
        import time

        bus = "CAN" if msg.channel in (None, "") else str(msg.channel)
        if self._offset_ns is None:
            self._offset_ns = round(wall_offset(msg.timestamp, time.time()) * 1e9)
        ch = self.out.channel(frames_topic(bus), FRAME_SCHEMA, {"bus": bus})
        t = max(round(msg.timestamp * 1e9) + self._offset_ns, self._last.get(bus, 0))
        self._last[bus] = t
        data = bytes(msg.data)
        ch.log(frame_json(msg.timestamp, msg.arbitration_id, data,
                          extended=msg.is_extended_id, remote=msg.is_remote_frame,
                          error=msg.is_error_frame, rx=msg.is_rx, dlc=msg.dlc), log_time=t)
        if self.out.failure is not None:
            raise self.out.failure

    def stop(self) -> None:
        """Finish the file (its owner renames it into place)."""
        self.out.finish()


# ---------------------------------------------------------------------- reading
def messages_of(file: str) -> Iterator[tuple[Any, Any, Any]]:
    """Every message of the MCAP ``file`` in log-time order, CRCs checked."""
    from mcap.reader import make_reader

    binary = fileio.open_input(file, limit=MCAP_LIMIT, what="an MCAP file",
                               error=lambda text: InputError(text, file=file))
    with binary:
        try:
            reader = make_reader(binary, validate_crcs=True)
            messages = reader.iter_messages(log_time_order=True)
            while True:
                try:
                    item = next(messages)
                except StopIteration:
                    return
                yield item
        except InputError:
            raise
        except Exception as err:  # the reader raises anything from McapError to struct.error
            text = str(err).strip().splitlines()
            raise InputError("not a complete MCAP file (or a damaged one): "
                             f"{text[0] if text else type(err).__name__}", file=file) from None


def read_frames(path: str | os.PathLike[str]) -> list[can.Message]:
    """Every CAN frame of an MCAP file ucom wrote (its ``ucom.CanFrame`` channels), in
    time order, each with its bus's name as channel and its bus time as timestamp;
    InputError naming the file when it is not one."""
    file = os.fspath(path)
    out: list[can.Message] = []
    try:
        for schema, channel, message in messages_of(file):
            if schema is None or schema.name != FRAME_SCHEMA_NAME:
                continue
            bus = channel.metadata.get("bus") or channel.topic.strip("/").removesuffix(
                FRAMES_SUFFIX.strip("/")).strip("/") or "CAN"
            f = json.loads(message.data)
            data = base64.b64decode(f["data"], validate=True)
            out.append(can.Message(
                timestamp=float(f["time"]), arbitration_id=int(f["id"]),
                is_extended_id=bool(f["extended"]), is_remote_frame=bool(f["remote"]),
                is_error_frame=bool(f["error"]), is_rx=f["direction"] != "tx",
                dlc=int(f["dlc"]), data=data, channel=bus, check=False))
    except (KeyError, TypeError, ValueError, binascii.Error) as err:
        raise InputError(f"a {FRAME_SCHEMA_NAME} message that does not fit its schema: "
                         f"{err!r}", file=file) from None
    out.sort(key=lambda m: m.timestamp)
    return out


def read_json_messages(path: str | os.PathLike[str], schema_name: str,
                       ) -> Iterator[tuple[Any, int, dict[str, Any]]]:
    """(channel, log time, message) of every message of schema ``schema_name``, in log
    time order, numbers as :class:`~decimal.Decimal` (exact)."""
    file = os.fspath(path)
    for schema, channel, message in messages_of(file):
        if schema is not None and schema.name == schema_name:
            try:
                body = json.loads(message.data, parse_float=Decimal)
            except ValueError as err:
                raise InputError(f"a {schema_name} message that is not JSON: {err}",
                                 file=file) from None
            yield channel, message.log_time, body


__all__ = ["EVENTS_TOPIC", "EXTENSION", "FRAME_SCHEMA", "FRAME_SCHEMA_NAME", "JOINTS_SCHEMA",
           "JOINTS_TOPIC", "LOG_LEVELS", "LOG_SCHEMA", "ROBOT_METADATA", "McapFile",
           "McapFrameWriter", "entry_json", "frame_json", "frames_topic", "is_mcap", "messages_of",
           "read_frames", "read_json_messages", "stamp_json", "wall_offset"]
