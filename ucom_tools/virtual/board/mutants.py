"""Mutant boards: documented defects a virtual UCoM can be given, to prove a conformance
suite (issue 12: a suite is only as good as the defects it catches).

Each :class:`Defect` names one deviation from ``man/ucom-protocol.7``: a one-line title,
the section of the page it violates and the symptom a host observes on the bus.  A board
gets a defect from its topology (``defect = "NAME"`` in its ``[[bus.board]]`` table) or
from its fleet (``Fleet(topology, defect="NAME")``, ``ucom fleet serve --defect NAME``:
every board that does not name its own); :func:`defects` lists the catalogue.

A defect changes only what its title says; everything else the board does stays as the
page specifies.  Without a defect a board behaves exactly as before: the hooks in
:mod:`~ucom_tools.virtual.board.ucom`, :mod:`~ucom_tools.virtual.board.programming` and
:mod:`~ucom_tools.virtual.board.runtime` compare the board's defect with the names here and
fall through to the conforming code when it is not theirs.

The catalogue itself (names, titles, sections, symptoms) is
:mod:`ucom_tools.config.mutants`, where the topology parser checks names; it is
re-exported here.  This module adds the defects' figures and the hooks' helpers.
"""

from __future__ import annotations

from collections.abc import Sequence

from ucom_tools.config.mutants import (
    ACCEPT_BAD_PROGID,
    AUTOSTART_LOST,
    BY_NAME,
    CATALOGUE,
    CI_WHILE_LATCHED,
    DESCR_TRUNCATED,
    DIGEST_UNKNOWN,
    DIGEST_WRONG,
    DUMP_OFF_BY_ONE,
    IGNORE_ALIVE,
    IGNORE_INITOUT,
    INFO_SWAPPED,
    INIT_TWICE,
    LATE_ANSWER,
    NAMES,
    NO_RANGE_CHECK,
    PROMISCUOUS,
    READY_COUNTS_WRONG,
    SEQ_FROM_ZERO,
    SO_SLOW,
    UNKNOWN_FUNCTION_SILENT,
    WRONG_PROGID,
    XRESET_KEEPS_AUTOSTART,
    Defect,
    check,
    defects,
    listing,
    unknown,
)
from ucom_tools.protocol.timeouts import DEFAULT

__all__ = [
    "ACCEPT_BAD_PROGID",
    "AUTOSTART_LOST",
    "BY_NAME",
    "CATALOGUE",
    "CI_WHILE_LATCHED",
    "DESCR_NAME_CHARS",
    "DESCR_TRUNCATED",
    "DIGEST_FLIP",
    "DIGEST_UNKNOWN",
    "DIGEST_WRONG",
    "DUMP_OFF_BY_ONE",
    "IGNORE_ALIVE",
    "IGNORE_INITOUT",
    "INFO_SWAPPED",
    "INIT_TWICE",
    "LATE_ANSWER",
    "LATE_FACTOR",
    "LATE_US",
    "NAMES",
    "NO_RANGE_CHECK",
    "PROMISCUOUS",
    "READY_COUNTS_WRONG",
    "SEQ_FROM_ZERO",
    "SO_SLOW",
    "SO_SLOW_TENTHS",
    "UNKNOWN_FUNCTION_SILENT",
    "WRONG_PROGID",
    "XRESET_KEEPS_AUTOSTART",
    "Defect",
    "check",
    "defects",
    "listing",
    "shifted_values",
    "so_slow_step",
    "unknown",
]

# ---------------------------------------------------------------------- their figures
LATE_FACTOR = 3
"""``late-answer``: the answer comes this many times the page's deadline after the
request."""
LATE_US = LATE_FACTOR * DEFAULT.reply * 1e6
"""``late-answer``: 3 x 0.05 s (TIMEOUTS: a request is answered within 0.05 s)."""
SO_SLOW_TENTHS = 11
"""``so-slow``: an SO map's interval in tenths of its period (1.1 x)."""
DESCR_NAME_CHARS = 16
"""``descr-truncated``: the characters of an edge name that are described."""
DIGEST_FLIP = 0x1
"""``digest-wrong``: the bits of the description's digest that are inverted."""

# ---------------------------------------------------------------------- helpers of hooks
def so_slow_step(countdown: int, period: int) -> tuple[bool, int]:
    """``so-slow``: one cycle of an SO map whose ``countdown`` counts tenths of a cycle
    (0: due now).  Whether the map goes out in this cycle, and the countdown after it:
    due maps wait 1.1 x ``period`` cycles more, the remainder carried, so the intervals
    are 1.1 x the period on average."""
    due = countdown <= 0
    if due:
        countdown += SO_SLOW_TENTHS * period
    return due, countdown - 10


def shifted_values(values: Sequence[int], first: int,
                   specs: Sequence[tuple[int, bool]]) -> list[int]:
    """``dump-off-by-one``: the values of the edges after ``first``.. (index + 1), each
    wrapped to the (width, signed) of the edge it is sent for; 0 past the last edge."""
    out = []
    for i, (width, signed) in enumerate(specs):
        n = first + 1 + i
        raw = values[n] if n < len(values) else 0
        bits = 8 * width
        raw &= (1 << bits) - 1
        if signed and raw >> (bits - 1):
            raw -= 1 << bits
        out.append(raw)
    return out
