"""Output helpers: data to stdout (tables for people, JSON when asked), the rest to stderr."""

from __future__ import annotations

import json
import sys
from typing import Any

from rich.console import Console


def _width() -> int | None:
    # Pipes and CI get rich's 80 columns by default; tables of boards need more.
    return None if sys.stdout.isatty() else 132


out = Console(highlight=False, soft_wrap=False, width=_width(), emoji=False)
err = Console(stderr=True, highlight=False, emoji=False)

LED_STYLE = {"red": "red", "yellow": "yellow", "green": "green"}


def emit_json(data: Any) -> None:
    sys.stdout.write(json.dumps(data, indent=2, default=str) + "\n")


def leds(state: dict[str, str]) -> str:
    """LEDs as coloured dots: ● on, ◐ blinking, · off."""
    parts = []
    for colour in ("red", "yellow", "green"):
        v = state.get(colour, "off")
        mark = {"on": "●", "blink": "◐"}.get(v, "·")
        parts.append(f"[{LED_STYLE[colour]}]{mark}[/]" if v != "off" else "[dim]·[/]")
    return " ".join(parts)

