"""The PC's loop of the run time (``dsp_remote_part``, dissertation 5.2.2): every period
the CI maps due and MCA Alive on every bus, then every frame the buses delivered.

Real buses: one thread does everything (no reader threads, so the GIL never keeps the
loop from its deadline).  Each cycle sleeps to its deadline on the wall clock (a short
spin for as long as a wake-up is late, at most 0.1 ms), sends the frames due (one write
per bus where the interface can batch them: socketcand), then takes every frame the
buses delivered meanwhile.
``realtime`` runs the loop's thread under SCHED_FIFO (:mod:`ucom_tools.ops.realtime`).
The in-process fleet in virtual time: the loop drives the fleet clock, nothing waits.

After its drain the loop watches every board (``man/ucom-protocol.7``, RUN TIME, Faults;
:mod:`~ucom_tools.ops.remote.watch`: a board whose SO maps stay away is lost).
A bus that fails (the connection or adapter: a
BusError, an interface that reports error-passive or bus-off) is a fault of every
board on it, at once.
The policy (``on_fault``): ``stop`` broadcasts MCA Start STOP on every bus in the cycle
of the detection and raises
:class:`~ucom_tools.ops.remote.faults.BoardLost`; ``hold`` runs the others on and, with
``rejoin``, steps a conversation that brings the lost board back
(:mod:`~ucom_tools.ops.remote.rejoin`) after each cycle's drain (its conversations, and
the writes it does not wait for, are a part it holds:
:mod:`~ucom_tools.ops.remote.conversations`); a lost board whose maps come again before
that ran on all along and is back as it was.
:class:`~ucom_tools.ops.remote.RemotePart` is a :class:`RemoteLoop`; its
:meth:`~RemoteLoop.cycle` is the performance-critical path (``benchmarks/runtime.py``).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any, Final, Self

import can

from ucom_tools.errors import BusError, FrameError, UcomError
from ucom_tools.native import mypyc_attr
from ucom_tools.ops.edges import EdgeRef
from ucom_tools.ops.exchange import BusExchange
from ucom_tools.ops.realtime import (
    RealtimeScheduling,
    ShortSlice,
    let_signals_in,
    precise_sleep,
)
from ucom_tools.ops.remote.conversations import REJOIN_MARGIN_S, Conversations
from ucom_tools.ops.remote.faults import (
    HOLD,
    STOP,
    BoardFault,
    BoardLost,
    LostBoard,
    check_policy,
)
from ucom_tools.ops.remote.report import BoardEvent, LoopStats, Value
from ucom_tools.ops.remote.values import RemoteValues
from ucom_tools.ops.remote.watch import BoardWatch, SilenceWatch
from ucom_tools.ops.robot import BusHandle, Robot
from ucom_tools.protocol.dispatch import share_clock
from ucom_tools.wire import mca
from ucom_tools.wire import messages as wire_messages
from ucom_tools.wire.codes import ErrorCode, ReadyReason
from ucom_tools.wire.ids import ALL, Function

if TYPE_CHECKING:
    from ucom_tools.config.topology import BoardKey

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
@mypyc_attr(allow_interpreted_subclasses=True)  # RemotePart extends it (see compiled.py)
class RemoteLoop(RemoteValues):
    """The loop over the exchanges of ``robot``'s buses at one period (see the module
    docstring); :meth:`_start_loop` begins it, :meth:`_end_loop` ends it."""

    def __init__(self, robot: Robot, exchanges: dict[str, BusExchange], period_s: float,
                 *, realtime: bool = False, on_fault: str = STOP, rejoin: bool = False,
                 ) -> None:
        super().__init__(robot, exchanges)
        check_policy(on_fault, rejoin)
        self.period_s = period_s
        self.watch = SilenceWatch(period_s, self._lose, self._maps_again)
        """Which boards are lost (:mod:`ucom_tools.ops.remote.watch`)."""
        self.on_fault = on_fault
        """The policy when a board is lost: ``stop`` (every other board stopped, the run
        ends: :class:`~ucom_tools.ops.remote.faults.BoardLost`) or ``hold``."""
        self.rejoin = rejoin
        """With ``hold``: bring a lost board back when it returns."""
        self.faults: list[BoardFault] = []
        """Every board lost or rejoined, in order (``man/ucom-protocol.7``, Faults)."""
        self.fault_hooks: list[Callable[[BoardFault], None]] = []
        """Called on the loop's thread with every fault event as it happens (a board lost,
        rejoined); what is called here must not wait for anything."""
        self._notes: dict[BoardKey, tuple[float, str]] = {}
        """What each board said last besides its maps (an Error, its bootloader's Ready,
        its program's unsolicited MCA Ready), with when (the watch's ``present``): what a
        lost event names."""
        self._failed: dict[str, str] = {}
        """Buses that failed (their connection or adapter) -> why; nothing is sent there."""
        self._sending: list[BusExchange] = list(exchanges.values())
        self._drain_of: list[tuple[str, Callable[[], int]]] = []
        """Each bus's name and its dispatcher's ``drain`` (:meth:`_drain`), from the first
        cycle on (a failed bus's left out)."""
        self._states: list[tuple[str, Any]] = []
        """Buses whose interface reports its state (python-can's ``state``)."""
        self._bad_state: dict[str, str] = {}
        self._newly: list[BoardFault] = []
        self._halt: BoardLost | None = None
        self.virtual = robot.virtual_time
        self.conversations = Conversations(self.virtual, self._rejoin_ended, self._held,
                                           self._hold, self._forget_answers)
        """The rejoins and the writes the loop steps (:mod:`~ucom_tools.ops.remote.
        conversations`)."""
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
    def failed_buses(self) -> dict[str, str]:
        """The buses whose connection or adapter failed while the loop ran, and why (their
        boards are lost; nothing more is sent there)."""
        return dict(self._failed)

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
        self.watch.start(clock, self.exchanges)
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
        if self._halt is not None:
            raise self._halt
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
        deadline = self._deadline
        failed: list[tuple[str, str]] | None = None
        try:
            for x in self._sending:
                try:
                    x.send_cycle(deadline)
                except BusError as err:  # this bus's connection or adapter: its boards'
                    if failed is None:  # fault; the other buses' cycles go on
                        failed = []
                    failed.append((x.bus.name, str(err)))
        except BaseException:
            for _, bus in batching:
                bus.release(write=False)
            raise
        for name, bus in batching:
            try:
                bus.release()
            except can.CanError as err:
                if failed is None:
                    failed = []
                failed.append((name, f"{name}: cannot send: {err}"))
        if not self.virtual:
            self._drain()  # after the sends: what came during the period, as fresh as can be
        if failed is not None:
            for name, why in failed:
                self._bus_failed(name, why, now)
        self.watch.check(now)
        if self._states:
            self._watch_states(now)
        if self.conversations.under_way:
            self.conversations.step(self._k, self._deadline + self.period_s - REJOIN_MARGIN_S)
        self.stats.cycles += 1
        self._k += 1
        self._deadline += self.period_s
        if self._newly:
            self._react()
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
                text = (f"its watchdog stopped every motor: no MCA Alive for {err.detail} "
                        "ms (stopped until MCA Start)" if err.code is ErrorCode.WATCHDOG
                        else err.describe())
                note = self._notes.get((h.name, n))
                if err.code is not ErrorCode.LATCHED or note is None or \
                        not note[1].startswith("its watchdog"):  # (its CI refused since:
                    self._notes[(h.name, n)] = (self.watch.present, text)  # the same news)
                if (h.name, n) in self._lost:
                    return  # answers to the rejoin's questions (NOT_RUNNING ...): not events
                self.events.append(BoardEvent(round(now - started, 4), h.name, n,
                                              x.where(n), err.code, text))

            def on_ready(msg: can.Message, h: BusHandle = h) -> None:
                if msg.arbitration_id & 0x20 or len(msg.data) < 2:
                    return  # a fixed ID (no run-time board), or no Ready of ours
                ident = msg.arbitration_id >> 6
                if ident == Function.READY and msg.data[0] == ReadyReason.BOOT:
                    text = "its bootloader announcing itself (Ready BOOT: it was reset)"
                elif ident == Function.MCA_READY and msg.data[1] == Function.MCA_READY:
                    text = ("its program announcing itself (an unsolicited MCA Ready: it "
                            "started again)")
                else:
                    return
                self._notes[(h.name, msg.arbitration_id & 0x1F)] = (self.watch.present, text)
            d = h.link.dispatcher
            self._event_subs.append((d, d.subscribe(
                lambda msg: msg.arbitration_id >> 6 == Function.ERROR,
                f"{h.name} board errors", on_frame=on_error)))
            self._event_subs.append((d, d.subscribe(
                lambda msg: msg.arbitration_id >> 6 in (Function.READY, Function.MCA_READY)
                and not msg.is_extended_id, f"{h.name} boards restarting",
                on_frame=on_ready)))

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
        live = [h for h, _ in self._handles() if h.name not in self._failed]
        self._batching = [(h.name, h.link.dispatcher.bus) for h in live
                          if not self.virtual and callable(
                              getattr(h.link.dispatcher.bus, "hold", None))]
        self._drain_of = [(h.name, h.link.dispatcher.drain) for h in live]
        self._states = [(h.name, h.link.dispatcher.bus) for h in live
                        if type(h.link.dispatcher.bus).state is not can.BusABC.state]

    def _drain(self) -> int:
        """Take and dispatch every frame the buses have delivered (without waiting); a
        bus that fails meanwhile is a fault of its boards (:meth:`_bus_failed`)."""
        if not self._prepared:
            self._drain_of = [(h.name, h.link.dispatcher.drain) for h, _ in self._handles()
                              if h.name not in self._failed]
        count = 0
        failed: list[tuple[str, str]] | None = None
        for name, drain in self._drain_of:
            try:
                count += drain()
            except BusError as err:
                if failed is None:
                    failed = []
                failed.append((name, str(err)))
        if failed is not None:
            now = self._clock()
            for name, why in failed:
                self._bus_failed(name, why, now)
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
                if h.name not in self._failed:
                    try:
                        h.link.dispatcher.pump(deadline)
                    except BusError as err:
                        self._bus_failed(h.name, str(err), self._clock())
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

    # ------------------------------------------------------------------ faults
    def _watch_states(self, now: float) -> None:
        for name, bus in self._states:
            try:
                state = bus.state
            except Exception:  # an interface whose state cannot be read: it reports none
                self._states = [(n, b) for n, b in self._states if n != name]
                continue
            if state is can.BusState.ACTIVE:
                self._bad_state.pop(name, None)
            elif name not in self._bad_state:  # the moment it turns: every board's fault
                what = "bus-off" if state is can.BusState.ERROR else "error-passive"
                self._bad_state[name] = what
                for w in self.watch.watches:
                    if w.bus == name and not w.lost:
                        self._lose(w, now, f"the bus failing: the interface reports {name} "
                                           f"{what}")

    def _bus_failed(self, name: str, why: str, now: float) -> None:
        """Bus ``name``'s connection or adapter failed: nothing more is sent there or
        read from it, and every board on it is lost."""
        if name in self._failed:
            return
        self._failed[name] = why
        self._sending = [x for x in self._sending if x.bus.name != name]
        self._drain_of = [(n, d) for n, d in self._drain_of if n != name]
        self._batching = [(n, b) for n, b in self._batching if n != name]
        self._states = [(n, b) for n, b in self._states if n != name]
        for w in self.watch.watches:
            if w.bus == name and not w.lost:
                self._lose(w, now, f"the bus failing: {why}")

    def _lose(self, w: BoardWatch, now: float, seen: str) -> None:
        """Board ``w`` is lost at ``now``: its event (with what was seen of it last), the
        lost set; the policy acts at the end of the cycle (:meth:`_react`)."""
        w.lost = True
        key = (w.bus, w.board)
        if seen.startswith("silence"):
            note = self._notes.get(key)
            if note is not None and note[0] >= w.last - self.period_s:
                seen = note[1]  # it said something after its last map
        t = round(now - self.stats.started_clock, 4)
        fault = BoardFault(t, w.bus, w.board, w.where, "lost", seen)
        self.faults.append(fault)
        status = "lost"
        if self.on_fault == HOLD and self.rejoin:
            status = ("cannot rejoin: its bus failed" if w.bus in self._failed
                      else "asking it to rejoin")
        lost = dict(self._lost)
        lost[key] = LostBoard(w.bus, w.board, w.where, t, seen, status)
        self._lost = lost
        self.watch.regroup(w)
        self._newly.append(fault)
        for hook in self.fault_hooks:
            hook(fault)

    def _react(self) -> None:
        """The policy, at the end of the cycle that found boards lost: ``stop`` sends MCA
        Start STOP to every board of every bus at once (broadcast) and raises BoardLost;
        ``hold`` leaves the lost board as it is (if it still hears, it holds its targets,
        which no write changes while it is lost) and, with ``rejoin``, starts asking it
        back."""
        newly, self._newly = self._newly, []
        if self.on_fault == STOP:
            stop = mca.encode(mca.McaStart(mca.StartOp.STOP), ALL)
            for x in list(self._sending):
                try:
                    x.link.send_raw(*stop)
                except BusError as err:  # that bus's boards are lost too: their watchdog
                    self._bus_failed(x.bus.name, str(err), self._clock())
            self._halt = BoardLost(newly + self._newly)
            self._newly = []
            raise self._halt
        if self.rejoin and self.conversations.rejoiner is not None:
            k = 0
            for f in newly:
                if f.bus not in self._failed:  # boards lost together asked a cycle apart
                    self.conversations.rejoin(f.bus, f.board, k * self.period_s)
                    k += 1

    def _maps_again(self, w: BoardWatch, now: float) -> None:
        """(hold) A lost board's maps came again before the PC brought it back: it ran on
        all along (a silence shorter than its watchdog: its bus-off, a cable, a stall of
        the source), configured as before and holding the targets it had, which did not
        change meanwhile (writes to it were refused): it is back as it was.  A rejoin
        under way that has not reached it yet is called off."""
        key = (w.bus, w.board)
        if not self.conversations.call_off(w.bus, w.board):
            return  # the rejoin reached it: it finishes the job
        lost = self._lost.get(key)
        if lost is None:
            return
        w.lost = False
        self.watch.regroup(w)
        replaced = dict(self._lost)
        del replaced[key]
        self._lost = replaced
        t = round(now - self.stats.started_clock, 4)
        fault = BoardFault(t, w.bus, w.board, w.where, "rejoined",
                           f"its SO maps came again {t - lost.since:.3f} s after the loss: "
                           "it ran on, as configured, with the targets it had")
        self.faults.append(fault)
        for hook in self.fault_hooks:
            hook(fault)

    def _forget_answers(self, bus: str) -> None:
        self.exchanges[bus].mca.forget()

    def _write_later(self, ref: EdgeRef, raw: int) -> bool:
        return self._running and self.conversations.write_later(ref, raw)

    def _rejoin_ended(self, r: Any) -> None:
        key = (r.bus, r.board)
        lost = self._lost.get(key)
        if lost is None:
            return
        if not r.ok:
            replaced = dict(self._lost)
            replaced[key] = LostBoard(lost.bus, lost.board, lost.where, lost.since,
                                      lost.seen, r.how)
            self._lost = replaced
            return
        now = self._clock()
        w = self.watch.watched[key]
        w.back(self.watch.present)
        self.watch.regroup(w)
        replaced = dict(self._lost)
        del replaced[key]
        self._lost = replaced
        started = self.stats.started_clock
        answered = None if r.answered is None else round(r.answered - started, 4)
        fault = BoardFault(round(now - started, 4), r.bus, r.board, w.where, "rejoined",
                           r.how, answered)
        self.faults.append(fault)
        for hook in self.fault_hooks:
            hook(fault)

    def _set_lost_status(self, bus: str, board: int, status: str) -> None:
        """What the PC does about lost board (bus, board) now (the rejoin's progress)."""
        lost = self._lost.get((bus, board))
        if lost is not None and lost.status != status:
            replaced = dict(self._lost)
            replaced[(bus, board)] = LostBoard(lost.bus, lost.board, lost.where,
                                               lost.since, lost.seen, status)
            self._lost = replaced
