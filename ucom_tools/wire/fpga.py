"""FPGA version registers (dissertation B.3.2, Tab. B.5 and B.6) and the register map.

Version register 1: bits 15-14 IKL, 13-7 App-ID, 6-5 IKH, 4 = 0, 3-0 Board-ID.
Version register 2: bits 15-10 major, 9-4 minor, 3-0 unused (written as 0, ignored).
The FPGA's 64 registers appear at X:4000-403F (B.1); their use is ours to define and is
listed in ``man/ucom-protocol.7``.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

from ucom_tools.errors import FrameError

FPGA_BASE = 0x4000
FPGA_REGISTERS = 64
QUAD_CHANNELS = 6


class Reg(IntEnum):
    """FPGA registers (offsets from X:4000)."""

    VERSION1 = 0x00
    VERSION2 = 0x01
    BOARD_ID = 0x02
    """Measured Board-ID of the plug-on board (bits 3-0, read only)."""
    STATUS = 0x03
    """Bit 0: neutral state (Board-ID mismatch); read only."""
    QUAD_COUNT0 = 0x08
    """0x08-0x0D: 16-bit quadrature counters 0-5; writing sets the counter."""
    QUAD_PRESCALE0 = 0x10
    """0x10-0x15: prescaler of counter 0-5 (count every n-th edge; 0 and 1 = every)."""
    QUAD_MODE = 0x16
    """Bit n: channel n reads an SSI sensor instead of the quadrature decoder."""
    PWM0 = 0x20
    """0x20-0x22: PWM duty of motor stage 0-2 (outputs to the plug-on board)."""
    OUTPUT_ENABLE = 0x23
    """Bit n: output stage n enabled (high impedance in the neutral state)."""
    DIGITAL_OUT = 0x24
    """Digital outputs / valves (high impedance in the neutral state)."""
    DIGITAL_IN = 0x28
    """Digital inputs of the plug-on board (read as 0 in the neutral state)."""


def _check(field: str, value: int, bits: int) -> None:
    if not 0 <= value < (1 << bits):
        raise FrameError(field, f"must fit {bits} bits (0..{(1 << bits) - 1}), got {value}")


@dataclass(frozen=True, slots=True)
class FpgaVersion:
    """The identity an FPGA configuration carries in its two version registers."""

    board_id: int
    app_id: int
    major: int
    minor: int
    ikl: int = 0
    ikh: int = 0

    def __post_init__(self) -> None:
        _check("Board-ID", self.board_id, 4)
        _check("App-ID", self.app_id, 7)
        _check("major version", self.major, 6)
        _check("minor version", self.minor, 6)
        _check("IKL", self.ikl, 2)
        _check("IKH", self.ikh, 2)

    def register1(self) -> int:
        return (self.ikl << 14) | (self.app_id << 7) | (self.ikh << 5) | self.board_id

    def register2(self) -> int:
        return (self.major << 10) | (self.minor << 4)

    @classmethod
    def decode(cls, register1: int, register2: int) -> FpgaVersion:
        _check("version register 1", register1, 16)
        _check("version register 2", register2, 16)
        if register1 & 0x10:
            raise FrameError("version register 1", "bit 4 must be 0")
        return cls(board_id=register1 & 0x0F, app_id=(register1 >> 7) & 0x7F,
                   major=register2 >> 10, minor=(register2 >> 4) & 0x3F,
                   ikl=register1 >> 14, ikh=(register1 >> 5) & 0x03)

    @property
    def version(self) -> str:
        return f"{self.major}.{self.minor}"
