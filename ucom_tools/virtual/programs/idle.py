"""A program the virtual fleet has no model of: it runs, offers no edges, does nothing."""

from __future__ import annotations

from typing import Final

from ucom_tools.edgelists.model import ProgramSpec

BASE_US: Final = 100.0
"""The MCA loop with nothing to control (dissertation 5.4.2: circa 100 us at 1 ms)."""


class IdleModel:
    """A program with no edges, cycling at 1 ms."""

    def __init__(self) -> None:
        self.spec = ProgramSpec("idle", "a program without a model: no edges", ())
        self.ci: list[int] = []
        self.so: list[int] = []
        self.par: list[int] = []

    def loop_us(self) -> float:
        return 1000.0

    def step(self, dt_us: float) -> float:
        return BASE_US

    def stop(self) -> None:
        pass

    def release(self) -> None:
        pass
