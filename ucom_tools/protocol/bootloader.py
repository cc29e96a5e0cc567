"""Client for the bootloader services of ``man/ucom-protocol.7``: reset, init chain,
probes, Info, SetStatus, Start and Reports.  One instance per bus.

Every wait ends at a deadline derived from the work (:meth:`Link.budget`), and a request
whose answer did not come is asked again (``Timeouts.retries``): on a bus that loses
frames a lost question or answer costs a second question, not a board.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterable
from dataclasses import dataclass, field

from ucom_tools.errors import BoardError, FrameError, UcomTimeoutError
from ucom_tools.protocol.link import Link, Received
from ucom_tools.protocol.timeouts import DEFAULT, Timeouts
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import (
    BoardState,
    InitAckKind,
    InitOp,
    ReadyReason,
    ReportChannel,
    Space,
    StatusOp,
    Target,
)
from ucom_tools.wire.ids import ALL, MAX_BOARD_NUMBER, Address, IdType
from ucom_tools.wire.info import INFO_FRAMES, BoardInfo


@dataclass(frozen=True)
class ChainAck:
    """One Init Ack seen during enumeration, in the order it arrived."""

    seq_id: int
    fixed_id: int
    serial: int
    bootloader_version: int
    order: int


@dataclass(frozen=True)
class InitResult:
    """What the init chain produced on one bus."""

    acks: tuple[ChainAck, ...]

    @property
    def numbers(self) -> list[int]:
        return sorted({a.seq_id for a in self.acks})

    def duplicates(self) -> dict[int, list[ChainAck]]:
        """Seq IDs claimed by more than one board (a broken init line or unpowered board)."""
        by: dict[int, list[ChainAck]] = {}
        for a in self.acks:
            by.setdefault(a.seq_id, []).append(a)
        return {k: v for k, v in by.items() if len({x.serial for x in v}) > 1}

    def fixed_id_clashes(self) -> dict[int, list[ChainAck]]:
        by: dict[int, dict[int, ChainAck]] = {}
        for a in self.acks:
            if a.fixed_id:
                by.setdefault(a.fixed_id, {}).setdefault(a.serial, a)
        return {k: list(v.values()) for k, v in by.items() if len(v) > 1}


@dataclass(frozen=True)
class Reply:
    """A board's answer to a command: Ready or Error, plus any text reports."""

    address: Address
    message: m.Ready | m.Error
    reports: tuple[str, ...] = field(default=())

    @property
    def ok(self) -> bool:
        return isinstance(self.message, m.Ready)


@dataclass(frozen=True)
class StartResult:
    """What a board answered to Start."""

    address: Address
    started: bool
    errors: tuple[m.Error, ...]
    reports: tuple[str, ...]
    state: BoardState | None

    @property
    def ok(self) -> bool:
        return self.started and not self.errors


@dataclass
class _Started:
    """What one board has said so far after Start."""

    started: bool = False
    errors: list[m.Error] = field(default_factory=list)
    state: BoardState | None = None


def _key(a: Address) -> tuple[int, int]:
    return (a.id_type, a.number)


