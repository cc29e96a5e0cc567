"""The armar3.fl.S model on the three-axis plant, with the B.5 eyes tree's defaults.

Everything runs in virtual time: each cycle is ``plant.advance(dt)`` then
``model.step(dt)`` with dt = LoopTime (1 ms).  Figures the tests hold the model to:

- a Target step reaches the target with an overshoot of at most 2 % of the step, or 2
  counts (1/125 degree; a count is the sensor's resolution) for steps too small for 2 % to
  be a count; Settled is 1 within |step| / Max Velocity + 0.5 s (a 10-count step, inside
  the loops' linear range: 150 ms);
- VELOCITY holds TargetVel within 10 % (mean over 0.5 s) and stops within 5 counts of a
  limit;
- homing ends within 1 s on the eyes (about 0.45 s from the middle);
- load: 100 us with every controller off, 700 us with three axes, 300 us with one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from decimal import Decimal
from functools import cache
from statistics import mean

import pytest

import ucom_tools.virtual.programs.armar3 as armar3_model
import ucom_tools.virtual.programs.armar3_axis as armar3_axis
from ucom_tools.config.attrtree import BoardBlock, Value, load
from ucom_tools.edgelists.armar3 import SPEC, Command
from ucom_tools.edgelists.model import EdgeKind, EdgeSpec
from ucom_tools.virtual.hardware.fpga import VirtualFpga
from ucom_tools.virtual.hardware.plant import (
    CURRENT_LIMIT_A,
    EYE_AXIS,
    EYES_BOARD,
    UNUSED_AXIS,
    AxisParams,
    ThreeAxisPlant,
)
from ucom_tools.virtual.programs.armar3 import Armar3Model
from ucom_tools.virtual.programs.base import Plant, ProgramModel
from ucom_tools.wire.fpga import FpgaVersion, Reg

TREE = "attribute_trees/armar3/head_right.tree"
COUNTS_PER_RAD = 360_000 / 4 / (2 * math.pi)
"""Joint-sensor counts per radian behind the eyes' prescaler 4."""
LOWER_STOP = (EYE_AXIS.end_stops or (0.0, 0.0))[0]


@cache
def eyes() -> BoardBlock:
    return load(TREE).boards[0]


def _raw(spec: EdgeSpec, value: Value) -> int:
    # EdgeSpec.raw() takes decimals; the tree writes bit masks in hex (0x444)
    return spec.raw(value.number if isinstance(value.number, int) else value.text)


@dataclass
class Hardware:
    fpga: VirtualFpga
    adc: list[int] = field(default_factory=lambda: [0] * 8)


class Rig:
    """One eyes board: FPGA, ADC, plant and program, the tree's defaults loaded."""

    def __init__(self, params: tuple[AxisParams, ...] = EYES_BOARD,
                 plug_board_id: int = 1, *, slow: bool = False) -> None:
        self.hw = Hardware(VirtualFpga(FpgaVersion(1, 1, 1, 0), plug_board_id))
        self.plant = ThreeAxisPlant(self.hw.fpga, self.hw.adc, params=params)
        self.model = Armar3Model(self.hw)
        self.load = 0.0
        for kind, values in ((EdgeKind.CI, self.model.ci), (EdgeKind.PAR, self.model.par)):
            for i, spec in enumerate(SPEC.of(kind)):
                default = eyes().generic(spec.name).default
                if default is not None:
                    values[i] = _raw(spec, default)
        if slow:  # a velocity limit that binds: 1 = 1000 counts/s (the eyes have 500)
            self.set("MotorA Max Velocity (x1000)", 1)
            self.set("MotorB Max Velocity (x1000)", 1)

    def _at(self, kind: EdgeKind, name: str) -> tuple[EdgeSpec, int]:
        for i, spec in enumerate(SPEC.of(kind)):
            if spec.name == name:
                return spec, i
        raise KeyError(name)

    def set(self, name: str, value: int | str) -> None:
        """Set a CI or PAR edge (by its program name) to a value in the edge's units."""
        kind = EdgeKind.CI if name in {e.name for e in SPEC.of(EdgeKind.CI)} else EdgeKind.PAR
        spec, i = self._at(kind, name)
        (self.model.ci if kind is EdgeKind.CI else self.model.par)[i] = spec.raw(
            Decimal(value))

    def so(self, name: str) -> int:
        return self.model.so[self._at(EdgeKind.SO, name)[1]]

    def cycle(self) -> None:
        dt = self.model.loop_us()
        self.plant.advance(dt)
        self.load = self.model.step(dt)

    def run(self, ms: int) -> None:
        for _ in range(ms):
            self.cycle()

    def pwm(self, k: int) -> int:
        raw = self.hw.fpga.read(Reg.PWM0 + k)
        return raw - 0x10000 if raw & 0x8000 else raw

    def counts(self, k: int) -> float:
        """The true joint position of axis k in (prescaled) joint-sensor counts."""
        return self.plant.joint_edges(k) / 4


