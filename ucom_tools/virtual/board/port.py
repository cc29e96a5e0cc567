"""What the parts of a virtual board (programming, the started DSP program) may use of it.

A :class:`~ucom_tools.virtual.board.ucom.VirtualBoard` composes its parts and hands itself to
them as a :class:`BoardPort`; the parts depend on this protocol only, never on the board
module, so the dependencies point one way.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

from ucom_tools.config.topology import Timing
from ucom_tools.virtual.hardware.fpga import ExternalMemory, VirtualFpga
from ucom_tools.virtual.programs.base import Plant
from ucom_tools.wire import mca
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import ErrorCode, Target
from ucom_tools.wire.descriptor import ImageDescriptor


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
