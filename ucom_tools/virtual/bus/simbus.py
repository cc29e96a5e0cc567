"""A simulated CAN bus: arbitration, bit-exact timing, load counters and the init line.

Time is virtual, in microseconds.  Each node sends its own frames in the order it queued
them (a FIFO transmit queue, as CAN interfaces keep an application's frames in order);
when the bus falls idle the frames at the heads of the nodes' queues go out in
arbitration order (lowest identifier first); each occupies the bus for its length in
bits (stuffing included, :mod:`ucom_tools.wire.canbits`) at the bus bitrate.  Nodes are
virtual boards and host ports; the bus also carries the init line that runs from each
board's init output to the next board's init input (dissertation B.2.2).

The protocol's frames are standard (11-bit identifiers).  A host may also send extended
frames (29-bit identifiers, ``extended=True``): they take the extended format's length
and arbitrate by their arbitration field (:func:`~ucom_tools.wire.canbits.arbitration_key`:
a standard frame wins against an extended one with the same base ID), and they reach
only the nodes that take them (``on_extended_frame``), as a CAN controller whose
acceptance filter passes standard frames only never shows the others to its software:
the boards ignore them.

Injected faults (:mod:`~ucom_tools.virtual.injected`) act on the bus too: a node whose CAN
controller stops (a board that loses power or goes bus-off) has its frames not yet on the
wire withdrawn (:meth:`SimBus.withdraw`), and a cable cut between the PC and the boards
(:meth:`SimBus.cut_cable`) loses every frame between a host and a board, both ways, while
the boards still hear each other; a host then finds its frames acknowledged by nobody
(:meth:`SimBus.acknowledged`).

Every bus of a fleet runs on the fleet's :class:`~ucom_tools.virtual.bus.clock.FleetClock`:
a frame becomes ready, the bus arbitrates among the ready frames when it falls idle (after
every frame ready at that instant), the winner ends ``bits / bitrate`` later and is then
delivered.  The clock is driven by the host (virtual time, as fast as the CPU allows) or
paced to the wall clock (:class:`~ucom_tools.virtual.bus.clock.RealtimeDriver`).
"""

from __future__ import annotations

import heapq
import threading
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Final, Protocol

from ucom_tools.virtual.bus.clock import FleetClock
from ucom_tools.wire.canbits import MAX_EXTENDED_ID, arbitration_key, frame_bits
from ucom_tools.wire.ids import Direction, Function

_Entry = tuple[int, int, bytes, object, int, bool]
"""A frame ready to contend: arbitration key, token (the order queued), data, sender,
identifier, extended."""

_heappush: Final = heapq.heappush
_heappop: Final = heapq.heappop

_MCA_CI: Final = int(Function.MCA_CONTROLLER_INPUT)
_FROM_BOARD: Final = tuple(
    any(f.value == code and f.direction is Direction.BOARD_TO_HOST for f in Function)
    for code in range(32))
"""Per function (identifier bits 10-6): a board sends it (its answers, Error, the run time's
SO maps), which no board takes from another board."""

TX_QUEUE: Final = 32
"""Frames a host may have waiting for the bus before ``send`` blocks (real time only),
like the transmit queue of a CAN adapter."""


class Node(Protocol):
    """Anything attached to the bus that receives frames.  A node that takes extended
    frames too has ``on_extended_frame(arbitration_id, data, t_end)`` as well.  A node
    with ``takes_board_frames`` false (a board) is not offered the frames of the
    functions boards send (:data:`_FROM_BOARD`), as a CAN controller's acceptance filter
    keeps them from its software: its ``on_frame`` would ignore each of them.  Likewise a
    node with ``takes_ci_map(number)`` is offered a CI process-data frame (function
    MCA_CONTROLLER_INPUT, identifier type 1) only for the maps it answers true for; it
    calls :meth:`SimBus.filters_changed` whenever that answer may change.  The fault
    injection of :attr:`SimBus.drop` is still asked for every node and frame."""

    def on_frame(self, arbitration_id: int, data: bytes, t_end: float) -> None: ...


@dataclass
class BusStats:
    """Counters of one bus since it was created (or last reset)."""

    frames: int = 0
    bits: int = 0
    payload_bits: int = 0
    busy_us: float = 0.0
    clashes: int = 0
    errors: int = 0
    """Error frames seen (:meth:`SimBus.error_frame`)."""
    extended: int = 0
    """Extended frames among :attr:`frames` (they have no function)."""
    function_counts: list[int] = field(default_factory=lambda: [0] * 32)
    """Standard frames by function (identifier bits 10-6), indexed by it: a list, not a
    Counter, because the bus counts every frame (a Counter is a dict subclass written
    in Python: each ``+= 1`` went through the interpreter)."""

    @property
    def by_function(self) -> Counter[int]:
        """:attr:`function_counts` as a Counter of the functions seen."""
        return Counter({f: n for f, n in enumerate(self.function_counts) if n})

    def load(self, elapsed_us: float) -> float:
        return self.busy_us / elapsed_us if elapsed_us > 0 else 0.0


