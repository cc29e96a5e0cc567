"""What a flash is asked (:class:`FlashRequest`) and what it says it did
(:class:`FlashResult`: per bus, per board), and where an interrupt can find it
(:data:`PHASES`).

The request is one value, frozen and keyword-only past the image, so that a caller
names every switch it turns (``init``, ``autostart``, ``start``, ``verify``, ``force``);
:func:`ucom_tools.ops.flash.flash` carries it out.  The results are facts: an outcome, the
ProgID read back, what an interrupt left (:mod:`ucom_tools.ops.leave`); the CLI words them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import KW_ONLY, dataclass, field

from ucom_tools.errors import InputError
from ucom_tools.image.model import Image
from ucom_tools.ops import leave
from ucom_tools.ops.enumerate import BusEnumeration
from ucom_tools.ops.robot import BusHandle
from ucom_tools.wire.codes import Target
from ucom_tools.wire.info import BoardInfo
from ucom_tools.wire.transfer import TransferPlan

ProgressFn = Callable[[str, int, int, int], None]
"""progress(bus, bytes sent, bytes total, boards)"""

LISTENING = "listening"
KEEP = "reading the values to keep"
RESET = "reset"
INIT = "init chain"
XRESET = "XReset"
ENABLE = "ProgEnable"
ERASE = "erase"
TRANSFER = "transfer"
VERIFICATION = "verification"
AUTOSTART = "AutoStart"
START = "start"
FINISHED = "finished"
NOT_BEGUN = "not begun"
PHASES = (NOT_BEGUN, LISTENING, KEEP, RESET, INIT, XRESET, ENABLE, ERASE, TRANSFER,
          VERIFICATION, AUTOSTART, START, FINISHED)
"""Where an interrupt can find a flash on a bus, in order (``not begun``: another bus's
job was interrupted first; ``finished``: the job was done when it saw the interrupt);
listening, reading the values to keep (``--keep-params``) and the reset are ``ucom
flash``'s, before the job."""



@dataclass(frozen=True)
class Selection:
    """Which boards to program: every board found, the ProgEnabled ones, or seq IDs."""

    kind: str  # "all" | "enabled" | "list"
    numbers: tuple[int, ...] = ()

    @classmethod
    def parse(cls, text: str) -> Selection:
        if text.strip().lower() == "all":
            return cls("all")
        try:
            nums = tuple(sorted({int(x) for x in text.split(",") if x.strip()}))
        except ValueError:
            raise InputError(f"{text!r}: expected 'all' or seq IDs like 1,3,5",
                             key="boards") from None
        if not nums or not all(1 <= n <= 31 for n in nums):
            raise InputError(f"{text!r}: seq IDs are 1-31", key="boards")
        return cls("list", nums)

@dataclass(frozen=True)
class FlashRequest:
    """A flash to do: ``image`` into the ``selection`` of every bus (``bus``: one), into
    ``target`` memory.

    ``init``: run the init chain first (else the boards keep the seq IDs they have);
    ``autostart``/``start``: set AutoStart on / start every verified board; ``verify``:
    read back each verified board's Info; ``force``: program boards the image does not
    fit (:func:`~ucom_tools.ops.compat.compare`); ``plan``: the transfer, when the caller
    made it (else the image's, made now)."""

    image: Image
    _: KW_ONLY
    selection: Selection = Selection("all")
    bus: str | None = None
    target: Target = Target.FLASH
    init: bool = True
    autostart: bool = False
    start: bool = False
    verify: bool = True
    force: bool = False
    plan: TransferPlan | None = None

    def transfer(self) -> TransferPlan:
        """The transfer plan: the one given, or the image's for :attr:`target`."""
        return self.plan or self.image.plan(target=self.target)


@dataclass(frozen=True)
class BoardResult:
    bus: str
    seq_id: int
    """0 for a board the topology expects that never answered (outcome "missing")."""
    serial: int | None
    placement: str | None
    outcome: str  # "verified" | "failed"
    progid: int | None
    detail: str
    resent_frames: int = 0
    """Data frames this board lacked after a round and that were sent again."""
    autostart: bool = False
    started: bool | None = None
    messages: tuple[str, ...] = ()
    warnings: tuple[str, ...] = ()
    left: BoardInfo | None = None
    """After an interrupt: the board's Info as the job left it (None: not read)."""

    @property
    def verified(self) -> bool:
        return self.outcome == "verified"


@dataclass(frozen=True)
class BusFlash:
    bus: str
    boards: tuple[BoardResult, ...]
    enumeration: BusEnumeration | None
    frames: int
    rounds: int
    note: str = ""
    resent_frames: int = 0
    interrupted: str = ""
    """The phase (:data:`PHASES`) an interrupt found the job in on this bus ("": none)."""


@dataclass(frozen=True)
class FlashResult:
    image: str
    progid: int
    size_words: int
    target: Target
    buses: tuple[BusFlash, ...] = field(default=())

    @property
    def boards(self) -> list[BoardResult]:
        return [b for bus in self.buses for b in bus.boards]

    @property
    def all_verified(self) -> bool:
        return bool(self.boards) and all(b.verified for b in self.boards)

    @property
    def failed(self) -> list[BoardResult]:
        """Boards not verified, or verified but not started although a start was asked."""
        return [b for b in self.boards if not b.verified or b.started is False]

    @property
    def interrupted(self) -> bool:
        return any(bus.interrupted for bus in self.buses)


class FlashInterrupted(KeyboardInterrupt):
    """A flash ended by an interrupt (Ctrl-C, SIGTERM, SIGHUP, its cancel event) after it
    put every bus's boards back; :attr:`result` says per board what it was left with
    (outcomes of :mod:`ucom_tools.ops.leave`, the Info in ``left``) and per bus in which
    phase the interrupt came.  Raised from the interrupt (``__cause__``: its signal)."""

    def __init__(self, result: FlashResult) -> None:
        super().__init__("flash interrupted")
        self.result = result



def at_phase(phase: str) -> str:
    """Where an interrupt came, in words: "while listening", "at the erase", "before the
    job began", "after the job was done"."""
    if phase in (LISTENING, KEEP):
        return f"while {phase}"
    if phase == NOT_BEGUN:
        return "before the job began"
    if phase == FINISHED:
        return "after the job was done"
    return f"at the {phase}"


def not_begun(h: BusHandle, phase: str) -> BusFlash:
    """Bus ``h`` when an interrupt came before the job sent it anything that changes a
    board's program or ProgEnable (``phase``: listening, the reset, the init chain, or
    :data:`NOT_BEGUN`): the boards its topology expects, each kept as found, unread."""
    boards = h.expected.boards if h.expected is not None else ()
    when = f"interrupted {at_phase(phase)} on {h.name}"
    what = ("its program as found, not erased, not ProgEnabled (the reset restarted it "
            "where AutoStart is set, else it waits in its bootloader)" if phase == RESET
            else "as found: nothing that changes its program or ProgEnable was sent")
    rows = tuple(BoardResult(h.name, 0, spec.serial if spec.serial_explicit or h.virtual
                             else None, spec.placement, leave.KEPT, None, f"{what} ({when})")
                 for spec in boards)
    return BusFlash(h.name, rows, None, 0, 0, "nothing programmed", interrupted=phase)

