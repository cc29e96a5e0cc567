"""What the run time reports when a board is lost and when it is back
(``man/ucom-protocol.7``, RUN TIME, Faults): the events, the lost boards, and the errors
a policy raises.

A board is *lost* when none of its SO maps came for :func:`lost_after` (three periods of
its fastest map, at least :data:`LOST_AFTER_MIN_S`), or when its bus failed; it is
*rejoined* when the PC brought it back into the running exchange (``rejoin``).  The loop
(:mod:`~ucom_tools.ops.remote.loop`) detects, :class:`~ucom_tools.ops.remote.RemotePart`
reacts by its policy (:data:`POLICIES`), the rejoin itself is
:mod:`~ucom_tools.ops.remote.rejoin`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final, Literal

from ucom_tools.errors import InputError, UcomError

LOST_AFTER_MIN_S: Final = 0.005
"""A board is lost after at least this long without any of its SO maps."""
LOST_PERIODS: Final = 3
"""... and at least this many periods of its fastest SO map."""
STOP: Final = "stop"
"""The default policy: a lost board stops every other one and ends the run."""
HOLD: Final = "hold"
"""The other boards run on with their targets; the lost one is reported."""
POLICIES: Final = (STOP, HOLD)
REJOIN_EVERY_S: Final = 0.025
"""How often the PC asks a lost board to rejoin (Init Request REJOIN) while it is away."""

Event = Literal["lost", "rejoined"]


def lost_after(fastest_interval_s: float) -> float:
    """The silence after which a board whose fastest SO map comes every
    ``fastest_interval_s`` seconds is lost."""
    return max(LOST_PERIODS * fastest_interval_s, LOST_AFTER_MIN_S)


@dataclass(frozen=True)
class BoardFault:
    """A board lost, or rejoined: ``part.faults``, ``--json``'s ``faults``."""

    time: float
    """Seconds since the exchange started (the bus clock): when the PC noticed."""
    bus: str
    board: int
    where: str
    """The bus, board and placement ('CAN0 board 3 (head right)')."""
    event: Event
    seen: str
    """Lost: what was seen last of the board ('silence: no SO map for 5.0 ms', its Error,
    its bootloader announcing itself, the bus failing).  Rejoined: how it came back."""
    answered: float | None = None
    """Rejoined: when the board first answered Init Request REJOIN (seconds since the
    exchange started), so ``time - answered`` is how long the rejoin took."""

    def describe(self) -> str:
        verb = "lost" if self.event == "lost" else "rejoined"
        return f"{self.where} {verb} at {self.time:.3f} s: {self.seen}"


@dataclass(frozen=True)
class LostBoard:
    """A board that is lost now: ``part.lost[(bus, board)]``."""

    bus: str
    board: int
    where: str
    since: float
    """When it was lost (seconds since the exchange started)."""
    seen: str
    """What was seen last (as its lost event says)."""
    status: str = "lost"
    """What the PC does about it: 'lost' (no --rejoin), 'asking it to rejoin', 'back,
    being configured', or why it cannot rejoin."""


class BoardLost(UcomError):
    """A board was lost under the ``stop`` policy: every other board was stopped (MCA
    Start STOP broadcast on every bus in the cycle of the detection), raised out of
    :meth:`RemotePart.cycle <ucom_tools.ops.remote.loop.RemoteLoop.cycle>` and every
    cycle after; leaving the part stops the boards one by one as usual."""

    def __init__(self, faults: list[BoardFault]) -> None:
        first = faults[0]
        more = f" (and {len(faults) - 1} more)" if len(faults) > 1 else ""
        super().__init__(f"{first.describe()}{more}; every other board was stopped")
        self.faults = faults


class LostBoardWrite(InputError):
    """A write to an edge of a lost board: refused, not queued (nothing was sent)."""


def check_policy(on_fault: str, rejoin: bool) -> None:
    """InputError for a policy that is none, or a rejoin without ``hold``."""
    if on_fault not in POLICIES:
        raise InputError(f"on_fault must be {' or '.join(POLICIES)}, not {on_fault!r}",
                         key="on_fault")
    if rejoin and on_fault != HOLD:
        raise InputError(f"rejoin needs the hold policy ({HOLD!r}), not {on_fault!r}: under "
                         "stop a lost board ends the run", key="rejoin")
