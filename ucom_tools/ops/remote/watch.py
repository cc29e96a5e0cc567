"""The loop's watch over the boards' SO maps (``man/ucom-protocol.7``, RUN TIME, Faults):
which board is lost, and when.

A board none of whose fastest SO maps came for :func:`~ucom_tools.ops.remote.faults.
lost_after` is lost.  The silence is counted in the frames its bus's other boards sent
meanwhile (their maps' periods say how long that took), not in time: frames come in the
order they were sent, so neither the loop's own stall (the drain after it takes what
came meanwhile) nor a transport or served fleet that delivers late and then all at
once, nor time stamps on another clock, make a board that sends look lost.  A board
from which nothing came at all for :data:`QUIET_MIN_S` (or the boards' watchdog time)
of the loop's own running time (a cycle counts at most :data:`PRESENT_CAP` periods: a
stall of the loop is no silence) is lost too: that is a whole bus gone silent, which
the other boards cannot tell.  :class:`SilenceWatch` does this after every cycle's drain
of :class:`~ucom_tools.ops.remote.loop.RemoteLoop`, which decides what a loss means.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Final

from ucom_tools.ops.exchange import BusExchange
from ucom_tools.ops.remote.faults import lost_after
from ucom_tools.protocol.mca import ProcessImage

if TYPE_CHECKING:
    from ucom_tools.config.topology import BoardKey

QUIET_MIN_S: Final = 0.5
"""A board from which nothing at all came for this long of the loop's running time (or
the boards' watchdog time, if longer) is lost: a whole bus gone silent, which the other
boards cannot tell.  Where the interface reports its state (error-passive: nobody
acknowledges, a cut cable, every board off; socketcand by the server's error frames)
that is noticed at once; where it does not (a socketcand server that sends no error
frames), a shorter time would make a transport or a served fleet that a busy
machine held for a moment (hundreds of milliseconds; the boards do not see it: their
time stood still too) end the run.  A board cut off from the PC has stopped by its own
watchdog long before."""
BURST_TRUST_MAX_S: Final = 1.0
"""After nothing came from a bus for cycles of this loop that sent (at least a board's
limit of silence) and then frames came again, its boards' frames prove no silence for
as long as the gap lasted (at most this long) and a limit more: the transport
(socketcand, a served fleet that a busy machine held) held this host's frames too and
delivers them to the bus in a burst that wins arbitration over every SO map; the
boards' queued maps then follow in the order of their identifiers, the lowest board's
last, so a board of low priority may stay unheard for several milliseconds while the
others' maps come (measured over ``fleet serve`` beside two busy processes: 5-7 ms, a
board lost that was not, in one run of two).  Only the quiet time and the bus's state
tell meanwhile."""
PRESENT_CAP: Final = 2.0
"""A cycle counts at most this many periods of the loop's running time (the time a board's
silence is measured on): a loop that was away longer was stalled."""
_EPSILON: Final = 1e-9
"""Sums of periods on the clock: a silence of exactly the limit counts as the limit."""


class BoardWatch:
    """One board's SO maps as the loop watches them: how many frames of the boards'
    fastest maps of its bus's process image (:class:`~ucom_tools.protocol.mca.
    ProcessImage`: ``watched``, ``order``, ``received``) had come when its latest frame
    came (:attr:`index`), when that changed on the loop's running time (:attr:`last`),
    and the silences after which it is lost: :attr:`limit` seconds, proved by
    :attr:`frames` frames of the other boards' fastest maps after its last (its own
    fastest: :attr:`rate` frames a second), or nothing at all for :attr:`quiet` of the
    loop's running time."""

    def __init__(self, bus: str, board: int, where: str, image: ProcessImage,
                 maps: list[int], fast: int, rate: float, limit: float, quiet: float,
                 present: float) -> None:
        self.bus = bus
        self.board = board
        self.where = where
        self.image = image
        self.order = image.order
        self.maps = maps
        self.rate = rate
        self.fast = fast
        """Its fastest maps."""
        self.limit = limit
        self.quiet = quiet
        self.frames = 0.0
        """The other boards' frames that prove :attr:`limit` of silence (0: no other
        board on its bus that is not lost: only :attr:`quiet` tells)."""
        self.others = 0.0
        """The frames a second of the fastest maps of the other boards not lost ..."""
        self.extra = 0
        """... and their number."""
        self.index = self.latest()
        self.last = present
        self.armed = False
        self.lost = False

    def latest(self) -> int:
        """How many of the bus's watched frames had come by its latest frame (0: none of
        it yet)."""
        order = self.order
        out = 0
        for n in self.maps:
            k = order.get(n, 0)
            if k > out:
                out = k
        return out

    def back(self, present: float) -> None:
        """Watched again from ``present`` (it rejoined)."""
        self.index = self.latest()
        self.last = present
        self.armed = False
        self.lost = False


class SilenceWatch:
    """Every watched board of the loop's buses, grouped by bus: :meth:`start` at the
    loop's start, :meth:`check` after each cycle's drain, which calls ``lose`` (a board,
    the clock, what was seen) for a board found lost and ``again`` (a board, the clock)
    for a lost board whose maps came again."""

    def __init__(self, period_s: float, lose: Callable[[BoardWatch, float, str], None],
                 again: Callable[[BoardWatch, float], None]) -> None:
        self.period_s = period_s
        self.lose = lose
        self.again = again
        self.present = 0.0
        """The loop's own running time since its start (seconds): the clock, but a cycle
        that came late counts at most :data:`PRESENT_CAP` periods.  Silence is measured on
        it, so that a stall of this process (or of the machine, a served fleet on it
        with it) is no silence of the boards: after it they get the time to deliver."""
        self.watch_at = 0.0
        """The clock when :attr:`present` last moved on."""
        self.watches: list[BoardWatch] = []
        """Every watched board ..."""
        self.watched: dict[BoardKey, BoardWatch] = {}
        """... by (bus, seq ID) ..."""
        self.groups: list[list[BoardWatch]] = []
        """... and by bus."""
        self.seen_received: list[int] = []
        """Per group (bus): its image's ``received`` when frames last came ..."""
        self.seen_at: list[float] = []
        """... the clock then ..."""
        self.trust_from: list[float] = []
        """... and until when its boards' frames prove no silence
        (:data:`BURST_TRUST_MAX_S`)."""
        self.quiet_cycles: list[int] = []
        """Per group: the cycles since its frames last came."""

    def regroup(self, w: BoardWatch) -> None:
        """After ``w`` was lost or came back: its bus's proofs of silence again."""
        self.proofs(self.group_of(w))

    def start(self, now: float, exchanges: Mapping[str, BusExchange]) -> None:
        """Watch every configured board's fastest SO maps from ``now`` (the loop's start)."""
        self.watches = []
        self.watched = {}
        self.groups = []
        self.seen_received = []
        self.seen_at = []
        self.trust_from = []
        self.quiet_cycles = []
        self.present = 0.0
        self.watch_at = now
        for name, x in exchanges.items():
            image = x.mca.image
            group: list[BoardWatch] = []
            quiet = max(x.plan.alive_ms / 1000, QUIET_MIN_S)
            for n in x.configured:
                maps = x.plan.maps_of(n)
                if not maps:
                    continue  # no SO map: nothing tells whether it lives
                fastest = min(m.interval_us for m in maps)
                limit = lost_after(fastest / 1e6)
                numbers = [m.number for m in maps if m.interval_us == fastest]
                image.watched.update(numbers)
                w = BoardWatch(name, n, x.where(n), image, [m.number for m in maps],
                               len(numbers), len(numbers) * 1e6 / fastest, limit,
                               max(limit, quiet) - _EPSILON, 0.0)
                group.append(w)
                self.watched[(name, n)] = w
            if group:
                self.groups.append(group)
                self.seen_received.append(image.received)
                self.seen_at.append(now)
                self.trust_from.append(now)
                self.quiet_cycles.append(0)
                self.watches += group
                self.proofs(group)

    @staticmethod
    def proofs(group: list[BoardWatch]) -> None:
        """How many frames of the other boards of a bus (those not lost) prove each one's
        limit of silence: as many as they send in it, and one more of each map (the
        first may come just after its last frame, at any phase)."""
        live = 0.0
        maps = 0
        for w in group:
            if not w.lost:
                live += w.rate
                maps += w.fast
        for w in group:
            others = live - (0.0 if w.lost else w.rate)
            extra = maps - (0 if w.lost else w.fast)
            w.others = others
            w.extra = extra
            w.frames = w.limit * others + extra - _EPSILON if others > 0 else 0.0

    def check(self, now: float) -> None:
        """After the cycle's drain, per bus: a board after whose last watched map the
        bus's other boards sent as many frames as fill its limit at their periods is lost
        (counted in frames, in the order they were sent, not in time: neither a stall of
        this loop nor a transport or served fleet that delivers late and then all at once
        makes a board that sends look lost; and not for a while after frames came
        again from a bus that had been silent while this loop cycled,
        :data:`BURST_TRUST_MAX_S`); so is one from which nothing came for its quiet time
        of the loop's running time (:attr:`present`: the whole bus silent)."""
        step = now - self.watch_at
        self.watch_at = now
        cap = PRESENT_CAP * self.period_s
        present = self.present + (step if step < cap else cap)
        self.present = present
        for g, group in enumerate(self.groups):
            received = group[0].image.received
            if received != self.seen_received[g]:
                # nothing came for cycles that sent (the transport held this host's
                # frames too), then all at once; a stall of this loop sent nothing, and a
                # bus whose boards were lost (an emergency stop, a cable) was silent
                # for that reason (no frames held: they came as they were sent)
                gap = now - self.seen_at[g]
                if self.quiet_cycles[g] * self.period_s >= group[0].limit and \
                        not any(w.lost for w in group):
                    trust = now + min(gap, BURST_TRUST_MAX_S) + group[0].limit
                    if trust > self.trust_from[g]:
                        self.trust_from[g] = trust
                self.seen_received[g] = received
                self.seen_at[g] = now
                self.quiet_cycles[g] = 0
            else:
                self.quiet_cycles[g] += 1
            trusted = now >= self.trust_from[g]
            for w in group:
                index = w.latest()
                if index != w.index:
                    w.index = index
                    w.last = present
                    w.armed = True
                    if w.lost:  # (hold) its maps came again: it ran on, its configuration
                        self.again(w, now)  # and targets as they were
                        continue
                elif w.lost:
                    continue
                after = received - index  # (a drain that brought its last frame and
                if trusted and w.armed and w.frames > 0.0 and after >= w.frames:
                    silent = max(w.limit, (after - w.extra) / w.others)
                    self.lose(w, now, f"silence: none of its SO maps for "
                                       f"{silent * 1e3:.1f} ms")
                elif present - w.last >= w.quiet:
                    self.lose(w, now, self.quiet_text(group, w, present))

    def group_of(self, w: BoardWatch) -> list[BoardWatch]:
        for group in self.groups:
            if w in group:
                return group
        return [w]

    def quiet_text(self, group: list[BoardWatch], w: BoardWatch, present: float) -> str:
        silent = present - w.last
        if all(present - other.last >= other.quiet or other.lost for other in group):
            return f"silence: nothing from any board of {w.bus} for {silent * 1e3:.1f} ms"
        return f"silence: none of its SO maps for {silent * 1e3:.1f} ms"
