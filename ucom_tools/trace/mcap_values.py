"""The values of an MCAP recording read back (``ucom remote plot run.mcap NAME``): each
board's ``/<Prefix>/values`` channel (:mod:`ucom_tools.trace.mcap_record`) as the same
:class:`~ucom_tools.trace.record.Values` a values CSV gives, so that ``remote plot``
draws either: a point where an edge's value changed (the samples between repeat it),
stale from a sample whose ``valid`` is false to the next valid one; times are the
samples' bus time (``time``), as in the CSV."""

from __future__ import annotations

import json
import os
from decimal import Decimal
from typing import Any

from ucom_tools.errors import InputError
from ucom_tools.trace.mcap_record import VALUES_SCHEMA_PREFIX
from ucom_tools.trace.mcapfile import messages_of
from ucom_tools.trace.record import Series, Values


def _edges(channel: Any, file: str) -> list[tuple[str, str, str]]:
    """(key, robot-wide name, kind) of a values channel's edges (its metadata)."""
    try:
        return [(str(k), str(n), str(kind)) for k, n, kind, *_ in
                json.loads(channel.metadata["edges"])]
    except (KeyError, ValueError, TypeError) as err:
        raise InputError(f"values channel {channel.topic}: its 'edges' metadata is not "
                         f"ucom's ({err!r})", file=file) from None


def read_mcap_values(path: str | os.PathLike[str]) -> Values:
    """Every board's values of an MCAP recording (see the module docstring); InputError
    naming the file when it is not one ucom wrote or holds no values channel."""
    file = os.fspath(path)
    series: dict[str, Series] = {}
    keys: dict[int, list[tuple[str, Series]]] = {}
    since: dict[str, float] = {}
    start: float | None = None
    end: float | None = None
    for schema, channel, message in messages_of(file):
        if schema is None or not schema.name.startswith(VALUES_SCHEMA_PREFIX):
            continue
        slots = keys.get(channel.id)
        if slots is None:
            slots = keys[channel.id] = []
            prefix, bus = channel.metadata.get("prefix", ""), channel.metadata.get("bus", "")
            board = int(channel.metadata.get("board", "0") or 0)
            for key, name, kind in _edges(channel, file):
                s = series.setdefault(f"{prefix}/{name}", Series(prefix, name, kind, bus,
                                                                 board))
                slots.append((key, s))
        try:
            body = json.loads(message.data, parse_float=Decimal)
            t = float(body["time"])
            valid = bool(body["valid"])
        except (ValueError, KeyError, TypeError) as err:
            raise InputError(f"a message of {channel.topic} that is not ucom's values "
                             f"({err!r})", file=file) from None
        start = t if start is None else min(start, t)
        end = t if end is None else max(end, t)
        for key, s in slots:
            _point(s, t, valid, body.get(key), since)
    if not keys:
        raise InputError("no values in the file: the MCAP recording of a run has a "
                         f"{VALUES_SCHEMA_PREFIX}* channel per board", file=file)
    for name, t in since.items():
        series[name].stale.append((t, None))
    return Values(file, series, start, end)


def _point(s: Series, t: float, valid: bool, raw: Any, since: dict[str, float]) -> None:
    """One sample of one edge into its series."""
    if raw is None:
        return
    q = s.qualified
    if not valid:
        since.setdefault(q, t)
        return
    value = raw if isinstance(raw, Decimal) else Decimal(raw)
    was = since.pop(q, None)
    if was is not None:
        s.stale.append((was, t))
    elif s.points and s.points[-1][1] == value:
        return
    s.points.append((t, value))


__all__ = ["read_mcap_values"]
