"""Field checks shared by the message codecs: each names the field it rejects."""

from __future__ import annotations

from enum import IntEnum
from typing import TypeVar

from ucom_tools.errors import FrameError

E = TypeVar("E", bound=IntEnum)


def check_length(name: str, data: bytes, *allowed: int) -> None:
    if len(data) not in allowed:
        want = " or ".join(str(n) for n in allowed)
        raise FrameError(f"{name} payload length", f"expected {want} bytes, got {len(data)}")


def check_enum(enum: type[E], field: str, value: int) -> E:
    try:
        return enum(value)
    except ValueError:
        raise FrameError(field, f"reserved value 0x{value:02X}") from None


def check_range(field: str, value: int, low: int, high: int) -> None:
    if not low <= value <= high:
        raise FrameError(field, f"must be {low}..{high}, got {value}")
