"""Client for the bootloader services of ``man/ucom-protocol.7``: reset, init chain,
probes, Info, SetStatus, Start and Reports.  One instance per bus."""

from __future__ import annotations

import contextlib
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
from ucom_tools.wire.ids import ALL, Address, IdType
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
        by: dict[int, list[ChainAck]] = {}
        for a in self.acks:
            if a.fixed_id:
                by.setdefault(a.fixed_id, []).append(a)
        return {k: v for k, v in by.items() if len(v) > 1}


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

    def _replies(self, address: Address, timeout: float, reason: ReadyReason | None,
                 expect_one: bool) -> list[Reply]:
        out: list[Reply] = []
        for got in self.link.messages(timeout):
            self._absorb(got)
            msg = got.message
            wanted = isinstance(msg, m.Error) or (
                isinstance(msg, m.Ready) and (reason is None or msg.reason is reason))
            if wanted and (address.is_broadcast or got.address == address):
                assert isinstance(msg, m.Ready | m.Error)
                out.append(Reply(got.address, msg))
                if expect_one:
                    break
        return out

    # ------------------------------------------------------------------ reset
    def reset(self, address: Address = ALL, *, clear_autostart: bool = False) -> list[Reply]:
        """Reset (or XReset) and collect Ready(BOOT) from every board that has a number."""
        self.link.send(m.XReset() if clear_autostart else m.Reset(), address)
        return self._replies(address, self.timeouts.reset, ReadyReason.BOOT,
                             expect_one=not address.is_broadcast)

    # ------------------------------------------------------------------ init chain
    def init_chain(self) -> InitResult:
        """Number the boards along the init line (B.2.2); the last is found by timeout."""
        acks: list[ChainAck] = []
        self.link.send(m.InitRequest(InitOp.BEGIN), ALL)
        number = 1
        while True:
            found = False
            for got in self.link.messages(self.timeouts.init_step):
                msg = got.message
                if isinstance(msg, m.InitAck) and msg.kind is InitAckKind.ASSIGNED:
                    acks.append(ChainAck(msg.seq_id, msg.fixed_id, msg.serial,
                                         msg.bootloader_version, len(acks)))
                    if msg.seq_id == number:
                        found = True
                        break
                else:
                    self._absorb(got)
            if not found or number == 31:
                break
            number += 1
            self.link.send(m.InitRequest(InitOp.NEXT, number), ALL)
        self.link.send(m.InitRequest(InitOp.END), ALL)
        return InitResult(tuple(acks))

    def probe(self, *, last: bool = False) -> list[m.InitAck]:
        """Which board(s) see no predecessor (first) or no successor (last) on the init line."""
        op = InitOp.PROBE_LAST if last else InitOp.PROBE_FIRST
        kind = InitAckKind.LAST if last else InitAckKind.FIRST
        self.link.send(m.InitRequest(op), ALL)
        out = []
        for got in self.link.messages(self.timeouts.probe):
            if isinstance(got.message, m.InitAck) and got.message.kind is kind:
                out.append(got.message)
            else:
                self._absorb(got)
        return out

    # ------------------------------------------------------------------ info
    def info(self, address: Address) -> BoardInfo:
        """The Info record of one board."""
        infos = self.info_many(address)
        if address in infos:
            return infos[address]
        raise UcomTimeoutError(f"board {address} did not answer Info Request "
                               f"within {self.timeouts.reply * 1000:.0f} ms")

    def info_many(self, address: Address = ALL) -> dict[Address, BoardInfo]:
        """Info records of one board or, broadcast, of every board that has a number."""
        self.link.send(m.InfoRequest(), address)
        parts: dict[Address, dict[int, bytes]] = {}
        done: dict[Address, BoardInfo] = {}
        for got in self.link.messages(self.timeouts.reply):
            msg = got.message
            if isinstance(msg, m.InfoFrame):
                frames = parts.setdefault(got.address, {})
                frames[msg.index] = msg.body
                if len(frames) == INFO_FRAMES:
                    with contextlib.suppress(FrameError):
                        done[got.address] = BoardInfo.from_frames(frames)
                    if not address.is_broadcast and got.address == address:
                        break
            elif isinstance(msg, m.Error) and got.address == address:
                raise BoardError(f"board {address}: {msg.describe()}")
            else:
                self._absorb(got)
        return done

    # ------------------------------------------------------------------ commands
    def set_status(self, address: Address, op: StatusOp, value: int) -> list[Reply]:
        """Set one status item; a new seq ID is acknowledged from the new number."""
        self.link.send(m.SetStatus(op, value), address)
        expect = address
        if op is StatusOp.SEQ_ID and not address.is_broadcast:
            expect = Address(IdType.SEQUENTIAL, value)
        return self._replies(expect, self.timeouts.reply, ReadyReason.STATUS,
                             expect_one=not address.is_broadcast)

    def start(self, address: Address, target: Target = Target.FLASH) -> list[StartResult]:
        """Start a program and gather what each board says: Ready(STARTED), the program's
        compatibility verdict (Error, text reports) and a reset that may follow."""
        self.link.send(m.Start(target), address)
        seen: dict[Address, _Started] = {}
        for got in self.link.messages(self.timeouts.reply):
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
        texts = self.take_texts()
        return [StartResult(a, s.started, tuple(s.errors), tuple(texts.get(a, ())), s.state)
                for a, s in sorted(seen.items(), key=lambda kv: (kv[0].id_type, kv[0].number))]

    def status(self, address: Address) -> m.StatusReport:
        self.link.send(m.ReportRequest(ReportChannel.STATUS), address)
        for got in self.link.messages(self.timeouts.reply):
            if isinstance(got.message, m.StatusReport) and got.address == address:
                return got.message
            if isinstance(got.message, m.Error) and got.address == address:
                raise BoardError(f"board {address}: {got.message.describe()}")
            self._absorb(got)
        raise UcomTimeoutError(f"board {address} sent no status report")

    def read_memory(self, address: Address, space: Space, start: int, count: int) -> list[int]:
        self.link.send(m.ReportRequest(ReportChannel.MEMORY, space, start, count), address)
        words: dict[int, int] = {}
        for got in self.link.messages(self.timeouts.reply):
            msg = got.message
            if isinstance(msg, m.MemoryReport) and got.address == address:
                for i, w in enumerate(msg.words):
                    words[msg.address + i] = w
                if len(words) >= count:
                    break
            elif isinstance(msg, m.Error) and got.address == address:
                raise BoardError(f"board {address}: {msg.describe()}")
        if len(words) < count:
            raise UcomTimeoutError(f"board {address} sent {len(words)} of {count} words")
        return [words[start + i] for i in range(count)]

