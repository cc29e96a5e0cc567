"""Host timeouts of the protocol (``man/ucom-protocol.7``, section TIMEOUTS), in seconds.

A frozen value object handed to the clients; never a mutable class attribute.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Timeouts:
    reply: float = 0.050
    """A board answers a request (SetStatus, Start, Info, Report) within this time."""
    init_step: float = 0.030
    """After Init BEGIN/NEXT: no Init Ack within this time = the chain has ended."""
    reset: float = 0.100
    """After Reset/XReset: Ready(BOOT) within this time."""
    probe: float = 0.030
    """After PROBE_FIRST/PROBE_LAST: every answer within this time."""
    erase_per_page: float = 0.025
    """Erase budget per 256-word page, plus ``reply``."""
    verify: float = 0.5
    """After Program END: Program Finished within this time."""
    pause: float = 2.0
    """A board that sent Ready(PAUSE) must send Ready(RESUME) within this time."""


DEFAULT = Timeouts()
