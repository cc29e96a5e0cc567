"""Recording a run (``ucom remote run --record FILE``): every frame of every bus into a
python-can log, every value change of the exchanged edges into ``FILE.values.csv``.

:class:`RunRecorder` is a :class:`can.Listener`: the bus readers (the PC's loop) hand it
each frame, from several threads at once, and it only queues them: a thread of its own
writes them (:class:`~ucom_tools.trace.logs.FrameWriter`), so that no file keeps the
loop from its deadline; ``ucom remote run`` hands it the value changes on a thread of
their own too (:class:`~ucom_tools.ops.remote.publish.ChangeFeed`).  One lock keeps the
values file whole.  The log format follows
FILE's extension (:data:`FORMATS`, written by :func:`can.Logger`); the extension and the
directory are checked before anything is written.  Both files are written by the rules of
``ucom(1)``, FILES (:mod:`ucom_tools.fileio`): under temporary names beside their targets,
renamed into place by :meth:`RunRecorder.close`, so FILE and FILE.values.csv are complete
recordings or keep what they had, never half-written (a device or FIFO is written through).

The values file (``man/ucom.1``, ``remote plot``) is a CSV with the header
:data:`VALUES_HEADER`, one row per change of a value: ``timestamp`` (seconds, 6
decimals, the bus clock of the frame that carried it), ``bus``, ``board`` (seq ID),
``prefix`` (the board's attribute-tree prefix), ``name`` (the edge's robot-wide unique
name), ``kind`` (CI, SO or PAR), ``value`` (exact decimal text) and ``valid`` (1; 0 when
its board was lost then: :meth:`RunRecorder.lost` writes such a row for each of the
board's edges, with its last value, and the edge's next value is written as valid even
where it is the same).  :func:`read_values` reads it back (for ``ucom remote plot``,
which leaves a gap where values were stale; a file without ``valid`` is all valid),
naming FILE:LINE of what does not fit.
"""

from __future__ import annotations

import contextlib
import csv
import io
import math
import os
import threading
from collections.abc import Iterable
from dataclasses import dataclass, field
from decimal import Decimal, InvalidOperation
from enum import Enum
from pathlib import Path
from types import TracebackType
from typing import IO

import can

from ucom_tools import fileio
from ucom_tools.errors import InputError, WriteError
from ucom_tools.fileio import Batch, Output, reason
from ucom_tools.trace.logs import (
    FrameWriter,
    LogError,
    check_buses,
    log_extension,
    not_kept,
)

VALUES_SUFFIX = ".values.csv"
"""Appended to the full name of the frame log: run.blf -> run.blf.values.csv."""

VALUES_HEADER = ("timestamp", "bus", "board", "prefix", "name", "kind", "value", "valid")
"""The columns of the values file, in this order."""
REQUIRED = VALUES_HEADER[:-1]
"""The columns a values file must have (files of earlier versions have no ``valid``)."""

KINDS = ("CI", "SO", "PAR")
"""The edge kinds of the ``kind`` column."""

def values_path(path: str | os.PathLike[str]) -> Path:
    """The values file recorded beside the frame log ``path``."""
    p = Path(path)
    return p.with_name(p.name + VALUES_SUFFIX)


def value_text(value: int | float | Decimal) -> str:
    """``value`` as exact decimal text: ints as ints, Decimals in positional notation,
    floats as the shortest text that reads back as the same float (never 1e-05)."""
    if isinstance(value, bool):
        return str(int(value))
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"not a finite value: {value!r}")
        value = Decimal(repr(value))
    if isinstance(value, Decimal):
        if not value.is_finite():
            raise ValueError(f"not a finite value: {value!r}")
        return format(value, "f")
    raise TypeError(f"a value must be int, float or Decimal, not {type(value).__name__}")


def kind_text(kind: str | Enum) -> str:
    """CI, SO or PAR from a string, ``attrtree.TreeEdgeKind``, ``mca.Kind`` or ``EdgeKind``."""
    text = kind.name if isinstance(kind, Enum) else str(kind)
    if text not in KINDS:
        raise ValueError(f"kind must be one of {', '.join(KINDS)}, not {kind!r}")
    return text