def test_model_and_plant_meet_the_protocols() -> None:
    rig = Rig()
    model: ProgramModel = rig.model
    plant: Plant = rig.plant
    assert model.spec is SPEC and plant is rig.plant
    assert len(model.ci) == 13 and len(model.so) == 20 and len(model.par) == 38
    assert model.loop_us() == 1000.0
    rig.set("LoopTime(ms)", "0.333")
    assert model.loop_us() == 333.0
    made, made_plant = armar3_model.make(rig.hw)
    assert isinstance(made, Armar3Model) and isinstance(made_plant, ThreeAxisPlant)


def test_eyes_defaults_arrive_in_par() -> None:
    rig = Rig()
    assert rig.model.par[1] == 14000  # Max PWM
    assert rig.model.par[4] == 0x444
    assert rig.model.par[5] == 50_000_000 and rig.model.par[6] == 500  # P 50, I 0.0005
    assert rig.model.ci[6] == -12725


def _step_response(rig: Rig, k: int, step: int, ms: int) -> tuple[list[float], int | None]:
    start = rig.counts(k)
    rig.set(f"Motor{'ABC'[k]} Target", step)
    trace: list[float] = []
    settled: int | None = None
    for t in range(ms):
        rig.cycle()
        trace.append((rig.counts(k) - start) * (1 if step > 0 else -1))
        if settled is None and rig.so(f"Motor {'ABC'[k]} Settled"):
            settled = t + 1
    return trace, settled


@pytest.mark.parametrize("step", [1000, -1000])
def test_position_step_reaches_target_without_overshoot(step: int) -> None:
    rig = Rig(slow=True)
    rig.run(20)
    trace, settled = _step_response(rig, 0, step, 2600)
    size = abs(step)
    assert max(trace) - size <= 0.02 * size
    rise = (next(t for t, x in enumerate(trace) if x >= 0.9 * size)
            - next(t for t, x in enumerate(trace) if x >= 0.1 * size))
    assert rise >= 0.8 * size / 1000 * 1000 * 0.99  # Max Velocity 1000 counts/s holds
    assert settled is not None and settled <= (size / 1000 + 0.5) * 1000
    assert abs(rig.so("Encoder 0") - step) <= armar3_model.SETTLED_COUNTS
    assert abs(rig.counts(1)) < 1 and rig.so("Encoder 2") == 0  # the left eye stayed put


def test_the_eyes_defaults_move_fast_and_well_damped() -> None:
    """Max Velocity (x1000) 500 = 500 000 counts/s does not bind: the motor's own speed
    and Max PWM do; a 1000-count saccade still arrives without overshoot."""
    rig = Rig()
    rig.run(20)
    trace, settled = _step_response(rig, 0, 1000, 1000)
    assert max(trace) - 1000 <= 20
    assert next(t for t, x in enumerate(trace) if x >= 900) < 200
    assert settled is not None and settled < 600


