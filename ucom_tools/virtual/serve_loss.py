"""``ucom fleet serve --loss``: frames lost at random between a client and its bus.

Each client of the serve has its own seeded generator, so the same run loses the same
frames; :class:`~ucom_tools.virtual.serve_connection.Connection` asks it for every frame
to the client and from it.
"""

from __future__ import annotations

import random


class Loss:
    """``fleet serve --loss``: frames lost between one client and its bus, a share
    ``share`` each way, from a generator seeded per client: the serve's seed, the bus and
    the client's number on this process (the same run loses the same frames)."""

    def __init__(self, share: float, seed: str) -> None:
        self.share = share
        self._rng = random.Random(seed)
        self.counts = {"to": 0, "from": 0}
        """Frames lost on their way to the client and from it."""

    def lost(self, direction: str) -> bool:
        if self._rng.random() < self.share:
            self.counts[direction] += 1
            return True
        return False
