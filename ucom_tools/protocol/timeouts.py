"""What the host allows a board for each answer (``man/ucom-protocol.7``, TIMEOUTS).

These are the board's own times, the protocol's promises.  The host never waits a bare
constant: :meth:`~ucom_tools.protocol.link.Link.budget` adds the wire time of the frames
still on their way and of the answers, and the link's transport margin.  A frozen value
object handed to the clients; never a mutable class attribute.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Timeouts:
    reply: float = 0.050
    """A board answers a request (SetStatus, Start, Info, Report) within this time."""
    init_step: float = 0.030
    """After Init BEGIN/NEXT the board that takes the number answers within this time
    (T_init); no answer after every retry = the chain has ended."""
    reset: float = 0.100
    """After Reset/XReset: Ready(BOOT) within this time."""
    probe: float = 0.030
    """After PROBE_FIRST/PROBE_LAST: every answer within this time."""
    erase_per_page: float = 0.025
    """Erase time a board may take per 256-word page, before Ready(ERASED)."""
    verify_base: float = 0.010
    """After Program END: Program Finished within this time ..."""
    verify_per_word: float = 1e-6
    """... plus this per word the board stored (it reads them back for the ProgID)."""
    startup: float = 0.001
    """A started program decides within this time whether it fits its board
    (COMPATIBILITY): its Error or MCA Ready comes within ``reply`` plus this."""
    retries: int = 2
    """A request whose answer did not come is asked again this many times: a lost frame
    costs a second question, not a board."""

    def verify(self, words: int) -> float:
        return self.verify_base + words * self.verify_per_word


DEFAULT = Timeouts()
