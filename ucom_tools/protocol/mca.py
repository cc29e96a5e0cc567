"""Host side of the run-time protocol (``man/ucom-protocol.7``, RUN TIME): one client per
bus, a subscriber of the bus's dispatcher beside the bootloader link.

Every configuring request (edge writes, Admin Data, MCA Start) is acknowledged by the
board with MCA Ready and asked again when the answer does not come, like the bootloader
services; descriptions and read-backs are assembled from their frames and what is missing
is asked for again, edge by edge.  Process data (SO maps) are not queued: the latest value
of every map is kept (MCA2's latest-value semantics).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Final

import can

from ucom_tools.errors import BoardError, FrameError, UcomTimeoutError
from ucom_tools.protocol.link import Link
from ucom_tools.protocol.routing import Subscription
from ucom_tools.protocol.timeouts import DEFAULT, Timeouts
from ucom_tools.wire import mca
from ucom_tools.wire import messages as m
from ucom_tools.wire.answers import AppReport
from ucom_tools.wire.codes import ReportChannel
from ucom_tools.wire.digest import DescrDigest, DigestRequest, digest_of
from ucom_tools.wire.ids import ALL, Address, Function

_ANSWERS: Final = frozenset({Function.MCA_READY, Function.MCA_DUMPIO_DESCR, Function.MCA_DSP_CI,
                      Function.ERROR})


def _answer(msg: can.Message) -> bool:
    """A board's generic run-time answer (type bit 0), or an Error."""
    if msg.is_extended_id or msg.is_error_frame or msg.is_remote_frame:
        return False
    return (msg.arbitration_id >> 6) in _ANSWERS and not msg.arbitration_id & 0x20


def _so_map(msg: can.Message) -> bool:
    return not msg.is_extended_id and (msg.arbitration_id >> 6) == Function.MCA_SENSOR_OUTPUT \
        and bool(msg.arbitration_id & 0x20)


@dataclass(frozen=True)
class BoardEdges:
    """A running program's edges as its board described them (MCA DumpIO Descr)."""

    ci: tuple[mca.EdgeRecord, ...]
    so: tuple[mca.EdgeRecord, ...]
    par: tuple[mca.EdgeRecord, ...]

    def of(self, kind: mca.Kind) -> tuple[mca.EdgeRecord, ...]:
        return (self.ci, self.so, self.par)[kind]

    def digest(self) -> int:
        """The description's digest (:func:`ucom_tools.wire.digest.digest_of`): what the
        board's program answers to :meth:`McaClient.digest` if it is this description."""
        return digest_of(self.ci + self.so + self.par)


MASK_TABLE: Final = bytes(b ^ mca.MAP_MASK for b in range(256))
""":func:`mca.mask` as a translation table (the process image unmasks every SO map)."""


@dataclass
class ProcessImage:
    """The latest SO process data of a bus: each map's values (unmasked bytes) and when
    they came, how many frames of each came; how many frames of the maps in
    :attr:`watched` (the boards' fastest, which the run time watches) came in all
    (:attr:`received`), and for each map how many of those had come when its latest
    frame came (:attr:`order`): the frames of the others that came after a board's last,
    in the order they were sent, tell how long it was silent."""

    frames: dict[int, bytes] = field(default_factory=dict)
    stamps: dict[int, float] = field(default_factory=dict)
    counts: dict[int, int] = field(default_factory=dict)
    watched: set[int] = field(default_factory=set)
    order: dict[int, int] = field(default_factory=dict)
    received: int = 0

    def take(self, msg: can.Message) -> None:
        """A received SO map, as a message (:meth:`take_data`)."""
        self.take_data(msg.arbitration_id, bytes(msg.data), msg.timestamp)

    def take_data(self, arbitration_id: int, data: bytes, stamp: float) -> None:
        """A received SO map by identifier, data and time stamp (every one the boards
        send: :func:`mca.mask` inlined)."""
        number = arbitration_id & 0x1F
        self.frames[number] = data.translate(MASK_TABLE)
        self.stamps[number] = stamp
        counts = self.counts
        counts[number] = counts.get(number, 0) + 1
        received = self.received
        if number in self.watched:
            received += 1
            self.received = received
        self.order[number] = received


SAME_BASE_S: Final = 600.0
"""A frame stamped up to this long before a request is a late answer to an earlier one;
one stamped longer before is on another time base (an adapter that counts from its own
start), which says nothing about when it came, and is taken as before."""


