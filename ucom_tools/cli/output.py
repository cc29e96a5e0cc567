"""Output: data to stdout (tables for people, JSON when asked), the rest to stderr.

The two rich consoles are made for each invocation (:func:`reset`), so the width follows
the situation of that run: ``COLUMNS`` when set, the terminal's width when standard output
is a terminal, and no limit when it is piped (a table is never cut short in a file or
a pipe; tables wrap their cells instead of truncating them on a narrow terminal).
"""

from __future__ import annotations

import json
import os
import sys
from decimal import Decimal
from typing import Any

from rich.console import Console

UNLIMITED = 100_000
"""Width of a piped standard output: tables take the width they need."""

_consoles: dict[str, Console] = {}
_emitted = {"json": False}


def _stdout_width() -> int | None:
    columns = os.environ.get("COLUMNS", "")
    if columns.isdigit() and int(columns) > 0:
        return int(columns)
    try:
        if sys.stdout.isatty():
            return None  # rich measures the terminal
    except (AttributeError, ValueError):
        pass
    return UNLIMITED


def reset() -> None:
    """Forget the consoles; the next use makes them for the current streams and env."""
    _consoles.clear()
    _emitted["json"] = False


def json_emitted() -> bool:
    """Whether this invocation printed its JSON document already."""
    return _emitted["json"]


def stdout() -> Console:
    """The console for data (tables); see the module docstring for its width."""
    c = _consoles.get("out")
    if c is None:
        c = _consoles["out"] = Console(highlight=False, soft_wrap=False, emoji=False,
                                       width=_stdout_width())
    return c


def stderr() -> Console:
    """The console for progress, notes and errors."""
    c = _consoles.get("err")
    if c is None:
        c = _consoles["err"] = Console(stderr=True, highlight=False, emoji=False)
    return c


def json_number(value: object) -> int | float | None:
    """A value for JSON as a number (an int where it is whole, else a float), from a
    number or its exact text (``1000``, ``0.0005``, ``0x444``); the exact text, where it
    matters, goes in a field of its own."""
    if value is None:
        return None
    if isinstance(value, bool):
        return int(value)
    if isinstance(value, int):
        return value
    if isinstance(value, str):
        text = value.strip()
        body = text.lstrip("-")
        if body.lower().startswith("0x"):
            n = int(body, 16)
            return -n if text.startswith("-") else n
        value = Decimal(text)
    if isinstance(value, Decimal):
        return int(value) if value == value.to_integral_value() else float(value)
    return float(value)  # type: ignore[arg-type]


def emit_json(data: Any) -> None:
    _emitted["json"] = True
    sys.stdout.write(json.dumps(data, indent=2, default=str) + "\n")
    sys.stdout.flush()


LED_STYLE = {"red": "red", "yellow": "yellow", "green": "green"}


def leds(state: dict[str, str]) -> str:
    """LEDs as coloured dots: ● on, ◐ blinking (with its rate when known), · off."""
    parts = []
    for colour in ("red", "yellow", "green"):
        v = state.get(colour, "off")
        mark = {"on": "●", "blink": "◐"}.get(v, "·")
        parts.append(f"[{LED_STYLE[colour]}]{mark}[/]" if v != "off" else "[dim]·[/]")
    text = " ".join(parts)
    if state.get("green") == "blink" and "green_hz" in state:
        text += f" {state['green_hz']} Hz"
    return text
