"""Model of ``armar3.fl.S``: three cascaded position-velocity controllers (dissertation 5.2.2,
5.4.2, B.5) on a virtual UCoM, for :data:`ucom_tools.edgelists.armar3.SPEC`.

The dissertation fixes the structure (a cascade with settable PID gains for both parts,
1 kHz, Target = target position); everything below is our definition.

Sensing, every cycle, axis k (Motor A/B/C = 0/1/2):

- the FPGA's 16-bit counters 2k (joint sensor) and 2k+1 (motor encoder) are read; bit n of
  ``Revert Encoder CountDir(BitMask)`` negates counter n.  The program extends each
  counter to an unbounded position by adding the wrapped 16-bit difference every cycle,
  so a counter may wrap around.  ``Encoder n`` reports the (negated) counter as signed
  16 bit.  Positions, targets and limits are joint-sensor counts.
- ``Encoder Prescaler(BitMask)``: bits 4k..4k+3 are motor k's prescaler, written to both
  of its counters (QUAD_PRESCALE 2k and 2k+1) whenever the field changes; 0 and 1 = every
  edge.
- Velocity (counts/s) from the joint counter: the count difference over the time since the
  last change of the count (plain differencing at speed, a period measurement at low
  speed: at most one count per elapsed time while the count stands still), then a
  first-order low-pass of :data:`VELOCITY_FILTER_US`.  ``Velocity X`` reports it.

Control of axis k by ``MotorX Command`` (:class:`~ucom_tools.edgelists.armar3.Command`),
gains = raw * 1e-6, sums and differences per cycle (discrete PID ``u = P e + I sum(e) +
D (e - e_prev)``; so I / T_loop is the continuous integral gain):

- POSITION: position error e = clamp(Target, Min, Max Position) - position [counts];
  velocity command = P e + I sum(e) + D de + feedforward gain * TargetVel [counts/s],
  clamped to +-v_max; v_max [counts/s] = ``Max Velocity (x1000)`` x 1000 (its unit is
  1000 counts/s, whatever the cycle time).  Inner loop: PWM = VP ev + VI sum(ev)
  + VD dev on ev = velocity command - velocity [counts/s], clamped to +-``Max PWM``
  [1/16000].  Anti-windup: a sum does not grow while its loop saturates in the error's
  direction; with I = 0 the sum is held at 0.
- VELOCITY: velocity command = clamp(TargetVel, +-v_max), then bounded by the position
  limits: at most max(0, g (Max - position)) and at least min(0, g (Min - position)),
  g = min(P, :data:`LIMIT_APPROACH_PER_S`) (with P = 0: 0 at or beyond the limit), so the
  axis brakes into a limit gently enough for the velocity loop to follow and never drives
  beyond it; the inner loop as above.
- HOMING (on entering it): drive open loop at ``Reset X PWM`` (clamped to Max PWM) until
  the joint counter moves by at most :data:`STALL_COUNTS` for :data:`STALL_US` while the
  current sense (ADC channel k) reads at least :data:`STALL_CURRENT_MV` (the end stop: a
  motor that does not turn although current flows; a stage that does not drive, e.g. in
  the FPGA's neutral state, is no stall); then counter 2k := Reset Offset, ``Reset
  Answer`` 2, and hold that position (the position loop, targets not clamped) while
  Command stays HOMING.  Reset Answer: 0 never homed, 1 homing, 2 homed, -1 failed (no
  stall within :data:`HOMING_TIMEOUT_US`, Reset PWM 0, or aborted by another Command or
  by stop(); the axis then holds where it is).  The motor counter is left alone.  To home
  again, set another Command, then HOMING.
- OFF: PWM 0, output stage disabled.

stop() writes PWM 0 and OUTPUT_ENABLE 0 at once, clears every sum and aborts homing; until
release() every cycle only senses and reports (the axes count as OFF, Settled 0).  After
release() every axis enters its Command afresh; an axis whose Command is still HOMING holds
its position instead of homing again.

``Set Joint Moving Direction(BitMask)`` bit k negates the PWM written to PWM0+k (the
program's positive PWM must raise its positive counts).  Every entered mode starts with
cleared sums.  OUTPUT_ENABLE bit k is set in every mode but OFF.  PAR and CI values are
read every cycle: a change acts in the next cycle.  ``Send Command via serial`` is ignored.

``Motor X Settled`` is 1 while a position loop runs (POSITION, or HOMING once homed) and
|target - position| <= :data:`SETTLED_COUNTS` and |velocity| <= :data:`SETTLED_SPEED` have
held for :data:`SETTLED_US`; else 0.  ``Voltage X`` is ADC channel k in mV (the current
sense, 0..3300), ``AD Channel 6/7`` the raw ADC channels 6 and 7.

Load (:meth:`Armar3Model.step`): :data:`BASE_US` = 100 us per cycle (MCA loop,
administration, communication: "circa 100 us", 10 % at 1 ms, 5.4.2) plus :data:`AXIS_US`
= 200 us per axis whose mode is not OFF: three axes 700 us fit in 1 ms; one axis 300 us
fits a 3 kHz cycle (333 us).

The axis's controller (constants, sensing, the cascade, homing, Settled) is
:mod:`ucom_tools.virtual.programs.armar3_axis`; this module holds the program around the
three axes and its plant.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

from ucom_tools.edgelists.armar3 import AXES, SPEC, Command
from ucom_tools.edgelists.model import EdgeKind, ProgramSpec
from ucom_tools.virtual.hardware.plant import (
    ANALOG_INPUTS_V,
    ARMAR3_BOARD,
    MAX_AXES,
    AxisParams,
    ThreeAxisPlant,
)
from ucom_tools.virtual.programs.armar3_axis import (  # the constants re-exported
    AXIS_US,
    BASE_US,
    HOMED,
    HOMING,
    HOMING_FAILED,
    HOMING_TIMEOUT_US,
    LIMIT_APPROACH_PER_S,
    NEVER_HOMED,
    PAR_INDEX,
    SETTLED_COUNTS,
    SETTLED_SPEED,
    SETTLED_US,
    SO_INDEX,
    STALL_COUNTS,
    STALL_CURRENT_MV,
    STALL_US,
    STANDSTILL_US,
    VELOCITY_FILTER_US,
    Axis,
    AxisConfig,
)
from ucom_tools.virtual.programs.base import Hardware, Plant
from ucom_tools.wire.fpga import Reg

__all__ = ["AXIS_US", "BASE_US", "HOMED", "HOMING", "HOMING_FAILED", "HOMING_TIMEOUT_US",
           "LIMIT_APPROACH_PER_S", "NEVER_HOMED", "SETTLED_COUNTS", "SETTLED_SPEED",
           "SETTLED_US", "SPEC", "STALL_COUNTS", "STALL_CURRENT_MV", "STALL_US",
           "STANDSTILL_US", "VELOCITY_FILTER_US", "Armar3Model", "make"]

_N_AXES: Final = len(AXES)
_AD_CHANNEL6: Final = SO_INDEX["AD Channel 6"]
_AD_CHANNEL7: Final = SO_INDEX["AD Channel 7"]
_CMD_OFF: Final = int(Command.OFF)
# the registers as plain ints (an IntEnum member costs a lookup on every use)
_PWM0: Final = int(Reg.PWM0)
_OUTPUT_ENABLE: Final = int(Reg.OUTPUT_ENABLE)
_QUAD_PRESCALE0: Final = int(Reg.QUAD_PRESCALE0)


@dataclass(frozen=True, slots=True)
class _Quiet:
    """A cycle that left every axis as it found it but for two clocks: the time since the
    count last changed (``since_us``) and Settled's time (``settled_us``).

    The cycle is a function of the axes' state and its inputs (the counters, CI, the ADC,
    dt, stopped or not; PAR through the configuration).  With the same inputs again the
    next cycle repeats it exactly, because neither clock can change a branch here:
    ``since_us`` only matters once the count moves or while a velocity is left (there is
    none: :meth:`Axis.at_rest`), and ``settled_us`` only while it has not reached
    :data:`SETTLED_US` (so it is 0, or Settled is 1 already).  So such a cycle only adds
    dt to the clocks that the full one adds it to, and writes the same PWM, output
    enables and SO values (as they are)."""

    counts: tuple[int, ...]
    ci: list[int]
    adc: list[int]
    so: list[int]
    dt_us: float
    control: bool
    settling: tuple[bool, ...]
    """Per axis: the cycle adds dt to ``settled_us`` (else it holds it at 0)."""
    registers: tuple[int, ...]
    """PWM0..2 and OUTPUT_ENABLE as the cycle wrote them."""
    work: float


class Armar3Model:
    """``armar3.fl.S`` on a virtual board: implements
    :class:`~ucom_tools.virtual.programs.base.ProgramModel` for
    :data:`ucom_tools.edgelists.armar3.SPEC`."""

    def __init__(self, hardware: Hardware) -> None:
        self.spec: ProgramSpec = SPEC
        self.hw = hardware
        self.ci = [e.default for e in SPEC.of(EdgeKind.CI)]
        self.so = [e.default for e in SPEC.of(EdgeKind.SO)]
        self.par = [e.default for e in SPEC.of(EdgeKind.PAR)]
        self.axes = [Axis(k) for k in range(len(AXES))]
        self._prescalers: list[int | None] = [None] * len(AXES)
        self._par_seen: list[int] | None = None
        """The PAR values the configuration was derived from."""
        self._configs: list[AxisConfig] = []
        self._stopped = False
        self._resumed = False
        self._quiet: _Quiet | None = None
        """The last cycle, if the next one with the same inputs repeats it."""

    # ------------------------------------------------------------------ ProgramModel
    def loop_us(self) -> float:
        return float(self.par[PAR_INDEX["LoopTime(ms)"]])  # exponent -3 ms: raw = us

    def step(self, dt_us: float) -> float:
        if self.par != self._par_seen:
            self._configure()
        quiet = self._quiet
        hw = self.hw
        counters = hw.fpga.quad
        if quiet is not None:
            if (not self._resumed and dt_us == quiet.dt_us
                    and tuple([q.count for q in counters]) == quiet.counts
                    and self.ci == quiet.ci and hw.adc == quiet.adc and self.so == quiet.so
                    and self._stopped != quiet.control):
                return self._repeat(quiet)
            self._quiet = None
        # the cycle could repeat itself: compare the state before and after
        check = dt_us > 0 and not self._resumed
        for a in self.axes:  # (a loop: a moving axis ends it at once)
            if a.value != 0.0 or not a.at_rest():
                check = False
                break
        if check:
            counts = tuple([q.count for q in counters])
            ci, adc = list(self.ci), list(hw.adc)
            before = [a.state() for a in self.axes]
        work = self._cycle(dt_us)
        if check and [a.state() for a in self.axes] == before and all(
                [a.settled or a.settled_us == 0.0 for a in self.axes]):
            registers = hw.fpga.registers
            self._quiet = _Quiet(
                counts, ci, adc, list(self.so), dt_us, not self._stopped,
                tuple([a.settled_us != 0.0 for a in self.axes]),
                (*registers[_PWM0:_PWM0 + _N_AXES], registers[_OUTPUT_ENABLE]),
                work)
        return work

    def _repeat(self, quiet: _Quiet) -> float:
        """The cycle again with the same inputs (:class:`_Quiet`)."""
        dt_us = quiet.dt_us
        axes, settlings = self.axes, quiet.settling  # (index loops, no zip: see compiled.py)
        for k in range(len(axes)):
            a = axes[k]
            a.since_us = a.since_us + dt_us
            if settlings[k]:
                a.settled_us += dt_us
                a.settled = a.settled_us >= SETTLED_US
        registers = self.hw.fpga.registers
        *pwms, enable = quiet.registers
        for k, pwm in enumerate(pwms):
            registers[_PWM0 + k] = pwm
        registers[_OUTPUT_ENABLE] = enable
        return quiet.work

    def _cycle(self, dt_us: float) -> float:
        hw = self.hw
        fpga = hw.fpga
        counters, registers = fpga.quad, fpga.registers
        ci, so, adc = self.ci, self.so, hw.adc
        control = not self._stopped
        resumed = self._resumed
        enable = active = 0
        axes, configs = self.axes, self._configs  # one per axis (_configure)
        for i in range(len(axes)):
            a, c = axes[i], configs[i]
            pwm = a.cycle(hw, counters, c, ci, so, adc, dt_us, control, resumed)
            if control:
                k = a.k
                registers[_PWM0 + k] = pwm & 0xFFFF  # as VirtualFpga.write(PWM0 + k, pwm)
                if a.command != _CMD_OFF:
                    enable |= 1 << k
            if a.active:
                active += 1
        if control:
            registers[_OUTPUT_ENABLE] = enable
            self._resumed = False
        else:
            self._outputs_off()
        so[_AD_CHANNEL6] = adc[6] & 0xFFF
        so[_AD_CHANNEL7] = adc[7] & 0xFFF
        return BASE_US + AXIS_US * active

    def stop(self) -> None:
        self._quiet = None
        self._stopped = True
        for a in self.axes:
            a.stop()
        self._outputs_off()

    def release(self) -> None:
        if self._stopped:
            self._quiet = None
            self._stopped, self._resumed = False, True

    # ------------------------------------------------------------------ one cycle
    def _configure(self) -> None:
        """Derive every axis's :class:`AxisConfig` from PAR and set the prescalers (in the
        first cycle and whenever a PAR value differs from the last cycle's)."""
        self._quiet = None
        self._par_seen = list(self.par)
        self._configs = [self._config(name, k) for k, name in enumerate(AXES)]
        self._write_prescalers()

    def _config(self, name: str, k: int) -> AxisConfig:
        par = self.par

        def gain(edge: str) -> float:
            return par[PAR_INDEX[edge]] * 1e-6

        revert = par[PAR_INDEX["Revert Encoder CountDir(BitMask)"]]
        return AxisConfig(
            p=gain(f"Motor{name} P"), i=gain(f"Motor{name} I"), d=gain(f"Motor{name} D"),
            feedforward=gain(f"Motor{name} feedforward gain"),
            vp=gain(f"Motor{name} Velocity P"), vi=gain(f"Motor{name} Velocity I"),
            vd=gain(f"Motor{name} Velocity D"),
            v_max=par[PAR_INDEX[f"Motor{name} Max Velocity (x1000)"]] * 1000.0,
            max_position=par[PAR_INDEX[f"Motor{name} Max Position"]],
            min_position=par[PAR_INDEX[f"Motor{name} Min Position"]],
            reset_pwm=par[PAR_INDEX[f"Reset {name} PWM"]],
            max_pwm=float(par[PAR_INDEX["Max PWM"]]),
            invert_pwm=bool(par[PAR_INDEX["Set Joint Moving Direction(BitMask)"]] >> k & 1),
            invert_joint=bool(revert >> 2 * k & 1), invert_motor=bool(revert >> 2 * k + 1 & 1))

    def _write_prescalers(self) -> None:
        mask = self.par[PAR_INDEX["Encoder Prescaler(BitMask)"]]
        for k in range(len(AXES)):
            field = mask >> 4 * k & 0xF
            if field != self._prescalers[k]:
                for channel in (2 * k, 2 * k + 1):
                    self.hw.fpga.write(_QUAD_PRESCALE0 + channel, max(1, field))
                self._prescalers[k] = field

    def _outputs_off(self) -> None:
        registers = self.hw.fpga.registers  # as VirtualFpga.write(PWM0 + k, 0) ...
        for k in range(len(AXES)):
            registers[_PWM0 + k] = 0
        registers[_OUTPUT_ENABLE] = 0


def make(hardware: Hardware, placement: str = "", plant: Plant | None = None, *,
         params: tuple[AxisParams, ...] = ARMAR3_BOARD) -> tuple[Armar3Model, ThreeAxisPlant]:
    """The program on ``hardware`` with its plant (:data:`~ucom_tools.virtual.hardware.plant.
    ARMAR3_BOARD` unless given: every ARMAR-III board drives the same kind of joints in
    this model, whatever its ``placement``).  ``plant``: the board's plant from a program
    before, kept when it is made of the same (the caller resumes it)."""
    model = Armar3Model(hardware)
    if isinstance(plant, ThreeAxisPlant) and \
            plant.key == ThreeAxisPlant.key_of(MAX_AXES, params, ANALOG_INPUTS_V):
        return model, plant
    return model, ThreeAxisPlant(hardware.fpga, hardware.adc, params=params)
