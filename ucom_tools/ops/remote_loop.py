"""The PC's loop of the run time (``dsp_remote_part``, dissertation 5.2.2): every period
the CI maps due and MCA Alive on every bus, then every frame the buses delivered.

Real buses: one thread does everything (no reader threads, so the GIL never keeps the
loop from its deadline).  Each cycle sleeps to its deadline on the wall clock (a short
spin for as long as a wake-up is late, at most 0.1 ms), sends the frames due (one write
per bus where the interface can batch them: socketcand), then takes every frame the
buses delivered meanwhile.
``realtime`` runs the loop's thread under SCHED_FIFO (:mod:`ucom_tools.ops.realtime`).
The in-process fleet in virtual time: the loop drives the fleet clock, nothing waits.
:class:`~ucom_tools.ops.remote.RemotePart` is a :class:`RemoteLoop`; its
:meth:`~RemoteLoop.cycle` is the performance-critical path (``benchmarks/runtime.py``).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Mapping
from typing import Any, Final, Self

import can

from ucom_tools.errors import BusError, FrameError, UcomError
from ucom_tools.native import mypyc_attr
from ucom_tools.ops.exchange import BusExchange
from ucom_tools.ops.realtime import (
    RealtimeScheduling,
    ShortSlice,
    let_signals_in,
    precise_sleep,
)
from ucom_tools.ops.remote_report import BoardEvent, LoopStats, Value
from ucom_tools.ops.remote_values import RemoteValues
from ucom_tools.ops.robot import BusHandle, Robot
from ucom_tools.protocol.dispatch import share_clock
from ucom_tools.wire import messages as wire_messages
from ucom_tools.wire.codes import ErrorCode
from ucom_tools.wire.ids import Function

SPIN_S: Final = 0.0001
"""The most the loop spins before a deadline.  A sleep wakes a little late (the thread's
timer slack is made small, see :func:`~ucom_tools.ops.realtime.precise_sleep`, but the
wake-up itself takes some 30-60 us); the loop sleeps until that lateness, as measured on
its own sleeps (:data:`WAKE_GAIN`), before the deadline and spins the rest.  A fixed
spin of 0.1 ms cost about 3 % of a core at 1 kHz for the same median lateness."""
WAKE_GAIN: Final = 0.05
"""How fast the expected wake-up lateness follows the measured one (a running mean over
some 20 sleeps; each measurement counts at most :data:`SPIN_S`, so a sleep cut short by
preemption does not make the loop spin long)."""
DRAIN_EVERY_S: Final = 0.001
"""At rates below 1 kHz the loop takes what the buses delivered at least this often while
it waits, so that no receive buffer fills."""
SWITCH_INTERVAL_S: Final = 0.0001
"""While the loop runs, Python switches threads this often (default 5 ms: a second
thread, a live view say, could keep the loop from its deadline that long)."""
_monotonic: Final = time.monotonic
_sleep: Final = time.sleep
"""Bound once: the loop's wait calls them every cycle."""
RECENT_SAMPLES: Final = 2_000
"""The cycles a running view's lateness figures are taken over (the last 2 s at 1 kHz)."""


