"""What a conformance case works with: one bus, its clients, the frames the case caused,
and timed requests (an answer counts with the time it took on the bus's clock)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import can

from ucom_tools.config.topology import SOURCE_ROOT
from ucom_tools.conformance.outcome import CaseFailed, Skipped
from ucom_tools.image.formats import load_image
from ucom_tools.image.model import Image
from ucom_tools.ops.robot import BusHandle
from ucom_tools.protocol.bootloader import InitResult
from ucom_tools.protocol.link import Received
from ucom_tools.protocol.mca import McaClient
from ucom_tools.protocol.programmer import Programmer
from ucom_tools.protocol.timeouts import Timeouts
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import BoardState, StatusOp, Target
from ucom_tools.wire.ids import ALL, Address, seq
from ucom_tools.wire.mca import McaReady

RUNTIME_IMAGE = SOURCE_ROOT / "firmware_images" / "armar3.fl.S"


@dataclass(frozen=True)
class Answer:
    """An answer and how long after its request it came (bus clock, seconds)."""

    got: Received
    delay: float


class Bench:
    """One bus under test."""

    def __init__(self, handle: BusHandle, timeouts: Timeouts,
                 runtime_image: Path = RUNTIME_IMAGE) -> None:
        self.handle = handle
        self.name = handle.name
        self.link = handle.link
        self.boot = handle.client
        self.timeouts = timeouts
        self.runtime_image = runtime_image
        self.frames: list[can.Message] = []
        """Every frame of the current case, received and sent."""
        self.link.dispatcher.taps.append(self.frames.append)
        self.numbers: list[int] = []
        self._mca: McaClient | None = None
        self._image: Image | None = None
        self.restarted_programs = False
        self.touched = False
        """A board may have changed: the suite reset them (the restore is due)."""

    # ------------------------------------------------------------------ time
    def clock(self) -> float:
        return self.link.clock()

    def wire(self, frames: int = 1) -> float:
        """Worst-case time ``frames`` 8-byte frames take on the bus (twice: shared bus)."""
        return 2 * self.link.wire_time(frames)

    def wait(self, seconds: float) -> list[Received]:
        """Let ``seconds`` pass on the bus clock; the bootloader-level messages that came."""
        return list(self.link.until(self.clock() + seconds))

    # ------------------------------------------------------------------ checks
    @staticmethod
    def expect(ok: bool, what: str, expected: object, got: object) -> None:
        if not ok:
            raise CaseFailed(what, expected, got)

    def skip(self, reason: str) -> None:
        raise Skipped(reason)

    # ------------------------------------------------------------------ requests
    def ask(self, msg: m.BootMessage, address: Address, *,
            answer: Callable[[Received], bool], within: float, count: int = 1,
            extra: float = 0.0) -> list[Answer]:
        """Send ``msg`` once and gather the answers ``answer`` accepts for ``within``
        seconds (the page's deadline) plus the wire time of ``count`` answers and the
        frames still queued (the deadline), and ``extra`` seconds more to see late ones."""
        sent = self.clock()
        self.link.send(msg, address)
        deadline = self.link.deadline(within, answers=count) + extra
        out = []
        for got in self.link.until(deadline):
            if answer(got):  # read as it arrives: the clock is the time it came
                out.append(Answer(got, self.clock() - sent))
        return out

    def allowed(self, within: float, count: int = 1) -> float:
        """What the page allows an answer: the board's time plus the wire."""
        return within + self.wire(count) + self.link.margin

    def ask_one(self, msg: m.BootMessage, address: Address, kind: type, *,
                within: float, what: str) -> Received:
        """The one answer of type ``kind`` from ``address``, on time (else CaseFailed)."""
        answers = self.ask(msg, address, answer=lambda g: g.address == address and
                           isinstance(g.message, kind), within=within, extra=within)
        self.expect(len(answers) >= 1, what, f"a {kind.__name__} from board {address}",
                    "no answer")
        first = answers[0]
        self.expect(first.delay <= self.allowed(within), f"{what}: answer time",
                    f"<= {self.allowed(within) * 1e3:.1f} ms",
                    f"{first.delay * 1e3:.1f} ms")
        return first.got

    # ------------------------------------------------------------------ set-up
    def reset_all(self) -> None:
        """Every board to its bootloader (XReset: a program with AutoStart would start
        again after a plain reset; the runner restores the flags at the end), seq IDs
        kept."""
        self.touched = True
        self.boot.reset(clear_autostart=True)
        self.wait(self.timeouts.reset)

    def init(self) -> InitResult:
        result = self.boot.init_chain()
        self.numbers = result.numbers
        return result

    def boards(self) -> list[int]:
        """Seq IDs of the boards (init first)."""
        if not self.numbers:
            self.init()
        if not self.numbers:
            self.skip("no board answered the init chain")
        return self.numbers

    @property
    def mca(self) -> McaClient:
        if self._mca is None:
            self._mca = McaClient(self.link, self.timeouts)
        return self._mca

    def runtime_program(self, n: int) -> McaReady:
        """Board ``n`` running the run-time test program from its external RAM (its flash
        is not touched; a reset ends it): the MCA Ready it sent when it came up."""
        if self._image is None:
            self._image = load_image(self.runtime_image)
        self.boot.set_status(seq(n), StatusOp.PROG_ENABLE, 1)
        result = Programmer(self.link, self.timeouts).transfer(
            self._image.plan(target=Target.EXTRAM), [seq(n)])
        if not result.all_verified:
            outcome = result.outcomes.get(seq(n))
            self.skip(f"board {n} does not take a program into external RAM "
                      f"({outcome.status if outcome else 'no answer'})")
        (started,) = self.boot.start(seq(n), Target.EXTRAM)
        if not started.started or started.state is not BoardState.RUNNING_EXTRAM:
            why = "; ".join(e.describe() for e in started.errors) or "it did not start"
            self.skip(f"board {n} cannot run the run-time program "
                      f"({self.runtime_image.name}): {why}")
        self.restarted_programs = True
        ready = self.mca.wait_ready(seq(n), self.timeouts.reply)
        self.expect(ready is not None, "MCA Ready after Start", "an MCA Ready", "none")
        assert ready is not None
        return ready

    def close(self) -> None:
        if self.frames.append in self.link.dispatcher.taps:
            self.link.dispatcher.taps.remove(self.frames.append)
        if self._mca is not None:
            self._mca.close()

    def broadcast(self, msg: m.BootMessage) -> None:
        self.link.send(msg, ALL)