def _board_side(node: object) -> bool:
    """A node on the boards' side of the bus (a board: it takes no board's frames, see
    :class:`Node`), not the PC's."""
    return getattr(node, "takes_board_frames", True) is False


class ChainMember(Protocol):
    in_drive: bool
    out_drive: bool

    @property
    def powered(self) -> bool: ...


class SimBus:
    """One CAN bus of a fleet, on the fleet's clock (its own when made alone)."""

    def __init__(self, name: str, bitrate: int, clock: FleetClock | None = None) -> None:
        if bitrate <= 0:
            raise ValueError("bitrate must be positive")
        self.name = name
        self.bitrate = bitrate
        self.us_per_bit = 1e6 / bitrate
        self.clock = clock or FleetClock()
        self.stats = BusStats()
        self._contenders: list[_Entry] = []
        """The frames at the heads of the senders' queues, a heap by arbitration key
        (a standard frame's key is its identifier << 19), then by the order queued."""
        self._waiting: dict[int, deque[_Entry] | None] = {}
        """Per sender with a frame contending (by id(sender)): the ready frames behind it,
        in order (None: none yet), so each node sends FIFO."""
        self._busy = False
        self._arbitration_due = False
        self._next_token = 0
        self.nodes: list[Node] = []
        self._board_listeners: list[Node] = []
        """The nodes offered the frames of :data:`_FROM_BOARD` (see :class:`Node`)."""
        self._ci_takers: dict[int, list[Node]] = {}
        """Per CI process-data identifier, the nodes offered its frames (see :class:`Node`);
        filled as frames come, emptied by :meth:`filters_changed`."""
        self.chain: list[ChainMember] = []
        self.broken_before: set[int] = set()
        """Chain positions p (0-based) whose init input is cut off from board p-1's output."""
        self.sent_marks: dict[int, float] = {}
        self._tracked: set[int] = set()
        self.queued: dict[object, int] = {}
        """Frames each sender has queued that are not on the wire yet (its TX queue)."""
        self.drop: Callable[[object, int, bytes], bool] | None = None
        """Fault injection: ``drop(node, id, data)`` true = ``node`` misses that standard
        frame (extended frames are not offered to it); :attr:`delivering` is its sender."""
        self.delivering: object = None
        """The sender of the frame being delivered while :attr:`drop` is asked."""
        self._cuts = 0
        """Cable cuts in force (:meth:`cut_cable`)."""
        self._drop_uncut: Callable[[object, int, bytes], bool] | None = None
        """:attr:`drop` before the cable was cut."""
        # the clock's callbacks of every frame, bound once (``self._ready`` makes a new
        # bound method each time it is read)
        self._on_ready: Callable[..., None] = self._ready
        self._on_arbitrate: Callable[[float], None] = self._arbitrate
        self._on_end: Callable[..., None] = self._end

    # ---------------------------------------------------------------- the clock's
    @property
    def now(self) -> float:
        return self.clock.now

    @property
    def lock(self) -> threading.RLock:
        return self.clock.lock

    @property
    def changed(self) -> threading.Condition:
        return self.clock.changed

    def at(self, t: float, callback: Callable[[float], None]) -> None:
        """Call ``callback(t)`` at virtual time ``t``."""
        self.clock.at(t, callback)

    def next_event_time(self) -> float | None:
        return self.clock.next_event_time()

    def run_until(self, limit: float, stop: Callable[[], bool] | None = None) -> None:
        """Run the fleet (every bus of the clock) up to ``limit`` or until ``stop()``."""
        self.clock.run_until(limit, stop)

    # ---------------------------------------------------------------- attaching
    def attach(self, node: Node) -> None:
        with self.lock:
            self.nodes.append(node)
            self._listen()

    def detach(self, node: Node) -> None:
        with self.lock:
            if node in self.nodes:
                self.nodes.remove(node)
                self._listen()

    def _listen(self) -> None:
        self._board_listeners = [n for n in self.nodes
                                 if getattr(n, "takes_board_frames", True)]
        self._ci_takers = {}

    def filters_changed(self) -> None:
        """A node's ``takes_ci_map`` may answer differently from now on (a board's program
        defined or dropped a CI map, started or ended)."""
        if self._ci_takers:
            self._ci_takers = {}

    def _ci_takers_of(self, arbitration_id: int) -> list[Node]:
        number = arbitration_id & 0x1F
        takers: list[Node] = []
        for node in self.nodes:
            takes = getattr(node, "takes_ci_map", None)
            if takes is None or takes(number):
                takers.append(node)
        self._ci_takers[arbitration_id] = takers
        return takers

    # ---------------------------------------------------------------- frames
    def send(self, sender: object, t_ready: float, arbitration_id: int, data: bytes,
             track: bool = False, *, extended: bool = False) -> int:
        """Queue a frame that may start at ``t_ready``; with ``track`` its end time can be
        asked with :meth:`sent_at` (the token is returned).  ``extended``: a 29-bit
        identifier."""
        if extended and not 0 <= arbitration_id <= MAX_EXTENDED_ID:
            raise ValueError(f"extended identifier 0x{arbitration_id:X}: more than 29 bits")
        token = self._next_token
        self._next_token = token + 1
        queued = self.queued  # (a plain dict: a Counter's += goes through Python)
        queued[sender] = queued.get(sender, 0) + 1
        if track:
            self._tracked.add(token)
        if type(data) is not bytes:  # (bytes(data) of bytes looks up __bytes__: costly)
            data = bytes(data)
        if extended:
            self.clock.at(t_ready, self._on_ready, arbitration_id, token, data, sender, True)
        else:
            self.clock.at(t_ready, self._on_ready, arbitration_id, token, data, sender)
        return token

    def send_alone(self, sender: object, t_ready: float, arbitration_id: int,
                   data: bytes, *, extended: bool = False) -> float | None:
        """Transmit a frame at once if nothing can come first: the bus is idle, no frame
        waits for it, and no event of the fleet is due before the frame would end (what
        :meth:`send` and the clock would do, without their queues).  Returns the frame's
        end time, or None when it must take the general way."""
        if self._busy or self._contenders or self._arbitration_due:
            return None
        if extended and not 0 <= arbitration_id <= MAX_EXTENDED_ID:
            raise ValueError(f"extended identifier 0x{arbitration_id:X}: more than 29 bits")
        clock = self.clock
        start = t_ready if t_ready > clock.now else clock.now
        bits = frame_bits(arbitration_id, data, extended=True) if extended else \
            frame_bits(arbitration_id, data)
        t_end = start + bits * self.us_per_bit
        if not clock.quiet_until(t_end):
            return None
        clock.advance_to(t_end)
        queued = self.queued  # (a plain dict: a Counter's += goes through Python)
        queued[sender] = queued.get(sender, 0) + 1
        self._deliver(t_end, arbitration_id, -1, data, sender, bits, extended)
        return t_end

    def _ready(self, t: float, arbitration_id: int, token: int, data: bytes,
               sender: object, extended: bool = False) -> None:
        entry: _Entry = (arbitration_key(arbitration_id, extended), token, data, sender,
                         arbitration_id, extended)
        key = id(sender)
        waiting = self._waiting
        if key not in waiting:
            waiting[key] = None  # the sender's head contends
            _heappush(self._contenders, entry)
        else:
            queue = waiting[key]
            if queue is None:
                waiting[key] = queue = deque()
            queue.append(entry)
        self._want_arbitration(t)

    def _want_arbitration(self, t: float) -> None:
        if not self._busy and not self._arbitration_due:
            self._arbitration_due = True
            self.clock.at(t, self._on_arbitrate, tier=1)  # after every frame ready at t

    def _arbitrate(self, t: float) -> None:
        self._arbitration_due = False
        contenders = self._contenders
        if self._busy or not contenders:
            return
        head = _heappop(contenders)
        rank, token, data, sender, arbitration_id, extended = head
        if contenders and contenders[0][0] == rank and contenders[0][3] is not sender:
            self.stats.clashes += 1
        key = id(sender)
        queue = self._waiting[key]
        if queue:
            _heappush(contenders, queue.popleft())
        else:
            del self._waiting[key]
        bits = frame_bits(arbitration_id, data, extended=True) if extended else \
            frame_bits(arbitration_id, data)
        self._busy = True
        self.clock.at(t + bits * self.us_per_bit, self._on_end, arbitration_id, token, data,
                      sender, bits, extended)

    def _end(self, t: float, arbitration_id: int, token: int, data: bytes, sender: object,
             bits: int, extended: bool) -> None:
        self._busy = False
        self._deliver(t, arbitration_id, token, data, sender, bits, extended)
        if self._contenders:
            self._want_arbitration(t)

    def _deliver(self, t_end: float, arbitration_id: int, token: int, data: bytes,
                 sender: object, bits: int, extended: bool = False) -> None:
        duration = bits * self.us_per_bit
        stats = self.stats
        stats.frames += 1
        stats.bits += bits
        stats.payload_bits += 8 * len(data)
        stats.busy_us += duration
        queued = self.queued
        queued[sender] = queued.get(sender, 0) - 1
        if token >= 0 and token in self._tracked:
            self._tracked.discard(token)
            self.sent_marks[token] = t_end
        if extended:
            stats.extended += 1
            for node in self.nodes:
                take = getattr(node, "on_extended_frame", None)
                if node is not sender and take is not None:
                    take(arbitration_id, data, t_end)
            return
        function = arbitration_id >> 6
        stats.function_counts[function] += 1
        drop = self.drop
        if drop is None:
            if function == _MCA_CI and arbitration_id & 0x20:
                takers = self._ci_takers.get(arbitration_id)
                if takers is None:
                    takers = self._ci_takers_of(arbitration_id)
            elif _FROM_BOARD[function]:
                takers = self._board_listeners
            else:
                takers = self.nodes
            for node in takers:
                if node is not sender:
                    node.on_frame(arbitration_id, data, t_end)
            return
        self.delivering = sender
        for node in self.nodes:
            if node is not sender and not drop(node, arbitration_id, data):
                node.on_frame(arbitration_id, data, t_end)

    ERROR_FRAME_BITS = 20
    """An error flag (6 dominant bits, up to 12 with superposition) and its delimiter (8)."""

    def error_frame(self, t: float) -> None:
        """Fault injection: an error frame at ``t`` (a node saw a bit, stuff, CRC or form
        error).  It occupies the bus for :data:`ERROR_FRAME_BITS` and every node that
        keeps error counters (``on_bus_error``) sees it."""
        def signal(when: float) -> None:
            self.stats.busy_us += self.ERROR_FRAME_BITS * self.us_per_bit
            self.stats.errors += 1
            for node in self.nodes:
                hook = getattr(node, "on_bus_error", None)
                if hook is not None:
                    hook(when)
        self.clock.at(t, signal)

    # ---------------------------------------------------------------- injected faults
    def withdraw(self, sender: object) -> int:
        """The frames ``sender`` queued that are not on the wire yet are lost (its CAN
        controller lost power or went bus-off), and one of its frames on the wire now is
        cut short: it ends unreceived (an error, :attr:`BusStats.errors`) when it would
        have ended.  Returns how many frames were lost.  Costs the clock's queue once."""
        on_ready, on_end = self._on_ready, self._on_end
        ends: list[float] = []

        def unwanted(t: float, callback: Callable[..., None], args: tuple[object, ...],
                     ) -> bool:
            if callback is on_ready and args[3] is sender:
                return True
            if callback is on_end and args[3] is sender:
                ends.append(t)
                return True
            return False

        lost = self.clock.cancel(unwanted) - len(ends)
        queue = self._waiting.pop(id(sender), None) if id(sender) in self._waiting else None
        contenders = self._contenders
        kept = [e for e in contenders if e[3] is not sender]
        lost += len(contenders) - len(kept) + (len(queue) if queue else 0)
        if len(kept) != len(contenders):
            heapq.heapify(kept)
            contenders[:] = kept
        if lost:
            self.queued[sender] = self.queued.get(sender, 0) - lost
        for t_end in ends:
            self.clock.at(t_end, self._cut_short, sender)
        return lost + len(ends)

    def _cut_short(self, t: float, sender: object) -> None:
        """A frame of ``sender`` that was on the wire when its controller stopped ends
        here, received by nobody."""
        self._busy = False
        self.stats.errors += 1
        self.queued[sender] = self.queued.get(sender, 0) - 1
        if self._contenders:
            self._want_arbitration(t)

    def cut_cable(self) -> None:
        """Cut the cable between the PC and the boards (an injected fault; cuts add up):
        every standard frame between a host and a board is lost, both ways; the boards
        hear each other, and so do the hosts.  Costs the slow way of :attr:`drop` per
        frame while it lasts, nothing after."""
        self._cuts += 1
        if self._cuts == 1:
            self._drop_uncut = self.drop
            self.drop = self._cut_drop

    def mend_cable(self) -> None:
        """End one :meth:`cut_cable`."""
        if self._cuts == 0:
            return
        self._cuts -= 1
        if self._cuts == 0:
            self.drop = self._drop_uncut
            self._drop_uncut = None

    @property
    def cable_cut(self) -> bool:
        return self._cuts > 0

    def _cut_drop(self, node: object, arbitration_id: int, data: bytes) -> bool:
        if _board_side(node) != _board_side(self.delivering):
            return True
        inner = self._drop_uncut
        return inner is not None and inner(node, arbitration_id, data)

    def acknowledged(self, sender: object) -> bool:
        """Would a frame that ``sender`` sends now be acknowledged: does another node take
        it - one that listens (a board powered and not bus-off; not a listen-only node:
        ``listening`` false), on ``sender``'s side of a cut cable?  (python-can's
        ``bus.state`` of a host: error-passive while nobody does.)"""
        cut = self._cuts > 0
        board = _board_side(sender)
        for node in list(self.nodes):
            if node is sender or (cut and _board_side(node) != board) or \
                    not getattr(node, "listening", True):
                continue
            return True
        return False

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
