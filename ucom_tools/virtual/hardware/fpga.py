"""The virtual FPGA of a UCoM (dissertation B.1, B.3.2).

64 registers at X:4000-403F, decoded like the real address decoder: every X: access whose
upper 10 address bits are ``0100 0000 00`` goes to the FPGA, every other external
address to RAM.  The FPGA compares the plug-on board's Board-ID (its resistor network)
with its own; on a mismatch it enters the neutral state: inputs from the plug-on board
are ignored, its outputs are high impedance, and DSP<->FPGA access keeps working.
Six 16-bit quadrature decoders with prescalers count encoder edges and can be read and
set by the DSP program.  A channel can take an absolute sensor instead (SSI, dissertation
5.2.1: the FPGA reads a potentiometer's position; :attr:`QuadratureDecoder.absolute`):
then it shows that position, prescaled, whatever it counted before, from power-on.

:meth:`VirtualFpga.read` and :meth:`VirtualFpga.write` decode every offset.  Code that runs
every control cycle (the program models and plants) may take the short way to the same
state: the quadrature counters are ``quad[n].count``, and every offset but the read-only
ones (VERSION1/2, BOARD_ID, STATUS, DIGITAL_IN), the counters and the prescalers (so PWM0-2,
OUTPUT_ENABLE, ...) is plain storage, ``registers[offset]``, holding 16-bit values.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Final

from ucom_tools.memory import is_fpga_address
from ucom_tools.wire.fpga import QUAD_CHANNELS, FpgaVersion, Reg

# the register map as plain ints (an IntEnum member costs a lookup on every use)
_VERSION1: Final = int(Reg.VERSION1)
_VERSION2: Final = int(Reg.VERSION2)
_BOARD_ID: Final = int(Reg.BOARD_ID)
_STATUS: Final = int(Reg.STATUS)
_QUAD_COUNT0: Final = int(Reg.QUAD_COUNT0)
_QUAD_PRESCALE0: Final = int(Reg.QUAD_PRESCALE0)
_DIGITAL_IN: Final = int(Reg.DIGITAL_IN)
_OUTPUT_ENABLE: Final = int(Reg.OUTPUT_ENABLE)
_READ_ONLY: Final = frozenset((_VERSION1, _VERSION2, _BOARD_ID, _STATUS, _DIGITAL_IN))


@dataclass
class QuadratureDecoder:
    """A 16-bit up/down counter of encoder edges with a prescaler.

    With :attr:`absolute` set the channel reads an absolute sensor (SSI) instead: its
    count is the sensor's position in edges divided by the prescaler (toward zero), plus
    what the program wrote to it since (:meth:`set`: an offset, gone with the FPGA at a
    power loss); edges fed only make it read the sensor again."""

    count: int = 0
    prescale: int = 1
    _residue: int = 0
    absolute: Callable[[], int] | None = None
    """The absolute sensor's position in edges (None: a quadrature encoder, counted)."""
    _offset: int = 0

    def feed(self, edges: int) -> None:
        """Count ``edges`` encoder edges (negative = backwards), every ``prescale``-th."""
        if self.absolute is not None:
            self.reread()
            return
        total = self._residue + edges
        step = self.prescale
        if step > 1:
            counted = int(total / step)  # toward zero, so the residue keeps the sign
            self._residue = total - counted * step
        else:  # 0 and 1: every edge
            counted, self._residue = total, 0
        self.count = (self.count + counted) & 0xFFFF

    def set(self, value: int) -> None:
        self.count = value & 0xFFFF
        self._residue = 0
        if self.absolute is not None:
            self._offset = value - self._position()

    def rescale(self, prescale: int) -> None:
        """A new prescaler (0 and 1: every edge); an absolute channel reads anew with it."""
        self.prescale = max(1, prescale)
        if self.absolute is not None:
            self.reread()

    def reread(self) -> None:
        """An absolute channel's count from its sensor now."""
        self.count = (self._position() + self._offset) & 0xFFFF

    def _position(self) -> int:
        source = self.absolute
        edges = 0 if source is None else source()
        step = self.prescale
        return int(edges / step) if step > 1 else edges


@dataclass
class VirtualFpga:
    """FPGA registers of one board; ``plug_board_id`` is what its resistor network reads."""

    config: FpgaVersion
    plug_board_id: int
    registers: list[int] = field(default_factory=lambda: [0] * 64)
    quad: list[QuadratureDecoder] = field(
        default_factory=lambda: [QuadratureDecoder() for _ in range(QUAD_CHANNELS)])
    inputs: int = 0
    """Digital inputs the plug-on board presents (what a test or simulation drives)."""

    @property
    def neutral(self) -> bool:
        return self.plug_board_id != self.config.board_id

    # ------------------------------------------------------------------ DSP side
    def read(self, offset: int) -> int:
        offset &= 0x3F
        if _QUAD_COUNT0 <= offset < _QUAD_COUNT0 + QUAD_CHANNELS:
            return self.quad[offset - _QUAD_COUNT0].count
        if _QUAD_PRESCALE0 <= offset < _QUAD_PRESCALE0 + QUAD_CHANNELS:
            return self.quad[offset - _QUAD_PRESCALE0].prescale
        if offset == _VERSION1:
            return self.config.register1()
        if offset == _VERSION2:
            return self.config.register2()
        if offset == _BOARD_ID:
            return self.plug_board_id & 0x0F
        if offset == _STATUS:
            return 1 if self.neutral else 0
        if offset == _DIGITAL_IN:
            return 0 if self.neutral else self.inputs & 0xFFFF
        return self.registers[offset]

    def write(self, offset: int, value: int) -> None:
        offset &= 0x3F
        value &= 0xFFFF
        if offset in _READ_ONLY:
            return
        if _QUAD_COUNT0 <= offset < _QUAD_COUNT0 + QUAD_CHANNELS:
            self.quad[offset - _QUAD_COUNT0].set(value)
        elif _QUAD_PRESCALE0 <= offset < _QUAD_PRESCALE0 + QUAD_CHANNELS:
            self.quad[offset - _QUAD_PRESCALE0].rescale(value)
        else:
            self.registers[offset] = value

    # ------------------------------------------------------------------ plug-on side
    def encoder_edges(self, channel: int, edges: int) -> None:
        """Edges arriving from encoder ``channel``; ignored in the neutral state."""
        if not self.neutral:
            self.quad[channel].feed(edges)

    def outputs_enabled(self) -> int:
        """Which output stages drive the plug-on board (none in the neutral state)."""
        return 0 if self.neutral else self.registers[_OUTPUT_ENABLE]


class ExternalMemory:
    """X:2000-FF7F as the DSP sees it: the FPGA's window and RAM everywhere else."""

    def __init__(self, fpga: VirtualFpga) -> None:
        self.fpga = fpga
        self.ram: dict[int, int] = {}

    def read(self, address: int) -> int:
        if is_fpga_address(address):
            return self.fpga.read(address)
        return self.ram.get(address, 0)

    def write(self, address: int, value: int) -> None:
        if is_fpga_address(address):
            self.fpga.write(address, value)
        else:
            self.ram[address] = value & 0xFFFF
