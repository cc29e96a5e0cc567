"""What the parts of a virtual board (programming, the bootloader's services, the started
DSP program) may use of it, and what a board is (:class:`Identity`).

A :class:`~ucom_tools.virtual.board.ucom.VirtualBoard` composes its parts and hands itself
to them as a :class:`BoardPort` (or one of its extensions); the parts depend on these
protocols only, never on the board module, so the dependencies point one way.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from ucom_tools.config.topology import Timing
from ucom_tools.virtual.bus.simbus import SimBus
from ucom_tools.virtual.hardware.fpga import ExternalMemory, VirtualFpga
from ucom_tools.virtual.programs.base import Plant
from ucom_tools.wire import mca
from ucom_tools.wire import messages as m
from ucom_tools.wire.answers import AppReport
from ucom_tools.wire.codes import BoardState, ErrorCode, Space, Target
from ucom_tools.wire.descriptor import ImageDescriptor
from ucom_tools.wire.fpga import FpgaVersion
from ucom_tools.wire.ids import Address


@dataclass(frozen=True)
class Identity:
    """What a board is, as the topology describes it."""

    position: int
    placement: str
    board: str
    serial: int
    fixed_id: int = 0
    fpga: FpgaVersion | None = None
    """The FPGA configuration; None = the one made for the plug-on board."""


class BoardPort(Protocol):
    """The services of a board: time, sending, persistence."""

    timing: Timing

    @property
    def powered(self) -> bool: ...

    def at(self, t: float, callback: Callable[[float], None]) -> None:
        """Call ``callback(t)`` at board time ``t`` (microseconds)."""

    def send(self, t: float, msg: m.BootMessage | mca.McaMessage, *,
             via_fixed: bool = False) -> None:
        """Send ``msg`` from this board at time ``t`` (if it has a number to send with)."""

    def send_raw(self, t: float, arbitration_id: int, data: bytes) -> None:
        """Send a frame with this identifier (process data, whose identifier is no board's
        address)."""

    def error(self, t: float, code: ErrorCode, function: int, detail: int = 0,
              via_fixed: bool = False) -> None:
        """Send an Error after the board's reply time."""

    def report_text(self, t: float, text: str) -> None:
        """Send a text report (channel 2)."""

    def persist(self, record_only: bool = False) -> None:
        """Write the non-volatile memory to the fleet's state directory (if any)."""

    def filters_changed(self) -> None:
        """The CI maps the board's program takes changed (its CAN controller's acceptance
        filter, :meth:`~ucom_tools.virtual.bus.simbus.SimBus.filters_changed`)."""


class ProgramHost(BoardPort, Protocol):
    """What a started DSP program sees of its board: the X: window with the FPGA, its own
    image descriptor, and the bootloader to return to."""

    @property
    def xmem(self) -> ExternalMemory: ...

    fpga: VirtualFpga
    adc: list[int]
    plant: Plant | None
    """The motors, joints and sensors behind the board (its hardware, kept across its
    programs); None until a program made one."""

    def bind_plant(self, plant: Plant, t: float) -> None:
        """A program starts driving ``plant`` at ``t``: the board's plant from before is
        resumed over the time since it last moved (:meth:`Plant.resume`), a new one
        replaces it."""

    @property
    def placement(self) -> str:
        """Where the board sits in its robot (the topology's placement)."""

    def descriptor(self, target: Target) -> ImageDescriptor | None:
        """The descriptor of the program stored in ``target`` (FrameError if corrupt)."""

    def running(self, program: object) -> bool:
        """Is ``program`` still the one the board runs?"""

    def end_program(self, t: float, *, reset: bool) -> None:
        """The program ends (back to the bootloader), with a reset if ``reset``."""


class BootloaderHost(BoardPort, Protocol):
    """What the bootloader's services (:mod:`~ucom_tools.virtual.board.bootloader`) see of
    their board: its identity, bus and init pins, its seq ID, and what it shows."""

    identity: Identity
    bus: SimBus
    seq_id: int
    in_drive: bool
    """The board sets its init input (the line from the board before it)."""
    out_drive: bool
    """The board sets its init output (the line to the board after it)."""
    stagger_us: float
    """How long after its decision the board's Init Ack goes out (from its serial number:
    boards that answer together do not all queue at once)."""
    fpga: VirtualFpga
    can_errors: int

    @property
    def state(self) -> BoardState: ...

    @property
    def runs_program(self) -> bool:
        """A DSP program runs (what only the bootloader may do is refused)."""

    def send(self, t: float, msg: m.BootMessage | mca.McaMessage, *, via_fixed: bool = False,
             address: Address | None = None) -> None:
        """Send ``msg`` at ``t``, from ``address`` if given, else from the board's own."""

    def reply_address(self, via_fixed: bool = False) -> Address | None: ...

    def application_report(self) -> AppReport | None:
        """The running program's report (channel APPLICATION); None without one."""

    def read_memory(self, space: Space, address: int, count: int) -> list[int] | None: ...

    def descriptor(self, target: Target) -> ImageDescriptor | None: ...

    def pins(self) -> dict[str, bool]: ...

    def leds(self) -> dict[str, str]: ...