@mypyc_attr(allow_interpreted_subclasses=True)  # RemotePart (ops/remote.py, from source)
class RemoteLoop(RemoteValues):
    """The loop over the exchanges of ``robot``'s buses at one period (see the module
    docstring); :meth:`_start_loop` begins it, :meth:`_end_loop` ends it."""

    def __init__(self, robot: Robot, exchanges: dict[str, BusExchange], period_s: float,
                 *, realtime: bool = False) -> None:
        super().__init__(robot, exchanges)
        self.period_s = period_s
        self.virtual = robot.virtual_time
        self.stats = LoopStats(self.period_s)
        self._running = False
        self._k = 0
        self._deadline = 0.0
        self._sent_at = -1.0
        """When the last cycle was sent (the loop's clock; negative: none yet)."""
        self._switch: float | None = None
        self._wake_late = SPIN_S / 2
        """How late a sleep of the loop wakes, as measured (:data:`WAKE_GAIN`)."""
        self._prepared = False
        self.events: list[BoardEvent] = []
        """What the boards reported while the exchange ran (their Error messages)."""
        self._event_subs: list[tuple[Any, Any]] = []
        self._drains: list[Callable[[], int]] = []
        """Each bus's dispatcher's ``drain`` (:meth:`_drain`), from the first cycle on."""
        self._batching: list[tuple[str, Any]] = []
        """The buses whose frames of a cycle go out in one write (``hold``/``release``:
        :class:`~ucom_tools.transport.socketcand.SocketcandBus`)."""
        self.scheduling: RealtimeScheduling | None = (
            RealtimeScheduling() if realtime and not robot.virtual_time else None)
        """``realtime``: the loop's thread under SCHED_FIFO from its first cycle to the stop
        (``scheduling.active``; ``scheduling.refused`` says why not).  Not in virtual time,
        where the loop drives the clock and nothing waits for the wall."""
        self.time_slice = ShortSlice()
        """On real buses at normal priority: the loop's thread's short time slice
        (``time_slice.granted``: None where the kernel keeps its own, or under
        ``realtime``), given back at the end."""
        self.each_cycle: list[Callable[[], None]] = []
        """Called on the loop's thread at the end of every cycle, after the sends (the
        network share, :mod:`ucom_tools.net.share`: writes from the network are applied
        here, and a snapshot handed to its publishing thread every few cycles).  What is
        called here must not wait for anything."""

    def _handles(self) -> list[tuple[BusHandle, BusExchange]]:
        return [(self.robot.buses[n], x) for n, x in self.exchanges.items()]

    @property
    def scheduled_as(self) -> str:
        """How the loop's thread is (or was) scheduled: 'SCHED_FIFO 40', 'normal', or
        'normal (why not SCHED_FIFO)'; with ', time slice 0.1 ms' where it runs at normal
        priority with the short slice it asked for (:attr:`time_slice`)."""
        text = "normal" if self.scheduling is None else self.scheduling.describe()
        granted = self.time_slice.granted
        return text if granted is None else f"{text}, time slice {granted / 1e6:g} ms"

    @property
    def running(self) -> bool:
        """Between :meth:`start` and :meth:`stop`."""
        return self._running

    # ------------------------------------------------------------------ begin, end
    def _start_loop(self) -> None:
        """The configured boards' exchange from the PC: MCA Alive as periodic frames while
        the boards are started one by one (an answer that has to be asked for again must
        not let the first ones' watchdogs fire), MCA Start on every board, then the
        first cycle; from then on the loop sends everything."""
        if self.virtual:
            share_clock([h.link.dispatcher for h, _ in self._handles()])
        else:
            for h, _ in self._handles():  # until the loop polls them itself
                h.link.dispatcher.start()
        for _, x in self._handles():
            x.start_alive()
        # running from the first MCA Start on: a start cut short (Ctrl-C, a board that
        # does not start) leaves a part that stop() stops, the boards started so far
        # with them, not to their watchdog
        self._running = True
        for _, x in self._handles():
            x.start_exchange(periodic=False)
        clock = self._clock()
        self._listen_for_events(clock)
        self.stats = LoopStats(self.period_s, started_wall=time.perf_counter(),
                               started_clock=clock)
        self._deadline = clock
        self._sent_at = -1.0
        self._k = 0
        if not self.virtual:
            for h, _ in self._handles():
                h.link.dispatcher.stop()
            self._switch = sys.getswitchinterval()
            sys.setswitchinterval(SWITCH_INTERVAL_S)
        self.cycle()
        for _, x in self._handles():
            x.stop_tasks()

    def _end_loop(self) -> None:
        """After the boards' stop: no periodic frames, the thread's scheduling as it was."""
        for _, x in self._handles():
            x.stop_tasks()
        if self.scheduling is not None:
            self.scheduling.leave()
        self.time_slice.leave()
        self._prepared = False
        if self._switch is not None:
            sys.setswitchinterval(self._switch)
            self._switch = None

    # ------------------------------------------------------------------ the loop
    def cycle(self) -> Mapping[str, Value | None]:
        """Wait for the next period, send the CI maps due and MCA Alive on every bus, and
        return the latest SO values by name."""
        if not self._running:
            raise UcomError("the exchange is not running (start() it first)")
        if not self._prepared:
            self._prepare()  # once, in the loop's own thread
        self._wait(self._deadline)
        let_signals_in()  # a Ctrl-C that came while the loop computed: raised here
        now = self._clock()
        if self._sent_at >= 0.0 and now - self._sent_at > self.stats.longest_gap_s:
            self.stats.longest_gap_s = now - self._sent_at
        self._sent_at = now
        late = now - self._deadline
        if late >= self.period_s:  # the loop came a whole period late or more
            skipped = int(late // self.period_s)
            self.stats.missed += skipped
            self._deadline += skipped * self.period_s
            self._k += skipped
            late -= skipped * self.period_s
        self.stats.late.append(late)
        batching = self._batching
        for _, bus in batching:
            bus.hold()
        try:
            for x in self.exchanges.values():
                x.send_cycle(self._deadline)
        except BaseException:
            for _, bus in batching:
                bus.release(write=False)
            raise
        for name, bus in batching:
            try:
                bus.release()
            except can.CanError as err:
                raise BusError(f"{name}: cannot send: {err}") from err
        if not self.virtual:
            self._drain()  # after the sends: what came during the period, as fresh as can be
        self.stats.cycles += 1
        self._k += 1
        self._deadline += self.period_s
        if self.on_values is not None:
            self._report_so()
        for hook in self.each_cycle:
            hook()
        return self.so

    @property
    def next_deadline(self) -> float | None:
        """When the loop sends its next cycle (``time.monotonic()`` seconds), for threads
        that want to keep out of its way then; None in virtual time or when not running."""
        return None if self.virtual or not self._running else self._deadline

    def _listen_for_events(self, started: float) -> None:
        """From now on every Error a board sends is kept in :attr:`events` (a watchdog
        that stopped a board's motors above all: the loop goes on, the board does not)."""
        for d, sub in self._event_subs:
            d.unsubscribe(sub)
        self._event_subs = []
        for h, x in self._handles():
            def on_error(msg: can.Message, h: BusHandle = h, x: BusExchange = x) -> None:
                try:
                    address, err = wire_messages.decode(msg.arbitration_id,
                                                        bytes(msg.data))
                except FrameError:
                    return
                assert isinstance(err, wire_messages.Error)
                n = address.number
                now = h.link.clock()
                if self.virtual:  # when it came: the pump hands over a stretch's frames
                    now -= max(0.0, h.link.dispatcher.stamp() - msg.timestamp)  # at its end
                self.events.append(BoardEvent(
                    round(now - started, 4), h.name, n, x.where(n), err.code,
                    f"its watchdog stopped every motor: no MCA Alive for {err.detail} ms "
                    "(stopped until MCA Start)" if err.code is ErrorCode.WATCHDOG
                    else err.describe()))
            d = h.link.dispatcher
            self._event_subs.append((d, d.subscribe(
                lambda msg: msg.arbitration_id >> 6 == Function.ERROR,
                f"{h.name} board errors", on_frame=on_error)))

    def _prepare(self) -> None:
        """The loop's thread: SCHED_FIFO (``realtime``), else a short time slice; precise
        sleeps; and the buses whose frames of a cycle can go out in one write."""
        self._prepared = True
        rt = self.scheduling
        if rt is not None:
            rt.enter()
        if not self.virtual:
            precise_sleep()
            if rt is None or not rt.active:
                self.time_slice.enter()
        self._batching = [(h.name, h.link.dispatcher.bus) for h, _ in self._handles()
                          if not self.virtual and callable(
                              getattr(h.link.dispatcher.bus, "hold", None))]
        self._drains = [h.link.dispatcher.drain for h, _ in self._handles()]

    def _drain(self) -> int:
        """Take and dispatch every frame the buses have delivered (without waiting)."""
        if not self._prepared:
            self._drains = [h.link.dispatcher.drain for h, _ in self._handles()]
        count = 0
        for drain in self._drains:
            count += drain()
        return count

    def _wait(self, deadline: float) -> None:
        """Until ``deadline``: in virtual time by driving the fleet clock; on real buses by
        sleeping (one thread does everything, no reader threads, so the GIL never keeps
        the loop from its deadline) until a sleep's measured lateness before it, then
        spinning (:data:`SPIN_S`); the frames that come meanwhile are taken after the
        cycle's sends (:meth:`cycle`), or every :data:`DRAIN_EVERY_S` while a long period
        passes."""
        if self.virtual:
            for h, _ in self._handles():
                h.link.dispatcher.pump(deadline)
            return
        while True:
            now = _monotonic()
            remaining = deadline - now
            if remaining <= 0:
                return
            early = self._wake_late
            if remaining > early:
                nap = min(DRAIN_EVERY_S, remaining - early)
                _sleep(nap)
                woke = _monotonic()
                late = min(max(woke - now - nap, 0.0), SPIN_S)
                self._wake_late = early + WAKE_GAIN * (late - early)
                if deadline - woke > DRAIN_EVERY_S:
                    self._drain()

    def run(self, seconds: float, each: Callable[[Self], None] | None = None) -> None:
        """Cycle for ``seconds`` (of the bus clock), calling ``each(self)`` every cycle."""
        end = self._clock() + seconds
        while self._clock() < end:
            self.cycle()
            if each is not None:
                each(self)
