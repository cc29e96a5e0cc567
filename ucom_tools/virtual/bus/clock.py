"""The fleet clock: one time base for every bus and board of a fleet.

Every event of a fleet - a frame that becomes ready, wins arbitration or ends on its bus,
a board's timer, a program's control cycle - is scheduled on one :class:`FleetClock`, in
virtual microseconds, and run in time order; so four buses at 1 kHz run in step.  Models
never read ``time``: they are called with the time of their event.

The clock runs as fast as the CPU allows when the host drives it (in-process tools, tests,
benchmarks: a wait for an answer runs the clock until the answer or the deadline), or
paced to the wall clock by a :class:`RealtimeDriver` (``ucom fleet serve``, ``--pace``).

The driver thread runs every node's ``on_frame`` and every scheduled callback.  One that
raises is logged with its traceback (logger ``ucom.bus``) and the fleet goes on; what
failed is not retried.
"""

from __future__ import annotations

import contextlib
import heapq
import itertools
import logging
import math
import select
import selectors
import socket
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any, Final

log = logging.getLogger("ucom.bus")
_heappush, _heappop = heapq.heappush, heapq.heappop

INF = float("inf")
MAX_STEP_US = 10_000.0
"""The most virtual time one step of the paced driver runs (a fleet that keeps up never
needs more than a fraction of it)."""
STEP_MIN_S = 0.0005
"""The least wall time between two steps of the paced driver: the events due meanwhile run
together in the next step (in virtual time, in their order, as always), so a busy fleet
wakes its driver at most 2,000 times a second, not once per frame start and end.  (The
wait's timeout is in whole milliseconds, epoll's, rounded up: without a client's data
or a poke to wake it, a busy driver sleeps 1 ms, so a frame may reach a client up to
about that much later than it ended on the bus; its timestamp still says when it
ended.  Served at 1 kHz, the PC's writes wake it once a millisecond.)"""
WAKE_SLACK_S = 0.001
"""Work handed to the driver (:meth:`RealtimeDriver.submit`) wakes it only when it would
otherwise sleep longer than this: a busy fleet takes a client's frames at its next step,
without a thread wake-up per frame, an idle one at once."""
SLIP_US = 5_000.0
"""A paced driver that was not run for this long when due (woken that much after its
wait's end, or kept from the fleet's lock: a machine busy with other work, a virtual
machine's host that took the processor) and finds the fleet behind by as much does not
catch up: its clock goes on from where it stopped, as if the pause had not happened (the
driver's time base and the fleet's epoch move on by the pause).  Catching up would run
the boards through the pause faster than the wall clock while the clients' frames came
at the wall clock's pace: the boards would see a stretch of virtual time without the
PC's MCA Alive, and their watchdogs would stop them for a pause of the simulation, not
of the PC.  A fleet behind because its own steps are slow catches up as before (in
steps of :data:`MAX_STEP_US`), and says so when it stays behind (:data:`LAG_WARN_US`)."""
CATCH_UP_RATE = 2.0
"""A fleet behind the wall clock by more than :data:`SLIP_US` that was not found paused
(its own steps were slow, or it was kept from running in the middle of one) catches up at
most this fast against the wall clock: at twice its pace the boards still get the PC's
MCA Alive at least every two of its intervals (the watchdog time is five), where running
through the lag at once would give them none for as long as the lag."""
LAG_WARN_US = 50_000.0
"""A paced fleet this far behind the wall clock after a step is reported: the machine
cannot run it in real time (its frames reach clients late, its timing is off)."""
LAG_PERSIST_S = 1.0
"""... when it stays that far behind for this long (a single slow step, e.g. a program
that starts, is no reason)."""
LAG_WARN_EVERY_S = 10.0
"""At most one such report in this many seconds."""

Event = tuple[float, int, int, Callable[..., None], tuple[Any, ...]]
"""(time, tier, sequence, function, arguments): at equal times tier 0 (state changes:
frames ready or ended, timers) runs before tier 1 (arbitration), then in order of
scheduling."""

