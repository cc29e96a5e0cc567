"""Another host on the bus: the frames it puts there, as this host sees them
(``man/ucom-protocol.7``, PROGRAMMING, Other hosts).  :class:`OtherHosts` tells this host's
own frames (echoed by the interface) from another's; :class:`ProgrammingWatch` notices a
host that is programming (its Program and ProgEnable frames, the answers to requests this
host never made); :func:`quiet_time` is how long to listen before one's own transfer."""

from __future__ import annotations

import contextlib
from collections import Counter, deque
from types import TracebackType
from typing import Self

import can

from ucom_tools.errors import BusError, FrameError
from ucom_tools.memory import REGIONS
from ucom_tools.protocol.link import Link
from ucom_tools.protocol.routing import Subscription
from ucom_tools.protocol.timeouts import DEFAULT, Timeouts
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import (
    ProgramOp,
    ReadyReason,
    StatusOp,
)
from ucom_tools.wire.ids import Function

OWN_SENDS = 8
"""The last sendings of each frame kept to recognise its echo (END, say, is sent again
to each board that did not answer)."""

LARGEST_PROGRAM = sum(r.end - r.start + 1 for r in REGIONS if r.programmable)
"""Words of the largest image a board takes (its program and data flash): what another
host's boards may read back after its END."""


# ---------------------------------------------------------------------- other hosts
class OtherHosts:
    """Frames another host put on the bus, as this host sees them (``man/ucom-protocol.7``,
    PROGRAMMING, Other hosts): a subscriber of the link's dispatcher that hands every frame
    of :attr:`functions` to :meth:`judge` and counts what it names in :attr:`seen`.

    A frame this host sent is never another host's.  Where the interface echoes sent frames
    (python-can's ``receive_own_messages``) the echo is marked as sent (``is_rx`` false),
    or it equals a frame this host sent and is stamped within the time an echo takes of
    the sending (the frames still on their way at the bus bitrate, and the transport
    margin; sent frames are stamped on the base of received ones,
    :meth:`~ucom_tools.protocol.dispatch.Dispatcher.stamp`): both are left alone.  The
    frames this host sends are seen through a tap on the dispatcher; :meth:`pause` takes
    it off a hot path, whose sender reports the frames that matter with :meth:`own`."""

    functions: frozenset[int] = frozenset()
    """Function codes (identifier bits 10-6) of the frames :meth:`judge` looks at."""

    def __init__(self, link: Link) -> None:
        self.link = link
        self.seen: Counter[str] = Counter()
        """What :meth:`judge` named, with how often."""
        self._own: dict[tuple[int, bytes], deque[tuple[float, float]]] = {}
        """Frames this host sent: when (stamp), and how long an echo may take, the last
        few times each was sent."""
        self._sub: Subscription | None = None
        self._tapping = False

    def _accepts(self, msg: can.Message) -> bool:
        return not (msg.is_extended_id or msg.is_error_frame or msg.is_remote_frame) and \
            (msg.arbitration_id >> 6) in self.functions

    # ------------------------------------------------------------------ life
    def start(self) -> Self:
        if self._sub is None:
            self._sub = self.link.dispatcher.subscribe(
                self._accepts, f"{self.link.name} other hosts", on_frame=self._take)
        self.resume()
        return self

    def close(self) -> None:
        self.pause()
        if self._sub is not None:
            self.link.dispatcher.unsubscribe(self._sub)
            self._sub = None

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def pause(self) -> None:
        """Stop looking at the frames this host sends (its sender reports them: :meth:`own`)."""
        if self._tapping:
            self._tapping = False
            with contextlib.suppress(ValueError):
                self.link.dispatcher.taps.remove(self._tap)

    def resume(self) -> None:
        """Look at the frames this host sends again."""
        if not self._tapping:
            self._tapping = True
            self.link.dispatcher.taps.append(self._tap)

    # ------------------------------------------------------------------ own frames
    def own(self, arbitration_id: int, data: bytes, stamp: float | None = None) -> None:
        """A frame this host sent (at ``stamp``, now if None): its echo is not another
        host's."""
        key = (arbitration_id, bytes(data))
        sends = self._own.get(key)
        if sends is None:
            sends = self._own[key] = deque(maxlen=OWN_SENDS)
        when = self.link.dispatcher.stamp() if stamp is None else stamp
        sends.append((when, self.link.budget(0.0, answers=1)))
        self.sent(arbitration_id, data)

    def sent(self, arbitration_id: int, data: bytes) -> None:
        """This host sent a frame of :attr:`functions` (what it asked for, for :meth:`judge`)."""

    def _tap(self, msg: can.Message) -> None:
        if not msg.is_rx and (msg.arbitration_id >> 6) in self.functions:
            self.own(msg.arbitration_id, bytes(msg.data), msg.timestamp)

    def _take(self, msg: can.Message) -> None:
        if not msg.is_rx:
            return  # an echo the interface marks as this host's
        key = (msg.arbitration_id, bytes(msg.data))
        t = msg.timestamp
        if any(abs(t - when) <= echo for when, echo in self._own.get(key, ())):
            return  # this host's own frame, echoed
        what = self.judge(msg.arbitration_id, key[1])
        if what:
            self.seen[what] += 1

    def judge(self, arbitration_id: int, data: bytes) -> str | None:
        """What a received frame that this host did not send shows of another host's
        work, or None when it shows nothing."""
        raise NotImplementedError

    # ------------------------------------------------------------------ looking
    def listen(self, seconds: float) -> None:
        """Read the bus for ``seconds`` of its clock, sending nothing (every frame is
        judged on its way: the watch subscribed first)."""
        d = self.link.dispatcher
        listening = d.subscribe(self._accepts, f"{self.link.name} listening")
        deadline = self.link.clock() + seconds
        try:
            while d.wait(listening, deadline) is not None:
                listening.queue.clear()
        finally:
            d.unsubscribe(listening)

    def summary(self, limit: int = 4) -> str:
        """What was seen, most frequent first (``12 x MCA Alive, CI map 1``)."""
        items = [f"{n} x {what}" if n > 1 else what
                 for what, n in self.seen.most_common(limit)]
        more = len(self.seen) - limit
        return ", ".join(items) + (f" and {more} other kinds" if more > 0 else "")