class BootloaderClient:
    """Bootloader services on one bus."""

    def __init__(self, link: Link, timeouts: Timeouts = DEFAULT) -> None:
        self.link = link
        self.timeouts = timeouts
        self.texts: dict[Address, list[str]] = {}
        self._text_parts: dict[Address, list[bytes]] = {}

    # ------------------------------------------------------------------ helpers
    def _absorb(self, got: Received) -> None:
        """Keep text reports that arrive between answers (program messages)."""
        if isinstance(got.message, m.TextReport):
            parts = self._text_parts.setdefault(got.address, [])
            parts.append(got.message.text)
            if got.message.last:
                text = b"".join(parts).decode("latin-1")
                self._text_parts[got.address] = []
                self.texts.setdefault(got.address, []).append(text)

    def take_texts(self, address: Address | None = None) -> dict[Address, list[str]]:
        if address is None:
            out, self.texts = self.texts, {}
            return out
        return {address: self.texts.pop(address, [])}

    def _attempts(self) -> range:
        return range(1 + self.timeouts.retries)

    def _replies(self, address: Address, board_time: float, reason: ReadyReason,
                 expect: set[Address] | None) -> dict[Address, Reply]:
        """Ready(``reason``) or Error answers to the request just sent to ``address``;
        with ``expect`` (or an addressed request) the wait ends once all have answered."""
        wanted = expect if expect is not None else (
            None if address.is_broadcast else {address})
        n = len(wanted) if wanted is not None else MAX_BOARD_NUMBER
        deadline = self.link.deadline(board_time, answers=n)
        out: dict[Address, Reply] = {}
        for got in self.link.until(deadline):
            self._absorb(got)
            msg = got.message
            fits = isinstance(msg, m.Error) or (isinstance(msg, m.Ready) and msg.reason is reason)
            if fits and (address.is_broadcast or got.address == address or
                         (wanted is not None and got.address in wanted)):
                assert isinstance(msg, m.Ready | m.Error)
                out[got.address] = Reply(got.address, msg)
                if wanted is not None and wanted <= out.keys():
                    break
        return out

    # ------------------------------------------------------------------ reset
    def reset(self, address: Address = ALL, *, clear_autostart: bool = False) -> list[Reply]:
        """Reset (or XReset) and collect Ready(BOOT) from every board that has a number;
        a board addressed alone is asked again when its answer does not come."""
        msg = m.XReset() if clear_autostart else m.Reset()
        attempts = self._attempts() if not address.is_broadcast else range(1)
        for _ in attempts:
            self.link.send(msg, address)
            got = self._replies(address, self.timeouts.reset, ReadyReason.BOOT, None)
            if got or address.is_broadcast:
                return sorted(got.values(), key=lambda r: _key(r.address))
        return []

    # ------------------------------------------------------------------ init chain
    def init_chain(self) -> InitResult:
        """Number the boards along the init line (B.2.2); the last is found by timeout.

        A step whose Init Ack does not come is asked again (BEGIN for number 1, NEXT n
        after that; a board that already holds n answers a repeated NEXT n again), so a
        lost frame does not cut the chain short; the chain has ended when no board
        answers after every retry."""
        acks: list[ChainAck] = []
        number = 1
        attempt = 0
        self.link.send(m.InitRequest(InitOp.BEGIN), ALL)
        while True:
            found = False
            deadline = self.link.deadline(self.timeouts.init_step, answers=1)
            for got in self.link.until(deadline):
                msg = got.message
                if isinstance(msg, m.InitAck) and msg.kind is InitAckKind.ASSIGNED:
                    acks.append(ChainAck(msg.seq_id, msg.fixed_id, msg.serial,
                                         msg.bootloader_version, len(acks)))
                    if msg.seq_id == number:
                        found = True
                        break
                else:
                    self._absorb(got)
            if found:
                if number == MAX_BOARD_NUMBER:
                    break
                number, attempt = number + 1, 0
            elif attempt < self.timeouts.retries:
                attempt += 1
            else:
                break
            self.link.send(m.InitRequest(InitOp.NEXT, number) if number > 1
                           else m.InitRequest(InitOp.BEGIN), ALL)
        self.link.send(m.InitRequest(InitOp.END), ALL)
        return InitResult(tuple(acks))

    def rejoin(self, number: int, serial: int, wait: float | None = None,
               ) -> m.InitAck | None:
        """Init Request REJOIN (INIT CHAIN, Rejoin): the board with ``serial`` takes seq ID
        ``number`` without an init chain; its Init Ack ASSIGNED, or None when it did not
        answer within ``wait`` (the reply time when None) and the transport's margin.
        Asked once: a board that is away is asked again at the caller's pace."""
        self.link.send(m.InitRequest(InitOp.REJOIN, number, serial), ALL)
        deadline = self.link.deadline(self.timeouts.reply if wait is None else wait,
                                      answers=1)
        for got in self.link.until(deadline):
            msg = got.message
            if isinstance(msg, m.InitAck) and msg.kind is InitAckKind.ASSIGNED and \
                    msg.seq_id == number and msg.serial == serial:
                return msg
            self._absorb(got)
        return None

    def probe(self, *, last: bool = False) -> list[m.InitAck]:
        """Which board(s) see no predecessor (first) or no successor (last) on the init line."""
        op = InitOp.PROBE_LAST if last else InitOp.PROBE_FIRST
        kind = InitAckKind.LAST if last else InitAckKind.FIRST
        self.link.send(m.InitRequest(op), ALL)
        out: dict[int, m.InitAck] = {}
        deadline = self.link.deadline(self.timeouts.probe, answers=MAX_BOARD_NUMBER)
        for got in self.link.until(deadline):
            if isinstance(got.message, m.InitAck) and got.message.kind is kind:
                out.setdefault(got.message.serial, got.message)
            else:
                self._absorb(got)
        return list(out.values())

    # ------------------------------------------------------------------ info
    def info(self, address: Address) -> BoardInfo:
        """The Info record of one board."""
        infos = self.info_many(address)
        if address in infos:
            return infos[address]
        raise UcomTimeoutError(f"board {address} did not answer Info Request "
                               f"({1 + self.timeouts.retries} times asked)")

    def info_many(self, address: Address = ALL, *,
                  expect: Iterable[Address] = ()) -> dict[Address, BoardInfo]:
        """Info records of one board or, broadcast, of every board that has a number.

        Boards in ``expect`` (and any board whose record arrived incomplete) that did
        not deliver a whole record are asked again, each on its own; the frames of the
        answers add up, so on a lossy bus each answer only has to fill the gaps."""
        wanted = set(expect) if address.is_broadcast else {address}
        parts: dict[Address, dict[int, bytes]] = {}
        done: dict[Address, BoardInfo] = {}
        ask: list[Address] = [address]
        for attempt in self._attempts():
            for a in ask:
                self.link.send(m.InfoRequest(), a)
            if address.is_broadcast and attempt == 0:
                answers = INFO_FRAMES * max(len(wanted), MAX_BOARD_NUMBER)
                target = None
            else:
                answers = INFO_FRAMES * len(ask)
                target = set(ask)
            deadline = self.link.deadline(self.timeouts.reply, answers=answers)
            for got in self.link.until(deadline):
                msg = got.message
                if isinstance(msg, m.InfoFrame):
                    if not (address.is_broadcast or got.address == address):
                        continue
                    frames = parts.setdefault(got.address, {})
                    frames[msg.index] = msg.body  # a later answer's frame wins
                    if len(frames) == INFO_FRAMES and got.address not in done:
                        with contextlib.suppress(FrameError):
                            done[got.address] = BoardInfo.from_frames(frames)
                    if target is not None and target <= done.keys():
                        break
                elif isinstance(msg, m.Error) and got.address == address and \
                        msg.function == m.InfoRequest.FUNCTION:
                    raise BoardError(f"board {address}: {msg.describe()}")
                else:
                    self._absorb(got)
            ask = sorted((wanted | parts.keys()) - done.keys(), key=_key)
            if not ask:
                break
            # the frames that did arrive are kept: the next answer fills the gaps
        return done

    # ------------------------------------------------------------------ commands
    def set_status(self, address: Address, op: StatusOp, value: int, *,
                   expect: Iterable[Address] = ()) -> list[Reply]:
        """Set one status item; a new seq ID is acknowledged from the new number.

        An addressed request (and, broadcast, every board in ``expect``) is asked again
        when its answer does not come; SetStatus is idempotent.  A new seq ID is not asked
        again (the board may have taken it): check with Info at the new number."""
        if op is StatusOp.SEQ_ID and not address.is_broadcast:
            self.link.send(m.SetStatus(op, value), address)
            new = Address(IdType.SEQUENTIAL, value)
            got = self._replies(new, self.timeouts.reply, ReadyReason.STATUS, {new})
            return list(got.values())
        wanted = set(expect) if address.is_broadcast else {address}
        self.link.send(m.SetStatus(op, value), address)
        out = self._replies(address, self.timeouts.reply, ReadyReason.STATUS, wanted or None)
        for _ in range(self.timeouts.retries):
            ask = sorted(wanted - out.keys(), key=_key)
            if not ask:
                break
            for a in ask:
                self.link.send(m.SetStatus(op, value), a)
            got = self._replies(ALL, self.timeouts.reply, ReadyReason.STATUS, set(ask))
            out.update({a: r for a, r in got.items() if a in ask})
        return sorted(out.values(), key=lambda r: _key(r.address))

    def start(self, address: Address, target: Target = Target.FLASH) -> list[StartResult]:
        """Start a program and gather what each board says: Ready(STARTED), the program's
        compatibility verdict (Error, text reports) and a reset that may follow.  A board
        started alone is asked again when nothing came back (a repeated Start to a running
        program is answered Ready(STARTED) again)."""
        seen: dict[Address, _Started] = {}
        attempts = self._attempts() if not address.is_broadcast else range(1)
        for _ in attempts:
            self.link.send(m.Start(target), address)
            board_time = self.timeouts.reply + self.timeouts.startup + self.timeouts.reset
            deadline = self.link.deadline(board_time, answers=2 * MAX_BOARD_NUMBER)
            for got in self.link.until(deadline):
                self._absorb(got)
                msg = got.message
                if not (address.is_broadcast or got.address == address):
                    continue
                if isinstance(msg, m.Ready) and msg.reason in (ReadyReason.STARTED,
                                                               ReadyReason.BOOT):
                    s = seen.setdefault(got.address, _Started())
                    s.started |= msg.reason is ReadyReason.STARTED
                    s.state = msg.state
                elif isinstance(msg, m.Error):
                    s = seen.setdefault(got.address, _Started())
                    s.errors.append(msg)
                    if s.started:
                        s.state = BoardState.BOOTLOADER  # the program ended or aborted
            if seen:
                break
        texts = self.take_texts()
        return [StartResult(a, s.started, tuple(s.errors), tuple(texts.get(a, ())), s.state)
                for a, s in sorted(seen.items(), key=lambda kv: _key(kv[0]))]

    def status(self, address: Address) -> m.StatusReport:
        for _ in self._attempts():
            self.link.send(m.ReportRequest(ReportChannel.STATUS), address)
            deadline = self.link.deadline(self.timeouts.reply, answers=1)
            for got in self.link.until(deadline):
                if isinstance(got.message, m.StatusReport) and got.address == address:
                    return got.message
                if isinstance(got.message, m.Error) and got.address == address:
                    raise BoardError(f"board {address}: {got.message.describe()}")
                self._absorb(got)
        raise UcomTimeoutError(f"board {address} sent no status report "
                               f"({1 + self.timeouts.retries} times asked)")

    def read_memory(self, address: Address, space: Space, start: int, count: int) -> list[int]:
        words: dict[int, int] = {}
        for _ in self._attempts():
            self.link.send(m.ReportRequest(ReportChannel.MEMORY, space, start, count), address)
            deadline = self.link.deadline(self.timeouts.reply,
                                          answers=m.memory_report_frames(count))
            for got in self.link.until(deadline):
                msg = got.message
                if isinstance(msg, m.MemoryReport) and got.address == address:
                    for i, w in enumerate(msg.words):
                        words[msg.address + i] = w
                    if all(start + i in words for i in range(count)):
                        return [words[start + i] for i in range(count)]
                elif isinstance(msg, m.Error) and got.address == address:
                    raise BoardError(f"board {address}: {msg.describe()}")
        raise UcomTimeoutError(f"board {address} sent {len(words)} of {count} words")