_NATIVE: Final = not __file__.endswith(".py")
"""This module runs compiled (:mod:`ucom_tools.compiled`): the events are
:class:`_Scheduled` objects in a heap of the clock's own, compared in C; from source they
are :data:`Event` tuples in a :mod:`heapq` heap, which is C too.  Both run the events in
the same order: by time, tier, sequence (all distinct), whatever the heap's layout."""


class _Scheduled:
    """One event of a compiled clock: :data:`Event`'s fields, typed; ``call`` is what the
    callback is called with, its time first (empty: the time alone): a call with one
    tuple of arguments, where ``callback(t, *args)`` built a list and a tuple of them
    for every event (some 230 instructions more, for two events of every frame)."""

    def __init__(self, t: float, tier: int, seq: int, callback: Callable[..., None],
                 call: tuple[Any, ...]) -> None:
        self.t = t
        self.tier = tier
        self.seq = seq
        self.callback = callback
        self.call = call


def _before(a: _Scheduled, b: _Scheduled) -> bool:
    """``a`` runs before ``b``: (t, tier, seq) compared as :data:`Event` tuples are."""
    if a.t != b.t:
        return a.t < b.t
    if a.tier != b.tier:
        return a.tier < b.tier
    return a.seq < b.seq


class FleetClock:
    """Virtual time and the events of one fleet; ``lock`` guards the whole fleet."""

    def __init__(self) -> None:
        self.now = 0.0
        self.lock = threading.RLock()
        self.changed = threading.Condition(self.lock)
        """Notified when frames went out (senders wait for room) or time was driven."""
        self._events: list[Event] = []
        self._heap: list[_Scheduled] = []
        self._seq = itertools.count()
        self._next_seq = 0

    def at(self, t: float, callback: Callable[..., None], *args: Any, tier: int = 0) -> None:
        """Call ``callback(t, *args)`` at virtual time ``t`` (never before ``now``)."""
        now = self.now
        if _NATIVE:
            seq = self._next_seq
            self._next_seq = seq + 1
            when = t if t > now else now
            # a concatenation, not (when, *args): see compiled.py
            call = (when,) + args if args else ()  # noqa: RUF005
            self._push(_Scheduled(when, tier, seq, callback, call))
        else:
            _heappush(self._events,
                      (t if t > now else now, tier, next(self._seq), callback, args))

    def _push(self, event: _Scheduled) -> None:
        heap = self._heap
        heap.append(event)
        pos = len(heap) - 1
        while pos > 0:  # sift up
            parent = (pos - 1) >> 1
            above = heap[parent]
            if not _before(event, above):
                break
            heap[pos] = above
            pos = parent
        heap[pos] = event

    def _pop(self) -> _Scheduled:
        heap = self._heap
        last = heap.pop()
        if not heap:
            return last
        first = heap[0]
        n = len(heap)
        pos = 0
        while True:  # sift the last one down from the top
            child = 2 * pos + 1
            if child >= n:
                break
            right = child + 1
            if right < n and _before(heap[right], heap[child]):
                child = right
            below = heap[child]
            if not _before(below, last):
                break
            heap[pos] = below
            pos = child
        heap[pos] = last
        return first

    def cancel(self, unwanted: Callable[[float, Callable[..., None], tuple[Any, ...]], bool],
               ) -> int:
        """Drop every scheduled event for which ``unwanted(t, callback, args)`` is true (fault
        injection: a board's frames that its CAN controller lost); returns how many.  The
        others keep their order (a sorted list is a heap).  Costs the whole queue once; may
        be called from a callback (the queue is changed in place)."""
        if _NATIVE:
            heap = self._heap
            kept = [e for e in heap if not unwanted(e.t, e.callback, e.call[1:])]
            dropped = len(heap) - len(kept)
            if dropped:
                kept.sort(key=lambda e: (e.t, e.tier, e.seq))
                heap[:] = kept  # in place: a run_until under way holds the list
            return dropped
        events = self._events
        left = [e for e in events if not unwanted(e[0], e[3], e[4])]
        dropped = len(events) - len(left)
        if dropped:
            heapq.heapify(left)
            events[:] = left  # in place: a run_until under way holds the list
        return dropped

    def next_event_time(self) -> float | None:
        if _NATIVE:
            return self._heap[0].t if self._heap else None
        return self._events[0][0] if self._events else None

    def quiet_until(self, t: float) -> bool:
        """True if no event is due at or before ``t``."""
        if _NATIVE:
            return not self._heap or self._heap[0].t > t
        return not self._events or self._events[0][0] > t

    def advance_to(self, t: float) -> None:
        """Let time pass to ``t`` when nothing is due before (see :meth:`quiet_until`)."""
        if t > self.now:
            self.now = t

    def run_until(self, limit: float, stop: Callable[[], bool] | None = None) -> None:
        """Run every event due up to ``limit`` in time order, or until ``stop()`` turns
        true after an event; then time stands at ``limit`` (if finite and reached)."""
        if _NATIVE:
            heap = self._heap
            while heap and heap[0].t <= limit:
                e = self._pop()
                t = e.t
                self.now = t
                call = e.call
                if call:
                    e.callback(*call)
                else:
                    e.callback(t)
                if stop is not None and stop():
                    return
        else:
            events = self._events
            pop = _heappop
            if stop is None:
                while events and events[0][0] <= limit:
                    t, _tier, _seq, callback, args = pop(events)
                    self.now = t
                    callback(t, *args)
            else:
                while events and events[0][0] <= limit:
                    t, _tier, _seq, callback, args = pop(events)
                    self.now = t
                    callback(t, *args)
                    if stop():
                        return
        if limit != INF and self.now < limit:
            self.now = limit


