"""The contract between a virtual board's run-time and the DSP program model it runs.

The run-time (:mod:`ucom_tools.virtual.board.runtime`) owns the CAN side: it decodes MCA
messages, range-checks values, keeps the process-data maps, the watchdog and the LEDs.
A program model owns the control: the edges' raw values (per kind, in the order of its
:class:`~ucom_tools.edgelists.model.ProgramSpec`), one control cycle at a time, and the
hardware it drives through the board's FPGA (PWM, output enables, quadrature counters)
and ADC.  Models never read a clock: time is what :meth:`ProgramModel.step` is given.
"""

from __future__ import annotations

from typing import Protocol

from ucom_tools.edgelists.model import ProgramSpec
from ucom_tools.virtual.hardware.fpga import VirtualFpga


class Hardware(Protocol):
    """What a program reaches of its board: the FPGA (X:4000-403F) and the 8 ADC channels
    (12 bit, 0..4095 for 0..3.3 V)."""

    fpga: VirtualFpga
    adc: list[int]


class ProgramModel(Protocol):
    """A running DSP program."""

    spec: ProgramSpec
    ci: list[int]
    """Raw CI values, indexed per kind; the run-time writes them (range-checked)."""
    so: list[int]
    """Raw SO values; the model updates them every cycle, the run-time reads them."""
    par: list[int]
    """Raw PAR values; the run-time writes them; a change takes effect at the next cycle."""

    def loop_us(self) -> float:
        """The cycle time the program is configured for (its LoopTime parameter)."""

    def step(self, dt_us: float) -> float:
        """Run one control cycle, ``dt_us`` after the previous one; returns the modelled
        execution time of the cycle in microseconds (the board's load)."""

    def stop(self) -> None:
        """Safe stop: every output stage off, PWM 0, controllers off and reset.  The model
        stays stopped (every later :meth:`step` only senses) until :meth:`release`."""

    def release(self) -> None:
        """Allow control again (the exchange was started explicitly)."""


class Plant(Protocol):
    """The physical world behind a board's FPGA: motors, gears, loads, sensors.  It is the
    board's (its hardware): a program that starts again gets the plant the last one left,
    resumed (:meth:`resume`)."""

    fpga: VirtualFpga

    def advance(self, dt_us: float) -> None:
        """Let ``dt_us`` microseconds pass: read PWM and output enables from the FPGA,
        integrate the mechanics, feed the encoders' edges to the FPGA's quadrature
        counters and set the ADC readings."""

    def resume(self, fpga: VirtualFpga, adc: list[int], dead_us: float) -> None:
        """A program starts on the board ``dead_us`` after the plant last moved with one:
        the joints coast over that time with every output stage off; on a new ``fpga``
        (the board lost power meanwhile) nothing was counted, the motor encoders count
        from 0 and the joint sensors read the joints' positions (absolute)."""