def test_small_step_is_well_damped() -> None:
    rig = Rig()
    rig.run(20)
    trace, settled = _step_response(rig, 0, 10, 300)  # 10 counts: the loops stay linear
    assert max(trace) - 10 <= 2
    assert settled is not None and settled <= 150


def test_target_is_clamped_to_min_and_max_position() -> None:
    rig = Rig()
    rig.set("MotorA Max Position", 300)
    rig.set("MotorA Min Position", -200)
    rig.set("MotorA Target", 2000)
    rig.run(1200)
    assert rig.so("Motor A Settled") == 1
    assert abs(rig.so("Encoder 0") - 300) <= armar3_model.SETTLED_COUNTS
    assert rig.counts(0) <= 303
    rig.set("MotorA Target", -32768)
    rig.run(1500)
    assert rig.so("Motor A Settled") == 1
    assert abs(rig.so("Encoder 0") + 200) <= armar3_model.SETTLED_COUNTS
    assert rig.counts(0) >= -203


def test_velocity_mode_holds_target_vel_and_stops_at_the_limits() -> None:
    rig = Rig(slow=True)
    rig.set("MotorA Max Position", 600)
    rig.set("MotorA Min Position", -300)
    rig.set("MotorA Command", Command.VELOCITY)
    rig.set("MotorA TargetVel", 300)
    rig.run(500)
    seen = []
    for _ in range(500):
        rig.cycle()
        seen.append(rig.so("Velocity A"))
    assert mean(seen) == pytest.approx(300, rel=0.1)
    rig.run(2000)
    assert abs(rig.counts(0) - 600) <= 5 and rig.plant.joint_velocity(0) == 0
    assert rig.so("Motor A Settled") == 0  # Settled is a position-loop flag
    rig.set("MotorA TargetVel", -1900)  # beyond Max Velocity: 1000 counts/s
    rig.run(300)
    seen = []
    for _ in range(300):
        rig.cycle()
        seen.append(rig.so("Velocity A"))
    assert mean(seen) == pytest.approx(-1000, rel=0.1)
    rig.run(1500)
    assert abs(rig.counts(0) + 300) <= 5 and rig.plant.joint_velocity(0) == 0


def test_homing_finds_the_end_stop_and_loads_reset_offset() -> None:
    rig = Rig()
    rig.run(10)
    assert rig.so("MotorA Reset Answer") == 0
    rig.set("MotorA Command", Command.HOMING)
    rig.set("MotorB Command", Command.HOMING)
    volts = 0
    for _ in range(1000):
        rig.cycle()
        assert rig.so("MotorA Reset Answer") in (1, 2)
        if rig.so("MotorA Reset Answer") == 1:
            volts = rig.so("Voltage A")
        if rig.so("MotorA Reset Answer") == rig.so("MotorB Reset Answer") == 2:
            break
    else:
        pytest.fail("homing did not end within 1 s")
    assert rig.so("Encoder 0") == -12725 and rig.so("Encoder 2") == -11457
    assert rig.plant.joint_angle(0) == LOWER_STOP
    # the stalled motor drew 7000/16000 * 24 V / 4 ohm = 2.6 A: 1.31 V at 0.5 V/A
    assert volts == pytest.approx(1313, abs=5)
    rig.run(300)  # and holds there
    assert rig.so("Encoder 0") == -12725 and rig.so("MotorA Reset Answer") == 2
    assert rig.so("Motor A Settled") == 1
    rig.set("MotorA Command", Command.POSITION)
    rig.set("MotorA Target", -12000)  # back inside the limits (-10000 clamps it)
    rig.run(300)
    assert rig.so("Encoder 0") > -12725 + 100 and rig.so("MotorA Reset Answer") == 2