class RealtimeDriver:
    """A thread that runs a fleet clock at the pace of the wall clock.

    Other threads (a socketcand client's, a paced in-process host's) hand it work with
    :meth:`submit` instead of taking the fleet's lock: the driver runs it at the start of
    its next step, so a busy fleet never keeps a client's frame waiting for the lock.

    The driver wakes when the next event is due, but at most every :data:`STEP_MIN_S`
    (the events due meanwhile run in one step); work handed to it wakes it only when it
    would sleep longer than :data:`WAKE_SLACK_S`.  Code that runs in a step may ask for
    a call after it (:meth:`after_step`: a client's frames of the step, written in one
    go), outside the fleet's lock.

    The driver waits in a selector: sockets :meth:`watch` ed (a socketcand client's) wake
    it when readable, and their callbacks run at the start of the next step, holding the
    lock, before the fleet runs on: a client's frames are read by the thread that steps
    the fleet, without a reader thread, and a fleet that catches up after a stall takes
    them before it runs its boards past them.

    A driver that was not run when due for longer than :data:`SLIP_US` goes on from where
    the pause began (:attr:`on_slip` moves the fleet's epoch with it) instead of running
    the boards through the pause to catch up."""

    def __init__(self, clock: FleetClock, name: str = "fleet") -> None:
        self.clock = clock
        self.name = name
        self.t0 = time.monotonic() - clock.now / 1e6
        self.worst_lag_us = 0.0
        """The most the fleet fell behind the wall clock after a step (0: kept up)."""
        self.slipped_us = 0.0
        """The pauses its clock went on from (:data:`SLIP_US`), in all."""
        self.slips = 0
        """How many."""
        self.on_slip: Callable[[float], None] | None = None
        """Called (holding the lock) with each pause in microseconds after the time base
        moved on by it: the fleet moves its epoch, so that time stamps stay the wall
        clock's."""
        self._slip_window_us = 0.0
        self._slip_window_start = 0.0
        self._next_lag_report = 0.0
        self._behind_since: float | None = None
        self.steps = 0
        """The steps taken so far (each loop of the driver: the callbacks of readable
        sockets, the work handed to it, the fleet run up to the wall clock)."""
        self._stop = False
        self._pending: deque[tuple[float, Callable[[], None]]] = deque()
        self._after: list[Callable[[], None]] = []
        self._sleep_until = 0.0
        """Until when (``time.monotonic()``) the driver sleeps; 0 while it steps."""
        self._waker, self._wake_end = socket.socketpair()
        self._waker.setblocking(False)
        self._wake_end.setblocking(False)
        self._waker_fd = self._waker.fileno()
        self._epoll = select.epoll() if hasattr(select, "epoll") else None
        """The wait for readable descriptors: epoll itself where there is one (Linux: no
        selector keys or maps per wake-up; its timeout in milliseconds, as with the
        selectors module), else the platform's selector."""
        self._selector = None if self._epoll is not None else selectors.DefaultSelector()
        self._register(self._waker_fd)
        self._readable: list[int] = []
        """The descriptors found readable, their callbacks due at the next step."""
        self._watched: dict[socket.socket, Callable[[], None]] = {}
        """Each watched socket and what to call when the driver stops."""
        self._fds: dict[socket.socket, int] = {}
        """Each watched socket's descriptor (a socket closed meanwhile has none)."""
        self._callbacks: dict[int, Callable[[], None]] = {}
        """Each watched descriptor's ``on_readable``."""
        self._rooms: list[Callable[[], bool]] = []
        self._runner = threading.Thread(target=self._run, name=f"ucom-clock-{name}",
                                        daemon=True)

    def in_driver_thread(self) -> bool:
        """Is this the driver's own thread (a node's ``on_frame``, a callback, work handed
        to it)?"""
        return threading.current_thread() is self._runner

    def now_us(self) -> float:
        """Virtual time that corresponds to the wall clock now."""
        return (time.monotonic() - self.t0) * 1e6

    def start(self) -> None:
        self._runner.start()

    def stop(self) -> None:
        """Stop the thread; every socket still watched is given back (its ``on_stop``)."""
        self._stop = True
        self.poke()
        self._runner.join(timeout=2)
        if self._runner.is_alive():
            return
        watched = list(self._watched.values())
        self._watched.clear()
        if self._epoll is not None:
            self._epoll.close()
        if self._selector is not None:
            self._selector.close()
        self._waker.close()
        self._wake_end.close()
        for on_stop in watched:
            try:
                on_stop()
            except Exception:
                log.exception("giving a socket back failed")

    @property
    def running(self) -> bool:
        return not self._stop

    def poke(self) -> None:
        """Wake the driver from its wait."""
        with contextlib.suppress(OSError):  # full (it is awake anyway) or closed
            self._wake_end.send(b"\0")

    def watch(self, sock: socket.socket, on_readable: Callable[[], None],
              on_stop: Callable[[], None]) -> None:
        """From the driver's thread: call ``on_readable()`` (holding the lock, at the start
        of a step) whenever ``sock`` is readable, until :meth:`unwatch`; ``on_stop()``
        when the driver stops meanwhile (in the stopping thread)."""
        fd = sock.fileno()
        if fd in self._callbacks:
            raise KeyError(f"{sock!r} (descriptor {fd}) is already watched")
        self._register(fd)
        self._watched[sock] = on_stop
        self._fds[sock] = fd
        self._callbacks[fd] = on_readable

    def unwatch(self, sock: socket.socket) -> None:
        """From the driver's thread: stop watching ``sock`` (idempotent)."""
        fd = self._fds.pop(sock, None)
        if self._watched.pop(sock, None) is not None and fd is not None:
            self._callbacks.pop(fd, None)
            with contextlib.suppress(KeyError, ValueError, OSError):
                if self._epoll is not None:
                    self._epoll.unregister(fd)
                elif self._selector is not None:
                    self._selector.unregister(fd)

    def wait_for_room(self, check: Callable[[], bool]) -> None:
        """From the driver's thread: call ``check()`` at the start of every step (holding
        the lock) until it returns true."""
        self._rooms.append(check)

    def submit(self, work: Callable[[], None], t: float | None = None) -> None:
        """Run ``work()`` in the driver thread, holding the fleet's lock, before the
        fleet's next step (at once when the driver would sleep longer than
        :data:`WAKE_SLACK_S`).  ``t``: the virtual time the work belongs to (default:
        now); an idle fleet's clock is brought there first."""
        self._pending.append((self.now_us() if t is None else t, work))
        if self._sleep_until - time.monotonic() > WAKE_SLACK_S:
            self.poke()

    def after_step(self, work: Callable[[], None]) -> None:
        """Call ``work()`` once the running step is over, outside the fleet's lock (only
        from code that runs in the driver thread: a node's ``on_frame``, a callback)."""
        self._after.append(work)

    def _run(self) -> None:
        clock = self.clock
        pending = self._pending
        after = self._after
        readable = self._readable
        last = previous = 0.0
        waited_from = -1.0  # the last wait: from when, how long asked, when it returned
        asked = returned = 0.0
        while not self._stop:
            self._sleep_until = 0.0
            self.steps += 1
            previous, last = last, time.monotonic()
            with clock.lock:
                if waited_from >= 0.0:
                    # not run when due: woken that much after the wait's end (a busy
                    # machine, a virtual machine's host) or kept from the lock
                    paused = (max(0.0, returned - waited_from - asked)
                              + time.monotonic() - returned) * 1e6
                    if paused > SLIP_US:
                        first = clock.next_event_time()
                        behind = 0.0 if first is None else self.now_us() - first
                        if behind > SLIP_US:  # go on from there, do not catch up
                            self._slip(min(paused, behind))
                if pending:
                    # an idle fleet's clock stands where its last step left it (up to a
                    # wait ago): bring it to the time of the first work first, so that a
                    # client's frame is taken when it came, not stamped in the past
                    first_t = pending[0][0]
                    if clock.quiet_until(first_t):
                        clock.advance_to(first_t)
                while pending:
                    try:
                        pending.popleft()[1]()
                    except Exception:
                        log.exception("work handed to the fleet failed")
                if readable:
                    self._run_readable()
                if self._rooms:
                    self._run_rooms()
                now = self.now_us()
                first = clock.next_event_time()
                # a fleet behind the wall clock catches up in steps of MAX_STEP_US, so
                # clients' work is taken in between and the lag can be seen; when far
                # behind, at most at CATCH_UP_RATE times the wall clock's pace
                limited = first is not None and now - first > SLIP_US and previous > 0.0
                step = MAX_STEP_US
                if limited:
                    step = min(step, CATCH_UP_RATE * 1e6 * max(last - previous, STEP_MIN_S))
                target = now if first is None else min(now, max(first, clock.now) + step)
                self._advance(target)
                if self._rooms:
                    # the step may have emptied a transmit queue that a client's frames
                    # wait for: fill it now, not after the sleep (a late wake-up on a
                    # busy machine drains the whole queue, and the bus would then stand
                    # idle until the next board event)
                    self._run_rooms()
                nxt = clock.next_event_time()
            if after:
                self._run_after()
            self._note_lag(self.now_us() - clock.now)
            if target < now and not limited:
                waited_from = returned = time.monotonic()
                asked = 0.0
                continue
            wait = 0.5 if nxt is None else min(0.5, max(0.0, (nxt - now) / 1e6))
            wait = max(wait, STEP_MIN_S - (time.monotonic() - last))
            if wait > 0:
                self._sleep_until = time.monotonic() + wait
            asked = wait if wait > 0 and not pending else 0.0
            waited_from = time.monotonic()
            self._select(asked)
            returned = time.monotonic()
            if self._epoll is not None:  # its timeout: whole milliseconds, rounded up
                asked = math.ceil(asked * 1000) / 1000

    def _register(self, fd: int) -> None:
        if self._epoll is not None:
            self._epoll.register(fd, select.EPOLLIN)
        elif self._selector is not None:
            self._selector.register(fd, selectors.EVENT_READ)

    def _select(self, timeout: float) -> None:
        """Wait up to ``timeout`` for a watched socket or a poke; note what is readable."""
        try:
            if self._epoll is not None:
                fds = [fd for fd, _ in self._epoll.poll(timeout if timeout > 0 else 0)]
            elif self._selector is not None:
                fds = [key.fd for key, _ in self._selector.select(timeout)]
            else:
                return
        except (OSError, ValueError):  # closed meanwhile (stopping)
            return
        waker = self._waker_fd
        for fd in fds:
            if fd == waker:
                with contextlib.suppress(OSError):
                    self._waker.recv(4096)
            else:
                self._readable.append(fd)

    def _run_readable(self) -> None:
        """The callbacks of the sockets found readable (a socket unwatched meanwhile is
        not called)."""
        fds = self._readable[:]
        self._readable.clear()
        callbacks = self._callbacks
        for fd in fds:
            call = callbacks.get(fd)
            if call is None:
                continue
            try:
                call()
            except Exception:
                log.exception("reading a watched socket failed")

    def _run_rooms(self) -> None:
        rooms, self._rooms = self._rooms, []
        for check in rooms:
            try:
                done = check()
            except Exception:
                log.exception("a wait for room failed")
                done = True
            if not done:
                self._rooms.append(check)

    def _run_after(self) -> None:
        """The calls :meth:`after_step` asked for, in order; one that raises is logged."""
        work = self._after[:]
        self._after.clear()
        for call in work:
            try:
                call()
            except Exception:
                log.exception("work after a step of the fleet failed")

    def _slip(self, pause_us: float) -> None:
        """Holding the lock: the time base moves on by ``pause_us`` (:data:`SLIP_US`);
        reported (logger ``ucom.bus``) when the pauses of one second add up to
        :data:`LAG_WARN_US`."""
        self.t0 += pause_us / 1e6
        self.slipped_us += pause_us
        self.slips += 1
        if self.on_slip is not None:
            self.on_slip(pause_us)
        t = time.monotonic()
        if t - self._slip_window_start > LAG_PERSIST_S:
            self._slip_window_start, self._slip_window_us = t, 0.0
        self._slip_window_us += pause_us
        if self._slip_window_us >= LAG_WARN_US and t >= self._next_lag_report:
            self._next_lag_report = t + LAG_WARN_EVERY_S
            log.warning("%s was kept from running for %.0f ms within a second (%d pauses "
                        "so far, %.0f ms in all): its clock goes on from where each pause "
                        "began, so that its boards do not take a pause for a PC that went "
                        "quiet; a machine that does this often cannot run the fleet in "
                        "real time", self.name, self._slip_window_us / 1000, self.slips,
                        self.slipped_us / 1000)
            self._slip_window_us = 0.0

    def _note_lag(self, behind_us: float) -> None:
        """``behind_us``: how far the fleet is behind the wall clock after a step;
        reported (logger ``ucom.bus``) when over :data:`LAG_WARN_US` for
        :data:`LAG_PERSIST_S`."""
        if behind_us > self.worst_lag_us:
            self.worst_lag_us = behind_us
        if behind_us < LAG_WARN_US / 5:
            self._behind_since = None
            return
        if behind_us <= LAG_WARN_US:
            return
        t = time.monotonic()
        if self._behind_since is None:
            self._behind_since = t
        elif t - self._behind_since >= LAG_PERSIST_S and t >= self._next_lag_report:
            self._next_lag_report = t + LAG_WARN_EVERY_S
            log.warning("%s runs %.0f ms behind the wall clock: this machine cannot run it "
                        "in real time (its frames reach clients late and its timing is off)",
                        self.name, behind_us / 1000)

    def _advance(self, now: float) -> None:
        """Run the fleet up to ``now`` (holding the lock); a node or callback that raises
        is logged and skipped, never the end of the fleet."""
        clock = self.clock
        while True:
            try:
                clock.run_until(now)
                break
            except Exception:
                log.exception("a node or scheduled callback failed at %.1f us; the bus "
                              "goes on", clock.now)
        clock.changed.notify_all()  # senders waiting for room in their TX queue
