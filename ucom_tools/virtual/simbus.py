"""A simulated CAN bus: arbitration, bit-exact timing, load counters and the init line.

Time is virtual, in microseconds.  Each node sends its own frames in the order it queued
them (a FIFO transmit queue, as CAN interfaces keep an application's frames in order);
when the bus falls idle the frames at the heads of the nodes' queues go out in
arbitration order (lowest identifier first); each occupies the bus for its length in
bits (stuffing included, :mod:`ucom_tools.wire.canbits`) at the bus bitrate.  Nodes are
virtual boards and host ports; the bus also carries the init line that runs from each
board's init output to the next board's init input (dissertation B.2.2).

The bus is driven either by its host (``run_until``: virtual time, as fast as the CPU
allows) or by a real-time clock (:class:`~ucom_tools.virtual.clock.RealtimeDriver`).
"""

from __future__ import annotations

import heapq
import itertools
import threading
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

from ucom_tools.wire.canbits import frame_bits


class Node(Protocol):
    """Anything attached to the bus that receives frames."""

    def on_frame(self, arbitration_id: int, data: bytes, t_end: float) -> None: ...


@dataclass
class BusStats:
    """Counters of one bus since it was created (or last reset)."""

    frames: int = 0
    bits: int = 0
    payload_bits: int = 0
    busy_us: float = 0.0
    clashes: int = 0
    by_function: Counter[int] = field(default_factory=Counter)

    def load(self, elapsed_us: float) -> float:
        return self.busy_us / elapsed_us if elapsed_us > 0 else 0.0


class ChainMember(Protocol):
    in_drive: bool
    out_drive: bool

    @property
    def powered(self) -> bool: ...