class ProgrammingWatch(OtherHosts):
    """Another host's programming traffic: Program frames and SetStatus PROG_ENABLE this
    host did not send (data frames until this host sends data of its own: then an echo
    could not be told from them, and their BLOCK frames still show), and answers to
    requests this host never made: Ready ERASED, PAUSE or RESUME before its PREPARE,
    Ready STATUS of ProgEnable before its SetStatus PROG_ENABLE, Program Finished before
    its END."""

    functions = frozenset({Function.PROGRAM, Function.SET_STATUS, Function.READY,
                           Function.PROGRAM_FINISHED})

    def __init__(self, link: Link) -> None:
        super().__init__(link)
        self.asked: set[str] = set()
        """What this host has sent so far: "enable", "prepare", "end", "data"."""

    def sending_data(self) -> None:
        """This host sends data frames from now on."""
        self.asked.add("data")

    def sent(self, arbitration_id: int, data: bytes) -> None:
        function = arbitration_id >> 6
        if function == Function.PROGRAM and len(data) < 8 and data:
            if data[0] == ProgramOp.PREPARE:
                self.asked.add("prepare")
            elif data[0] == ProgramOp.END:
                self.asked.add("end")
        elif function == Function.SET_STATUS and data[:1] == bytes([StatusOp.PROG_ENABLE]):
            self.asked.add("enable")

    def judge(self, arbitration_id: int, data: bytes) -> str | None:
        function = arbitration_id >> 6
        if function == Function.PROGRAM:
            if len(data) == 8:
                return None if "data" in self.asked else "Program data frame"
            try:
                return f"Program {ProgramOp(data[0]).name}"
            except (IndexError, ValueError):
                return "Program frame"
        if function == Function.SET_STATUS:
            if data[:1] == bytes([StatusOp.PROG_ENABLE]):
                return "SetStatus PROG_ENABLE"
            return None
        if function == Function.PROGRAM_FINISHED:
            return None if "end" in self.asked else "Program Finished (this host sent no END)"
        try:
            ready = m.Ready.decode(data)
        except FrameError:
            return None
        if ready.reason in (ReadyReason.ERASED, ReadyReason.PAUSE, ReadyReason.RESUME) and \
                "prepare" not in self.asked:
            return f"Ready {ready.reason.name} (this host sent no PREPARE)"
        if ready.reason is ReadyReason.STATUS and ready.value16 >> 8 == StatusOp.PROG_ENABLE \
                and "enable" not in self.asked:
            return "Ready STATUS of ProgEnable (this host sent no SetStatus)"
        return None

    def check(self, bus: str, done: str) -> None:
        """BusError naming what was seen, if another host showed itself; ``done`` says
        what became of this host's job."""
        if self.seen:
            raise BusError(f"another host is programming {bus} (frames from another host: "
                           f"{self.summary()}); {done}")


def quiet_time(link: Link, timeouts: Timeouts = DEFAULT) -> float:
    """How long to listen for another host's transfer before one's own: the longest its
    boards leave the bus silent once their flash is erased, the wait for Program Finished
    after END of the largest image a board takes (the boards' verification, their answer,
    the transport margin).  The erase itself (up to 25 ms a page) can pass unheard; that
    host shows itself when its data begin (:class:`ProgrammingWatch`)."""
    return link.budget(timeouts.reply + timeouts.verify(LARGEST_PROGRAM), answers=1)