class McaClient:
    """Run-time services on one bus."""

    def __init__(self, link: Link, timeouts: Timeouts = DEFAULT, *,
                 process_data: bool = True) -> None:
        self.link = link
        self.timeouts = timeouts
        self.image = ProcessImage()
        self.errors: list[tuple[Address, m.Error]] = []
        dispatcher = link.dispatcher
        self._sub = dispatcher.subscribe(_answer, f"{link.name} run time")
        self._maps: Subscription | None = dispatcher.subscribe(
            _so_map, f"{link.name} process data", on_data=self.image.take_data) \
            if process_data else None
        """The SO maps into :attr:`image` (not with ``process_data`` false: a second
        client beside the run time's, for requests only)."""

    def close(self) -> None:
        self.link.dispatcher.unsubscribe(self._sub)
        if self._maps is not None:
            self.link.dispatcher.unsubscribe(self._maps)

    def forget(self) -> int:
        """Drop the answers and Errors that came while nothing of this client waited
        (others' answers on a bus where another client asks, a rejoin's, say: each
        subscription gets a copy); how many.  Only between this client's requests."""
        return self.link.dispatcher.discard(self._sub)

    # ------------------------------------------------------------------ plumbing
    def _send(self, msg: mca.McaMessage, address: Address | None = None) -> None:
        arb, data = mca.encode(msg, address)
        self.link.send_raw(arb, data)

    def _next(self, deadline: float, after: float | None = None,
              ) -> tuple[Address, mca.McaMessage | m.Error] | None:
        """The next run-time answer or Error by ``deadline``; with ``after``, none that was
        on the bus before then (a late answer to an earlier request is not this one's; an
        Error is kept in :attr:`errors` all the same)."""
        while True:
            raw = self.link.dispatcher.wait(self._sub, deadline)
            if raw is None:
                return None
            stale = after is not None and 0.0 < after - raw.timestamp < SAME_BASE_S
            try:
                if raw.arbitration_id >> 6 == Function.ERROR:
                    address, err = m.decode(raw.arbitration_id, bytes(raw.data))
                    assert isinstance(err, m.Error)
                    self.errors.append((address, err))
                    if stale:
                        continue
                    return address, err
                if stale:
                    continue
                address2, msg = mca.decode(raw.arbitration_id, bytes(raw.data))
            except FrameError:
                continue
            if address2 is not None:
                return address2, msg

    def _ack(self, address: Address, request: mca.McaMessage, function: Function,
             echo0: int) -> mca.McaReady:
        """Send ``request`` until the board acknowledges it (or refuses it: BoardError)."""
        sent = self.link.dispatcher.stamp()  # on the base of the answers' time stamps
        for _ in range(1 + self.timeouts.retries):
            self._send(request, address)
            deadline = self.link.deadline(self.timeouts.reply, answers=1)
            while (got := self._next(deadline, after=sent)) is not None:
                source, msg = got
                if source != address:
                    continue
                if isinstance(msg, m.Error) and msg.function == function:
                    raise BoardError(f"board {address}: {msg.describe()}")
                if isinstance(msg, mca.McaReady) and msg.answers == function and \
                        msg.echo[0] == echo0:
                    return msg
        raise UcomTimeoutError(f"board {address} did not acknowledge "
                               f"{function.label} ({1 + self.timeouts.retries} times asked)")

    # ------------------------------------------------------------------ state
    def wait_ready(self, address: Address, timeout: float) -> mca.McaReady | None:
        """The MCA Ready a board sends once its program is up (unsolicited), within
        ``timeout`` seconds; falls back to asking (QUERY)."""
        deadline = self.link.deadline(timeout, answers=1)
        while (got := self._next(deadline)) is not None:
            source, msg = got
            if source == address and isinstance(msg, mca.McaReady):
                return msg
        try:
            return self.query(address)
        except UcomTimeoutError:
            return None

    def wait_started(self, address: Address, timeout: float,
                     ) -> mca.McaReady | m.Error | None:
        """After a Start sent to ``address``: its program's MCA Ready (the program is up,
        its compatibility check passed: nothing else can follow), or an Error of that
        board (its refusal, or another), whichever comes first within ``timeout``
        seconds; None: neither (ask no QUERY: the caller decides)."""
        deadline = self.link.deadline(timeout, answers=2)
        while (got := self._next(deadline)) is not None:
            source, msg = got
            if source == address and isinstance(msg, (mca.McaReady, m.Error)):
                return msg
        return None

    def query(self, address: Address) -> mca.McaReady:
        return self._ack(address, mca.McaStart(mca.StartOp.QUERY), Function.MCA_START,
                         mca.StartOp.QUERY)

    def start(self, address: Address, op: mca.StartOp = mca.StartOp.START) -> mca.McaReady:
        return self._ack(address, mca.McaStart(op), Function.MCA_START, op)

    def admin(self, address: Address, data: mca.AdminData) -> mca.McaReady:
        return self._ack(address, data, Function.MCA_ADMIN_DATA, data.op)

    def app_status(self, address: Address) -> mca.AppStatus:
        """The program's state, load, cycle time and overruns (Report channel 3)."""
        for _ in range(1 + self.timeouts.retries):
            self.link.send(m.ReportRequest(ReportChannel.APPLICATION), address)
            deadline = self.link.deadline(self.timeouts.reply, answers=1)
            while (got := self.link.recv_until(deadline)) is not None:
                if got.address != address:
                    continue
                if isinstance(got.message, AppReport):
                    return mca.AppStatus.decode(got.message.data)
                if isinstance(got.message, m.Error) and \
                        got.message.function == Function.REPORT_REQUEST:
                    raise BoardError(f"board {address}: {got.message.describe()}")
        raise UcomTimeoutError(f"board {address} did not send its application report "
                               f"({1 + self.timeouts.retries} times asked)")

    # ------------------------------------------------------------------ descriptions
    def describe(self, address: Address, counts: tuple[int, int, int] | None = None,
                 *, at_a_time: int = 0) -> BoardEdges:
        """Every edge's description.  ``counts`` (CI, SO, PAR; from MCA Ready, asked for
        when not given) tells when the description is complete; edges that did not arrive
        whole are asked for again, each on its own.  ``at_a_time``: so many edges asked
        for, each on its own, the next ones once they came (a board joining a running
        exchange: its whole description at once would hold the bus for tens of
        milliseconds, and MCA Alive, whose identifier loses to it, with it); 0: all at
        once."""
        if counts is None:
            ready = self.query(address)
            counts = (ready.ci, ready.so, ready.par)
        parts: dict[tuple[int, int], dict[int, bytes]] = {}
        done: dict[tuple[int, int], mca.EdgeRecord] = {}
        lasts: dict[tuple[int, int], int] = {}
        wanted = {(int(k), i) for k in mca.Kind for i in range(counts[k])}
        if at_a_time > 0:
            order = sorted(wanted)
            for first in range(0, len(order), at_a_time):
                some = order[first:first + at_a_time]
                self._gather(address, set(some), [mca.DescrRequest(mca.Kind(k), i)
                                                  for k, i in some], parts, lasts, done)
        else:
            self._gather(address, wanted, [mca.DescrRequest()], parts, lasts, done)
        if wanted - done.keys():
            raise UcomTimeoutError(f"board {address}: {len(wanted - done.keys())} edge "
                                   "descriptions did not arrive")
        return BoardEdges(*(tuple(done[(k, i)] for i in range(counts[k])) for k in mca.Kind))

    def digest(self, address: Address) -> int | None:
        """The description's digest (MCA DumpIO Descr Request DLC 1), or None when the
        board refuses the request (a program that does not know it answers Error
        BAD_LENGTH) or does not answer within the reply time.  Asked once: None only
        costs the caller the reading of the records (:meth:`describe`), which it falls
        back to, where asking again would cost a program that stays silent the reply
        time twice more."""
        sent = self.link.dispatcher.stamp()
        self._send(DigestRequest(), address)
        deadline = self.link.deadline(self.timeouts.reply, answers=1)
        while (got := self._next(deadline, after=sent)) is not None:
            source, msg = got
            if source != address:
                continue
            if isinstance(msg, DescrDigest):
                return msg.value
            if isinstance(msg, m.Error) and \
                    msg.function == Function.MCA_DUMPIO_DESCR_REQUEST:
                return None
        return None

    def _gather(self, address: Address, wanted: set[tuple[int, int]],
                ask: list[mca.DescrRequest], parts: dict[tuple[int, int], dict[int, bytes]],
                lasts: dict[tuple[int, int], int],
                done: dict[tuple[int, int], mca.EdgeRecord]) -> None:
        """Ask with ``ask`` and collect the records of ``wanted`` into ``done``; what did
        not arrive whole is asked for again, edge by edge, twice at most."""
        for _ in range(1 + self.timeouts.retries):
            for request in ask:
                self._send(request, address)
            frames = len(wanted) * 10 if len(ask) == 1 and ask[0].kind is None \
                else 10 * len(ask)
            deadline = self.link.deadline(self.timeouts.reply, answers=frames)
            missing = wanted - done.keys()
            while missing and (got := self._next(deadline)) is not None:
                source, msg = got
                if source == address and isinstance(msg, m.Error) and \
                        msg.function == Function.MCA_DUMPIO_DESCR_REQUEST:
                    raise BoardError(f"board {address}: {msg.describe()}")
                if source != address or not isinstance(msg, mca.DescrSegment):
                    continue
                key = (msg.kind, msg.index)
                parts.setdefault(key, {})[msg.segment] = msg.data
                if msg.last:
                    lasts[key] = msg.segment
                if key in lasts and key not in done and \
                        len(parts[key]) == lasts[key] + 1:
                    raw = b"".join(parts[key][n] for n in range(lasts[key] + 1))
                    try:
                        done[key] = mca.EdgeRecord.decode(raw)
                        missing.discard(key)
                    except FrameError:
                        parts.pop(key)
                        lasts.pop(key)
            if not missing:
                return
            ask = [mca.DescrRequest(mca.Kind(k), i) for k, i in sorted(missing)]

    # ------------------------------------------------------------------ values
    def write(self, address: Address, kind: mca.Kind, index: int, raws: Sequence[int],
              records: Sequence[mca.EdgeRecord]) -> None:
        """Write raw values to consecutive edges of ``kind`` from ``index`` (CI or PAR),
        packed into as few frames as fit, each acknowledged."""
        function = Function.MCA_CONTROLLER_INPUT if kind is mca.Kind.CI else \
            Function.MCA_PARAMETER
        i = 0
        while i < len(raws):
            j, size = i, 0
            while j < len(raws) and size + records[index + j].width <= 7:
                size += records[index + j].width
                j += 1
            specs = [(records[index + n].width, records[index + n].signed)
                     for n in range(i, j)]
            data = mca.pack_values(specs, raws[i:j])
            self._ack(address, mca.EdgeWrite(kind, index + i, data), function, index + i)
            i = j

    def dump(self, address: Address, kind: mca.Kind, index: int, count: int,
             records: Sequence[mca.EdgeRecord]) -> list[int]:
        """Read back ``count`` values of ``kind`` from ``index`` (MCA Dump CI); what did
        not arrive is asked for again."""
        values: dict[int, int] = {}
        ask = [(index, count)]
        for _ in range(1 + self.timeouts.retries):
            for first, n in ask:
                self._send(mca.DumpRequest(kind, first, n), address)
            frames = sum(n for _, n in ask)
            deadline = self.link.deadline(self.timeouts.reply, answers=frames)
            while len(values) < count and (got := self._next(deadline)) is not None:
                source, msg = got
                if source != address:
                    continue
                if isinstance(msg, m.Error) and msg.function == Function.MCA_DUMP_CI:
                    raise BoardError(f"board {address}: {msg.describe()}")
                if not isinstance(msg, mca.DumpValues) or msg.kind is not kind:
                    continue
                pos, n = 0, msg.index
                while pos < len(msg.data) and n < len(records):
                    r = records[n]
                    values[n] = int.from_bytes(msg.data[pos:pos + r.width], "big",
                                               signed=r.signed)
                    pos += r.width
                    n += 1
            missing = [i for i in range(index, index + count) if i not in values]
            if not missing:
                return [values[i] for i in range(index, index + count)]
            ask = [(i, 1) for i in missing]
        raise UcomTimeoutError(f"board {address}: {count - len(values)} values of the "
                               "read-back did not arrive")

    # ------------------------------------------------------------------ cyclic
    def alive(self, address: Address = ALL) -> None:
        self._send(mca.Alive(), address)

    def send_map(self, map_no: int, data: bytes) -> None:
        """CI process data: the values of CI map ``map_no`` (not acknowledged)."""
        arb, payload = mca.encode(mca.MapFrame(Function.MCA_CONTROLLER_INPUT, map_no, data))
        self.link.send_raw(arb, payload)

    def pump(self, until: float) -> None:
        """Take what arrives until ``until`` (bus clock): SO maps into :attr:`image`,
        answers into the queue."""
        self.link.dispatcher.pump(until)


def values_of(data: bytes, records: Sequence[mca.EdgeRecord]) -> list[int]:
    """Raw values of a map's bytes, given its edges in map order."""
    return mca.unpack_values([(r.width, r.signed) for r in records], data)


MapDecoder = Callable[[bytes], list[int]]
