"""A conformance case: what it checks, which protocol page section, what it writes."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ucom_tools.conformance.bench import Bench

GROUPS = ("identifiers", "reset", "init chain", "info", "program enable", "programming",
          "extram", "autostart", "fpga", "run time", "bad input")
"""The groups, in the order of the protocol page."""


@dataclass(frozen=True)
class Case:
    id: str
    """group.short-name, e.g. ``init.numbering``."""
    group: str
    title: str
    section: str
    """The protocol page section the case checks (``INIT CHAIN``, ``RUN TIME, Watchdog``)."""
    run: Callable[[Bench], None] = field(compare=False, repr=False)
    writes: str = ""
    """What the case changes on the boards (and the runner restores); "" = nothing."""


REGISTRY: list[Case] = []


def case(id: str, group: str, section: str, *, writes: str = ""
         ) -> Callable[[Callable[[Bench], None]], Callable[[Bench], None]]:
    """Register a case function; its docstring's first line is its title."""
    if group not in GROUPS:
        raise ValueError(f"unknown group {group!r}")

    def register(fn: Callable[[Bench], None]) -> Callable[[Bench], None]:
        title = (fn.__doc__ or id).strip().splitlines()[0]
        if any(c.id == id for c in REGISTRY):
            raise ValueError(f"case {id} registered twice")
        REGISTRY.append(Case(id, group, title, section, fn, writes))
        return fn
    return register