class RunRecorder(can.Listener):
    """Records a run: frames into a python-can log at ``path``, value changes into
    ``path.values.csv`` (see the module docstring).

    Thread-safe: :meth:`on_message_received` and :meth:`value` may be called from any
    thread.  Frames arriving after :meth:`close` are ignored (bus readers may still be
    delivering); a :meth:`value` after close is a ValueError.  As a context manager the
    files are kept when the block ends, also by an exception (the recording of a failed
    run is what one wants to look at), except after an :class:`InputError` (exit code 3
    promises that nothing was written), which discards them.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.values_path = values_path(self.path)
        self.extension = log_extension(self.path)
        self._lock = threading.Lock()
        self._rows = 0
        self._last: dict[tuple[str, int, str], tuple[Decimal | None, str, str, str]] = {}
        """(bus, board, name) -> the last value recorded (None: it is stale, the next is
        written whatever it is), its prefix, kind and text."""
        self._closed = False
        self._failure: BaseException | None = None
        self._batch = Batch(key="record")
        self._frames: FrameWriter | None = None
        self._values_file: IO[str] | None = None
        try:
            log_out = self._output(self.path, self.extension)
            self._frames = FrameWriter(log_out, self.extension)
            values_out = self._output(self.values_path, VALUES_SUFFIX)
            self._values_file = values_out.open("w", encoding="utf-8", newline="")
            self._csv = csv.writer(self._values_file, lineterminator="\n")
            self._csv.writerow(VALUES_HEADER)
        except WriteError as err:
            self._discard()
            raise InputError(err.reason, key="record") from None
        except OSError as err:
            self._discard()
            raise InputError(f"cannot write {os.fspath(self.path)}: {reason(err)}",
                             key="record") from None
        except BaseException:
            self._discard()
            raise

    def _output(self, target: Path, suffix: str) -> Output:
        """Where ``target`` is written (``ucom(1)``, FILES): a temporary file beside it
        whose name ends in ``suffix`` (python-can picks the format by it), or the device
        or FIFO itself."""
        return self._batch.output(target, suffix=suffix)

    # --------------------------------------------------------------------- counters
    @property
    def frames(self) -> int:
        """Frames recorded so far."""
        return self._frames.frames if self._frames is not None else 0

    @property
    def channels(self) -> dict[str, int]:
        """Bus name -> channel number stored in the formats of :data:`INT_CHANNELS`."""
        return self._frames.channels if self._frames is not None else {}

    @property
    def rows(self) -> int:
        """Value rows written so far (changes, the first value of each edge included)."""
        with self._lock:
            return self._rows

    @property
    def closed(self) -> bool:
        return self._closed

    # --------------------------------------------------------------------- frames
    def check_buses(self, buses: Iterable[str]) -> None:
        """InputError when this recording's format cannot keep ``buses`` apart."""
        check_buses(self.extension, buses, self.path, "record")

    def on_message_received(self, msg: can.Message) -> None:
        """Record one frame (its ``channel``, the bus name, is kept: verbatim in the
        text formats, as the bus's number in :data:`INT_CHANNELS`)."""
        if self._frames is not None:  # after close, it drops the frame
            self._frames.write(msg)

    def on_error(self, exc: Exception) -> None:
        """A bus reader's error is the reader's business; the recording goes on."""

    def stop(self) -> None:
        """:class:`can.Notifier` ends its listeners with this: same as :meth:`close`."""
        self.close()

    # --------------------------------------------------------------------- values
    def value(self, timestamp: float, bus: str, board: int, prefix: str, name: str,
              kind: str | Enum, value: int | float | Decimal) -> bool:
        """Record ``value`` of edge ``name`` (unique name) of board ``board`` (seq ID,
        tree prefix ``prefix``) on ``bus`` at ``timestamp`` (seconds, bus clock) when it
        differs (numerically) from the last one recorded for (bus, board, name); the
        first is always written, and the first after its board was :meth:`lost`.  True
        when a row was written."""
        text = value_text(value)
        kind_ = kind_text(kind)
        number = Decimal(text)
        key = (bus, int(board), name)
        with self._lock:
            if self._closed:
                raise ValueError(f"{self.values_path}: the recorder is closed")
            self._raise_failure()
            last = self._last.get(key)
            if last is not None and last[0] == number:
                return False
            self._row(timestamp, bus, board, prefix, name, kind_, text, 1)
            self._last[key] = (number, prefix, kind_, text)
            return True

    def fresh(self, timestamp: float, bus: str, board: int, prefix: str, name: str,
              kind: str | Enum, value: int | float | Decimal) -> bool:
        """:meth:`value` of an edge only where it is stale (its board was lost since its
        last row): its value is current again, even where the same as before."""
        with self._lock:
            last = self._last.get((bus, int(board), name))
            if last is None or last[0] is not None:
                return False
        return self.value(timestamp, bus, board, prefix, name, kind, value)

    def lost(self, timestamp: float, bus: str, board: int) -> int:
        """Board ``board`` of ``bus`` was lost at ``timestamp``: a row with ``valid`` 0 and
        its last value for each of its edges recorded so far (its values are stale from
        then on, until the next of each); how many rows."""
        with self._lock:
            if self._closed:
                raise ValueError(f"{self.values_path}: the recorder is closed")
            self._raise_failure()
            n = 0
            for key, (number, prefix, kind_, text) in list(self._last.items()):
                if key[0] == bus and key[1] == int(board) and number is not None:
                    self._row(timestamp, bus, board, prefix, key[2], kind_, text, 0)
                    self._last[key] = (None, prefix, kind_, text)
                    n += 1
            return n

    def _row(self, timestamp: float, bus: str, board: int, prefix: str, name: str,
             kind: str, text: str, valid: int) -> None:
        try:
            self._csv.writerow((f"{float(timestamp):.6f}", bus, int(board), prefix, name,
                                kind, text, valid))
        except Exception as err:
            self._failure = err
            self._raise_failure()
        self._rows += 1

    def check(self) -> None:
        """LogError when writing either file failed (cheap: the loop calls it every
        cycle, so that a recording that failed ends the run as a failed write would)."""
        if self._failure is not None or (self._frames is not None
                                         and self._frames.failure is not None):
            with self._lock:
                self._raise_failure()

    def _raise_failure(self) -> None:
        err = self._failure or (self._frames.failure if self._frames is not None else None)
        if err is not None:
            raise LogError(f"{self.path}: {reason(err)}; nothing was kept",
                           path=str(self.path), key="record") from err

    # --------------------------------------------------------------------- end
    def close(self) -> None:
        """Flush both files and rename them into place (idempotent).  LogError, and
        no files, when writing failed."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            if self._frames is not None:
                self._frames.stop()
            try:
                if self._values_file is not None:
                    self._values_file.close()
            except Exception as err:
                if self._failure is None:
                    self._failure = err
            if self._failure is not None or (self._frames is not None
                                             and self._frames.failure is not None):
                self._discard()
                self._raise_failure()
            try:
                self._batch.commit()  # both synced before either is renamed
            except WriteError as err:
                self._failure = err
                self._discard()
                raise not_kept(err) from None

    def discard(self) -> None:
        """End the recording without keeping anything (idempotent; after :meth:`close`
        the files stay)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._discard()

    def _discard(self) -> None:
        if self._frames is not None:
            self._frames.stop()
        with contextlib.suppress(Exception):
            if self._values_file is not None:
                self._values_file.close()
        self._batch.discard()

    def __enter__(self) -> RunRecorder:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if isinstance(exc, InputError):
            self.discard()
        else:
            self.close()

    def __repr__(self) -> str:
        return (f"RunRecorder({os.fspath(self.path)!r}, frames={self._frames}, "
                f"rows={self._rows}{', closed' if self._closed else ''})")


