"""Key expressions and payloads of the robot's network (``man/ucom-network.7``).

Every key starts with ``ucom/<robot>``; a board's keys with ``ucom/<robot>/<bus>/<board>``
(its seq ID on the bus).  An edge's key ends in its unique name, escaped for a key
expression (:func:`escape`: ``%``, ``/``, ``*``, ``$``, ``?``, ``#`` as ``%XX``; spaces stay).
Every payload is a JSON object with ``"v": VERSION``, sent with Zenoh's encoding
``application/json``.
"""

from __future__ import annotations

import json
from decimal import Decimal
from pathlib import PurePath
from typing import Any

from ucom_tools.errors import InputError

VERSION = 1
"""The payloads' version (their ``"v"`` field): a reader refuses another."""
PREFIX = "ucom"
DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
"""Where ``remote run --zenoh`` listens and ``browse`` connects when no endpoint is given:
loopback only."""

KEYS = {
    "structure": "ucom/{robot}/structure",
    "alive": "ucom/{robot}/alive",
    "events": "ucom/{robot}/events",
    "set": "ucom/{robot}/set",
    "stop": "ucom/{robot}/stop",
    "values": "ucom/{robot}/{bus}/{board}/values",
    "edge": "ucom/{robot}/{bus}/{board}/edge/{name}",
    "board_alive": "ucom/{robot}/{bus}/{board}/alive",
    "status": "ucom/{robot}/{bus}/{board}/status",
}
"""Every key expression (``man/ucom-network.7`` lists the same; a test compares them)."""

_ESCAPED = "%/*$?#"


def check_rate(publish_hz: float, loop_hz: float) -> None:
    """InputError unless 0 < ``publish_hz`` <= ``loop_hz``."""
    if not 0 < publish_hz <= loop_hz * 1.0001:
        raise InputError(f"the publishing rate must be more than 0 and at most the loop's "
                         f"rate ({loop_hz:g} Hz), not {publish_hz:g}", key="publish_hz")


def robot_id(source: str, name: str) -> str:
    """The robot's chunk of every key: the topology's file name without its extension
    (``armar3`` for the bundled ARMAR-III, ``head`` for ``head.toml``), else its name."""
    stem = PurePath(source).name.rsplit(".", 1)[0] if source else ""
    return stem or name


def escape(chunk: str) -> str:
    """``chunk`` as one chunk of a key expression: the characters a key cannot hold (and
    ``%``) as ``%XX``; an empty chunk as ``%``.  :func:`unescape` undoes it."""
    if not chunk:
        return "%"
    return "".join(f"%{ord(c):02X}" if c in _ESCAPED or ord(c) < 0x20 else c for c in chunk)


def unescape(chunk: str) -> str:
    if chunk == "%":
        return ""
    out, i = [], 0
    while i < len(chunk):
        code = chunk[i + 1:i + 3]
        if chunk[i] == "%" and len(code) == 2 and all(c in "0123456789ABCDEFabcdef"
                                                      for c in code):
            out.append(chr(int(code, 16)))
            i += 3
        else:
            out.append(chunk[i])
            i += 1
    return "".join(out)


def robot_key(robot: str, what: str) -> str:
    """``ucom/<robot>/<what>`` for the robot-wide keys (structure, alive, events, set, stop)."""
    return KEYS[what].format(robot=escape(robot))


def board_key(robot: str, bus: str, board: int, what: str = "values") -> str:
    """``ucom/<robot>/<bus>/<board>/values`` (or ``board_alive``, ``status``)."""
    return KEYS[what].format(robot=escape(robot), bus=escape(bus), board=board)


def edge_key(robot: str, bus: str, board: int, unique: str) -> str:
    return KEYS["edge"].format(robot=escape(robot), bus=escape(bus), board=board,
                               name=escape(unique))


def number(value: object) -> int | float | str | None:
    """A value as a JSON number: ints as they are, decimals as floats (an edge's value is
    raw x 10^exponent: a float carries it exactly enough to be read back exactly)."""
    if value is None or isinstance(value, int | float):
        return value
    if isinstance(value, Decimal):
        return int(value) if value == value.to_integral_value() else float(value)
    return str(value)


def dumps(document: dict[str, Any]) -> bytes:
    """A payload: compact JSON with the version first."""
    return json.dumps({"v": VERSION, **document}, separators=(",", ":"),
                      ensure_ascii=False).encode()


def loads(payload: bytes | str) -> dict[str, Any]:
    """A payload's document; ValueError for one that is not ours (not JSON, not an object,
    another version)."""
    doc = json.loads(payload)
    if not isinstance(doc, dict):
        raise ValueError("not a JSON object")
    if doc.get("v") != VERSION:
        raise ValueError(f"payload version {doc.get('v')!r}, this reader knows {VERSION}")
    return doc