def test_homing_fails_without_a_stall(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(armar3_axis, "HOMING_TIMEOUT_US", 300_000.0)  # read there
    rig = Rig(params=(replace(EYE_AXIS, end_stops=None), EYE_AXIS, UNUSED_AXIS))
    rig.set("Reset B PWM", 0)
    rig.set("MotorA Command", Command.HOMING)
    rig.set("MotorB Command", Command.HOMING)
    rig.cycle()
    assert rig.so("MotorA Reset Answer") == 1 and rig.so("MotorB Reset Answer") == -1
    rig.run(290)
    assert rig.so("MotorA Reset Answer") == 1
    rig.run(20)
    assert rig.so("MotorA Reset Answer") == -1


def test_a_gain_change_acts_in_the_next_cycle() -> None:
    a, b = Rig(slow=True), Rig(slow=True)
    for rig in (a, b):
        rig.set("MotorA Target", 500)
        rig.run(300)
    assert a.pwm(0) == b.pwm(0) != 0 and a.so("Velocity A") == b.so("Velocity A")
    b.set("MotorA Velocity P", 0)
    a.cycle()
    b.cycle()
    assert a.pwm(0) != b.pwm(0)
    assert abs(b.pwm(0)) < abs(a.pwm(0))  # only the velocity sum is left


def test_stop_zeroes_outputs_at_once_and_holds_until_release() -> None:
    rig = Rig(slow=True)
    rig.set("MotorA Target", 1000)
    rig.set("MotorB Target", -1000)
    rig.run(400)
    assert rig.hw.fpga.read(Reg.OUTPUT_ENABLE) == 0b111 and rig.pwm(0) != 0
    rig.model.stop()
    assert rig.hw.fpga.read(Reg.OUTPUT_ENABLE) == 0
    assert [rig.pwm(k) for k in range(3)] == [0, 0, 0]
    at_stop = rig.counts(0)
    rig.run(300)  # the joints coast to rest; the program only senses and reports
    assert rig.plant.joint_velocity(0) == 0 and rig.plant.joint_velocity(1) == 0
    assert 0 < rig.counts(0) - at_stop < 40
    assert rig.so("Encoder 0") == round(rig.counts(0) - 0.5)
    assert rig.hw.fpga.read(Reg.OUTPUT_ENABLE) == 0 and rig.pwm(0) == 0
    assert rig.so("Velocity A") == 0 and rig.so("Motor A Settled") == 0
    assert rig.load == armar3_model.BASE_US
    rig.model.release()
    rig.cycle()
    assert rig.hw.fpga.read(Reg.OUTPUT_ENABLE) == 0b111 and rig.pwm(0) != 0
    rig.run(2000)
    assert rig.so("Motor A Settled") == 1 and rig.so("Motor B Settled") == 1


def test_stop_aborts_homing() -> None:
    rig = Rig()
    rig.set("MotorA Command", Command.HOMING)
    rig.run(50)
    rig.model.stop()
    rig.run(1000)  # coasts to rest
    assert rig.so("MotorA Reset Answer") == -1
    assert rig.plant.joint_velocity(0) == 0
    rig.model.release()
    rig.run(100)  # Command still HOMING: the axis holds where it is, no new homing
    assert rig.so("MotorA Reset Answer") == -1
    assert rig.so("Motor A Settled") == 1


def test_revert_encoder_count_dir_negates_each_counter() -> None:
    rig = Rig()
    rig.set("Revert Encoder CountDir(BitMask)", 0b001001)
    for channel, value in enumerate((100, 200, 300, 7, 500, 600)):
        rig.hw.fpga.write(Reg.QUAD_COUNT0 + channel, value)
    rig.set("MotorA Command", Command.OFF)
    rig.set("MotorB Command", Command.OFF)
    rig.cycle()
    assert [rig.so(f"Encoder {n}") for n in range(6)] == [-100, 200, 300, -7, 500, 600]


def test_joint_moving_direction_negates_the_pwm() -> None:
    signs = []
    for mask in (0x3, 0x2):
        rig = Rig()
        rig.set("Set Joint Moving Direction(BitMask)", mask)
        rig.set("MotorA Target", 100)
        rig.cycle()
        signs.append(rig.pwm(0))
    assert signs[0] < 0 < signs[1] and signs[0] == -signs[1]


def test_the_masks_close_the_loop_on_other_wiring() -> None:
    # the eyes need direction bits 0x3 (motor wired negatively) ...
    rig = Rig()
    rig.set("MotorA Target", 200)
    rig.run(700)
    assert rig.so("Motor A Settled") == 1 and rig.so("Encoder 1") > 0
    # ... and run away without them
    rig = Rig()
    rig.set("Set Joint Moving Direction(BitMask)", 0x2)
    rig.set("MotorA Target", 200)
    rig.run(300)
    assert rig.counts(0) < -100
    # a motor wired positively with both sensors counting down: Revert bits 0 and 1
    inverted = AxisParams(joint_sensor_polarity=-1, motor_encoder_polarity=-1)
    rig = Rig(params=(inverted, EYE_AXIS, UNUSED_AXIS))
    rig.set("Set Joint Moving Direction(BitMask)", 0x2)
    rig.set("Revert Encoder CountDir(BitMask)", 0b11)
    rig.set("MotorA Target", 200)
    rig.run(700)
    assert rig.so("Motor A Settled") == 1
    assert rig.plant.joint_angle(0) * COUNTS_PER_RAD == pytest.approx(200, abs=6)
    assert rig.so("Encoder 1") > 0


def test_encoder_prescaler_fields_set_both_counters_of_a_motor() -> None:
    rig = Rig()
    rig.cycle()
    assert [rig.hw.fpga.read(Reg.QUAD_PRESCALE0 + n) for n in range(6)] == [4] * 6
    rig.set("Encoder Prescaler(BitMask)", 0x120)
    rig.cycle()
    assert [rig.hw.fpga.read(Reg.QUAD_PRESCALE0 + n) for n in range(6)] == [1, 1, 2, 2, 1, 1]
    rig.hw.fpga.encoder_edges(3, 100)
    rig.cycle()
    assert rig.so("Encoder 3") == 50


def test_counter_wraparound_keeps_velocity_continuous() -> None:
    rig = Rig()
    rig.set("Encoder Prescaler(BitMask)", 0x111)
    rig.set("MotorA Command", Command.OFF)
    rig.hw.fpga.write(Reg.QUAD_COUNT0, 32000)
    velocities = []
    for _ in range(100):  # 20 counts per 1 ms cycle: 20000 counts/s across +32767
        rig.hw.fpga.encoder_edges(0, 20)
        rig.model.step(1000)
        velocities.append(rig.so("Velocity A"))
    assert rig.so("Encoder 0") == 32000 + 2000 - 65536
    assert max(velocities) <= 20000  # no jump from the counter's start value or the wrap
    assert min(velocities[50:]) == max(velocities[50:]) == pytest.approx(20000, abs=1)


def test_load_figures() -> None:
    rig = Rig()
    rig.cycle()  # the eyes tree: A and B position control, C too (its Command is 0)
    assert rig.load == 700 < 1000
    for axis in "ABC":
        rig.set(f"Motor{axis} Command", Command.OFF)
    rig.cycle()
    assert rig.load == 100 == 0.1 * rig.model.loop_us()
    rig.set("MotorA Command", Command.POSITION)
    rig.cycle()
    assert rig.load == 300 < 1e6 / 3000


def test_neutral_fpga_keeps_the_motors_still() -> None:
    rig = Rig(plug_board_id=2)  # the plug-on board's Board-ID does not match
    assert rig.hw.fpga.neutral
    rig.set("MotorA Command", Command.HOMING)
    rig.set("MotorB Target", 1000)
    rig.set("MotorC Command", Command.VELOCITY)
    rig.set("MotorC Velocity P", 1)
    rig.set("MotorC Max Velocity (x1000)", 500)
    rig.set("MotorC TargetVel", 500)
    rig.run(500)
    assert rig.pwm(0) != 0 and rig.pwm(1) != 0  # the program commands ...
    for k in range(3):  # ... but nothing moves and no current flows
        assert rig.plant.joint_angle(k) == 0 and rig.plant.motor_current(k) == 0
    assert [rig.so(f"Encoder {n}") for n in range(6)] == [0] * 6
    assert rig.so("Voltage A") == 0
    assert rig.so("MotorA Reset Answer") == 1  # no current: no stall, no false "homed"


def test_current_sense_and_analog_inputs() -> None:
    rig = Rig()
    rig.cycle()
    assert rig.so("AD Channel 6") == 1241 and rig.so("AD Channel 7") == 2482  # 1 V, 2 V
    assert rig.so("Voltage A") == 0


def test_plant_limits_the_current_and_integrates_any_dt() -> None:
    hw = Hardware(VirtualFpga(FpgaVersion(1, 1, 1, 0), 1))
    plant = ThreeAxisPlant(hw.fpga, hw.adc)
    hw.fpga.write(Reg.OUTPUT_ENABLE, 0b001)
    hw.fpga.write(Reg.PWM0, 16000)  # full supply; the right eye turns negatively
    plant.advance(2_000_000)  # one call, 2 s: stable, ends at the stop
    assert plant.joint_angle(0) == LOWER_STOP
    assert plant.motor_current(0) == -CURRENT_LIMIT_A  # 24 V / 4 ohm = 6 A, limited
    assert hw.adc[0] == round(2.5 / 3.3 * 4095)
    assert plant.joint_angle(1) == 0 and plant.motor_current(1) == 0  # not enabled
    twins = []
    for chunks in ([1000.0] * 30, [100.0] * 300, [30_000.0], [250.0, 750.0] * 30):
        hw = Hardware(VirtualFpga(FpgaVersion(1, 1, 1, 0), 1))
        plant = ThreeAxisPlant(hw.fpga, hw.adc)
        hw.fpga.write(Reg.OUTPUT_ENABLE, 0b100)
        hw.fpga.write(Reg.PWM0 + 2, 4000)
        for dt in chunks:
            plant.advance(dt)
        twins.append((plant.joint_angle(2), hw.fpga.read(Reg.QUAD_COUNT0 + 4)))
    assert twins[0] == twins[1] == twins[2]  # whole substeps: the same, bit for bit
    assert twins[3][0] == pytest.approx(twins[0][0], rel=1e-3)  # shortened substeps
    assert twins[0][0] > 0


@pytest.mark.parametrize("duty, enable, reversing", [
    (16000, 0b111, False),  # the current limit, then the end stop (A, B) or free (C)
    (7000, 0b111, False),  # homing-like: stalls at the end stop with 2.6 A
    (60, 0b111, False),  # below the breakaway duty of about 113: the motors stick
    (3000, 0b111, True),  # the duty changes sign every 40 ms
    (9000, 0b000, False),  # not enabled
])
def test_a_long_call_equals_its_substeps(duty: int, enable: int, reversing: bool) -> None:
    """advance(1000) takes ten substeps in one go and stops early once nothing can change any
    more (at rest, or stalled at an end stop): bit for bit what ten calls of 100 us give."""
    twins: list[list[object]] = []
    for chunk, calls in ((1000.0, 1), (100.0, 10)):
        hw = Hardware(VirtualFpga(FpgaVersion(1, 1, 1, 0), 1))
        plant = ThreeAxisPlant(hw.fpga, hw.adc, params=(EYE_AXIS, EYE_AXIS, UNUSED_AXIS))
        trace: list[object] = []
        for ms in range(600):
            hw.fpga.write(Reg.OUTPUT_ENABLE, enable if ms < 400 else 0)  # then coasting
            now = -duty if reversing and ms // 40 % 2 else duty
            for k in range(3):
                hw.fpga.write(Reg.PWM0 + k, (now if k != 1 else -now) & 0xFFFF)
            for _ in range(calls):
                plant.advance(chunk)
            trace.append(([(plant.joint_angle(k), plant.joint_velocity(k),
                            plant.motor_current(k)) for k in range(3)],
                          [hw.fpga.read(Reg.QUAD_COUNT0 + n) for n in range(6)], list(hw.adc)))
        twins.append(trace)
    assert twins[0] == twins[1]