class SimBus:
    """One CAN bus of the fleet."""

    def __init__(self, name: str, bitrate: int) -> None:
        if bitrate <= 0:
            raise ValueError("bitrate must be positive")
        self.name = name
        self.bitrate = bitrate
        self.us_per_bit = 1e6 / bitrate
        self.now = 0.0
        self.stats = BusStats()
        self.lock = threading.RLock()
        self.changed = threading.Condition(self.lock)
        self._events: list[tuple[float, int, Callable[[float], None] | None,
                                 tuple[int, bytes, object] | None]] = []
        self._contenders: list[tuple[int, int, bytes, object]] = []
        self._waiting: dict[int, deque[tuple[int, int, bytes, object]] | None] = {}
        """Per sender with a frame contending (by id(sender)): the ready frames behind it,
        in order (None: none yet), so each node sends FIFO."""
        self._seq = itertools.count()
        self.nodes: list[Node] = []
        self.chain: list[ChainMember] = []
        self.broken_before: set[int] = set()
        """Chain positions p (0-based) whose init input is cut off from board p-1's output."""
        self.sent_marks: dict[int, float] = {}
        self._tracked: set[int] = set()
        self.queued: Counter[object] = Counter()
        """Frames each sender has queued that are not on the wire yet (its TX queue)."""
        self.drop: Callable[[object, int, bytes], bool] | None = None
        """Fault injection: ``drop(node, id, data)`` true = ``node`` misses that frame."""

    # ---------------------------------------------------------------- attaching
    def attach(self, node: Node) -> None:
        with self.lock:
            self.nodes.append(node)

    def detach(self, node: Node) -> None:
        with self.lock:
            if node in self.nodes:
                self.nodes.remove(node)

    # ---------------------------------------------------------------- scheduling
    def send(self, sender: object, t_ready: float, arbitration_id: int, data: bytes,
             track: bool = False) -> int:
        """Queue a frame that may start at ``t_ready``; with ``track`` its end time can be
        asked with :meth:`sent_at` (the token is returned)."""
        token = next(self._seq)
        self.queued[sender] += 1
        if track:
            self._tracked.add(token)
        heapq.heappush(self._events, (t_ready, token, None, (arbitration_id, bytes(data), sender)))
        return token

    def send_alone(self, sender: object, t_ready: float, arbitration_id: int,
                   data: bytes) -> float | None:
        """Transmit a frame at once if nothing else can come first: no event is due by
        ``t_ready`` and no frame waits for the bus (what :meth:`send` and
        :meth:`run_until` would do, without their queues).  Returns the frame's end time,
        or None when the frame must take the general way."""
        events = self._events
        if self._contenders or (events and events[0][0] <= t_ready):
            return None
        if t_ready > self.now:
            self.now = t_ready
        self.queued[sender] += 1
        self._transmit(arbitration_id, -1, data, sender)
        return self.now

    def at(self, t: float, callback: Callable[[float], None]) -> None:
        """Call ``callback(t)`` at virtual time ``t``."""
        heapq.heappush(self._events, (t, next(self._seq), callback, None))

    def next_event_time(self) -> float | None:
        if self._contenders:
            return self.now
        return self._events[0][0] if self._events else None

    def run_until(self, limit: float, stop: Callable[[], bool] | None = None) -> None:
        """Advance virtual time up to ``limit``, or until ``stop()`` turns true."""
        events, contenders, waiting = self._events, self._contenders, self._waiting
        while True:
            while events and events[0][0] <= self.now:
                t, seq, callback, frame = heapq.heappop(events)
                if frame is None:
                    assert callback is not None
                    callback(t)
                else:
                    entry = (frame[0], seq, frame[1], frame[2])
                    key = id(frame[2])
                    if key not in waiting:
                        waiting[key] = None  # the sender's head contends
                        heapq.heappush(contenders, entry)
                    else:
                        queue = waiting[key]
                        if queue is None:
                            waiting[key] = queue = deque()
                        queue.append(entry)
            if contenders:
                if self.now > limit:
                    return
                head = heapq.heappop(contenders)
                key = id(head[3])
                queue = waiting[key]
                if queue:
                    heapq.heappush(contenders, queue.popleft())
                else:
                    del waiting[key]
                self._transmit(*head)
                if stop is not None and stop():
                    return
                continue
            if not events or events[0][0] > limit:
                if self.now < limit != float("inf"):
                    self.now = limit
                return
            self.now = events[0][0]

    def _transmit(self, arbitration_id: int, seq: int, data: bytes, sender: object) -> None:
        contenders = self._contenders
        if contenders and contenders[0][0] == arbitration_id and contenders[0][3] is not sender:
            self.stats.clashes += 1
        bits = frame_bits(arbitration_id, data)
        duration = bits * self.us_per_bit
        t_end = self.now + duration
        stats = self.stats
        stats.frames += 1
        stats.bits += bits
        stats.payload_bits += 8 * len(data)
        stats.busy_us += duration
        stats.by_function[arbitration_id >> 6] += 1
        self.now = t_end
        self.queued[sender] -= 1
        if seq >= 0 and seq in self._tracked:
            self._tracked.discard(seq)
            self.sent_marks[seq] = t_end
        drop = self.drop
        for node in self.nodes:
            if node is not sender and (drop is None or not drop(node, arbitration_id, data)):
                node.on_frame(arbitration_id, data, t_end)

    def sent_at(self, token: int) -> float | None:
        """End time of the frame queued with ``token`` once it went out (and forget it)."""
        return self.sent_marks.pop(token, None)

    # ---------------------------------------------------------------- init line
    def init_in_set(self, pos: int) -> bool:
        """Does board ``pos`` measure a set (electrically Lo) level at its init input?"""
        me = self.chain[pos]
        if me.powered and me.in_drive:
            return True
        if pos == 0 or pos in self.broken_before:
            return False
        prev = self.chain[pos - 1]
        return prev.powered and prev.out_drive

    def init_out_set(self, pos: int) -> bool:
        """Does board ``pos`` measure a set level at its init output?"""
        me = self.chain[pos]
        if me.powered and me.out_drive:
            return True
        nxt = pos + 1
        if nxt >= len(self.chain) or nxt in self.broken_before:
            return False
        other = self.chain[nxt]
        return other.powered and other.in_drive