# ------------------------------------------------------------------------- reading
@dataclass
class Series:
    """One edge's recorded values: (timestamp, value) per change, in time order."""

    prefix: str
    name: str
    kind: str
    bus: str
    board: int
    points: list[tuple[float, Decimal]] = field(default_factory=list)
    """The valid values."""
    stale: list[tuple[float, float | None]] = field(default_factory=list)
    """(from, until) where the edge's board was lost: its value stale from its row with
    ``valid`` 0 to its next valid row (None: to the end)."""

    @property
    def qualified(self) -> str:
        """``Prefix/Unique name``, as the plot and its NAME arguments call it."""
        return f"{self.prefix}/{self.name}"


@dataclass(frozen=True)
class Values:
    """A values file read back: its series by qualified name (in order of first
    appearance) and the time span of all its rows (None when it has no rows)."""

    file: str
    series: dict[str, Series]
    start: float | None
    end: float | None


VALUES_LIMIT = 1 << 30
"""The largest values file read (1 GiB: about ten hours of ARMAR-III's exchange)."""


def read_values(path: str | os.PathLike[str]) -> Values:
    """Read a values file written by :class:`RunRecorder`; InputError naming FILE:LINE
    when it is not one (missing header column, bad number or kind, short row).  An MCAP
    recording's values: :func:`~ucom_tools.trace.mcap_values.read_mcap_values`."""
    file = os.fspath(path)
    series: dict[str, Series] = {}
    rows_of: dict[str, list[tuple[float, Decimal, bool]]] = {}
    start: float | None = None
    end: float | None = None
    line = 1
    try:
        binary = fileio.open_input(file, limit=VALUES_LIMIT, what="a values file",
                                   error=lambda text: InputError(text, file=file))
        with io.TextIOWrapper(binary, encoding="utf-8", newline="") as f:
            reader = csv.reader(f)
            header = next(reader, None)
            if header is None:
                raise InputError("empty file: not a values file (header "
                                 f"{','.join(VALUES_HEADER)})", file=file, line=1)
            missing = [c for c in REQUIRED if c not in header]
            if missing:
                raise InputError(f"not a values file: the header lacks {', '.join(missing)} "
                                 f"(expected {','.join(VALUES_HEADER)})", file=file, line=1)
            col = {c: header.index(c) for c in VALUES_HEADER if c in header}
            width = max(col.values()) + 1
            for row in reader:
                line = reader.line_num
                if not row:
                    continue
                if len(row) < width:
                    raise InputError(f"{len(row)} fields, expected {len(header)}", file=file,
                                     line=line)
                t = _number(row[col["timestamp"]], "timestamp", file, line)
                board = _board(row[col["board"]], file, line)
                value = _decimal(row[col["value"]], file, line)
                kind, prefix, name = (row[col[c]] for c in ("kind", "prefix", "name"))
                if kind not in KINDS:
                    raise InputError(f"kind: {kind!r} is not one of {', '.join(KINDS)}",
                                     file=file, line=line)
                if not name:
                    raise InputError("name: empty", file=file, line=line)
                valid = True
                if "valid" in col:
                    flag = row[col["valid"]].strip()
                    if flag not in ("0", "1"):
                        raise InputError(f"valid: {flag!r} is not 0 or 1", file=file,
                                         line=line)
                    valid = flag == "1"
                key = f"{prefix}/{name}"
                s = series.get(key)
                if s is None:
                    s = series[key] = Series(prefix, name, kind, row[col["bus"]], board)
                    rows_of[key] = []
                rows_of[key].append((t, value, valid))
                start = t if start is None else min(start, t)
                end = t if end is None else max(end, t)
    except OSError as err:
        raise InputError(f"cannot read: {err.strerror or err}", file=file) from None
    except UnicodeDecodeError:
        raise InputError("not UTF-8 text: not a values file", file=file, line=line) from None
    except csv.Error as err:
        raise InputError(f"not a CSV file: {err}", file=file, line=line) from None
    for key, s in series.items():
        since: float | None = None
        for t, value, valid in sorted(rows_of[key], key=lambda r: r[0]):
            if valid:
                if since is not None:
                    s.stale.append((since, t))
                    since = None
                s.points.append((t, value))
            elif since is None:
                since = t
        if since is not None:
            s.stale.append((since, None))
    return Values(file, series, start, end)


def _number(text: str, column: str, file: str, line: int) -> float:
    try:
        t = float(text)
    except ValueError:
        raise InputError(f"{column}: {text!r} is not a number", file=file,
                         line=line) from None
    if not math.isfinite(t):
        raise InputError(f"{column}: {text!r} is not a finite number", file=file, line=line)
    return t


def _board(text: str, file: str, line: int) -> int:
    try:
        return int(text)
    except ValueError:
        raise InputError(f"board: {text!r} is not a seq ID", file=file, line=line) from None


def _decimal(text: str, file: str, line: int) -> Decimal:
    try:
        d = Decimal(text.strip())
    except InvalidOperation:
        d = None
    if d is None or not d.is_finite():
        raise InputError(f"value: {text!r} is not a decimal number", file=file, line=line)
    return d



__all__ = ["KINDS", "VALUES_HEADER", "VALUES_SUFFIX", "LogError",
           "RunRecorder", "Series", "Values", "log_extension", "read_values",
           "value_text", "values_path"]

