"""The lauron4.fl.S spec against the LAURON-IV trees, and its model on a virtual leg.

Everything runs in virtual time: each cycle is ``plant.advance(dt)`` then
``model.step(dt)`` with dt = Cycle Time (1 ms), as the run-time does.  Figures the tests
hold the model to (left leg, the front left leg tree's defaults):

- a 20 deg step of beta: velocity at most 6000 (60 deg/s) + 2 %, Settled within 1 s,
  within 0.1 deg of the set point, no overshoot beyond 0.02 deg;
- pressing the foot into the ground, the measured current stays within 3 % of Current
  Limit x Torque Limit (a slow approach) and the foot force halves with the torque limit;
- compliant mode under 5 N m on alpha: about 0.5 deg (a spring), back to the set point
  without the load; position mode nearly 0; with a 20 % torque limit the joint gives way;
- load: 130 us with everything off, 730 us with a leg in control, 500 us on the head.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from decimal import Decimal
from functools import cache
from pathlib import Path

import pytest

import ucom_tools.virtual.programs.lauron4 as lauron4_model
from ucom_tools.config.attrtree import BoardBlock, TreeEdgeKind, Value, load
from ucom_tools.edgelists import by_name
from ucom_tools.edgelists.lauron4 import NAME, SPEC, LegMode, Status
from ucom_tools.edgelists.model import EdgeKind, EdgeSpec
from ucom_tools.image.formats import load_image
from ucom_tools.virtual.hardware.fpga import VirtualFpga
from ucom_tools.virtual.hardware.plant import AxisParams
from ucom_tools.virtual.programs.base import Plant, ProgramModel
from ucom_tools.virtual.programs.lauron4 import (
    GROUND_Z,
    HEAD_JOINTS,
    LEG_JOINTS,
    Lauron4Model,
    LegPlant,
)
from ucom_tools.wire.fpga import FpgaVersion, Reg

TREES = sorted(Path("attribute_trees/lauron4").glob("*.tree"))
KINDS = {TreeEdgeKind.CI: EdgeKind.CI, TreeEdgeKind.SO: EdgeKind.SO, TreeEdgeKind.PAR: EdgeKind.PAR}
DEG = math.pi / 180


@cache
def tree_board(name: str) -> BoardBlock:
    return load(Path("attribute_trees/lauron4") / name).boards[0]


def _raw(spec: EdgeSpec, value: Value) -> int:
    # EdgeSpec.raw() takes decimals; the trees write bit masks in hex (0x1)
    return spec.raw(value.number if isinstance(value.number, int) else value.text)


# ---------------------------------------------------------------------- spec and trees
def test_name_is_the_image_descriptors_and_the_spec_is_known() -> None:
    descriptor = load_image("firmware_images/lauron4.fl.S").descriptor
    assert descriptor is not None and descriptor.name == NAME == "lauron4 leg"
    assert by_name(NAME) is SPEC
    assert [len(SPEC.of(k)) for k in EdgeKind] == [11, 15, 30]
    assert SPEC.edges[0].name == "Leg Mode" and SPEC.edges[10].name == "Reference Run"
    assert SPEC.edges[25].name == "Supply Voltage(mV)"
    assert SPEC.edges[55].name == "Foot Force Filter(ms)"


@pytest.mark.parametrize("path", TREES, ids=lambda p: p.stem)
def test_every_tree_maps_the_specs_edges_in_order(path: Path) -> None:
    (board,) = load(path).boards
    assert [(e.generic, KINDS[e.kind]) for e in board.edges] == [
        (s.name, s.kind) for s in SPEC.edges]


@pytest.mark.parametrize("path", TREES, ids=lambda p: p.stem)
def test_every_tree_default_travels_exactly(path: Path) -> None:
    (board,) = load(path).boards
    for edge, spec in zip(board.edges, SPEC.edges, strict=True):
        if edge.default is not None:
            number = edge.default.number
            exact = Decimal(number) if isinstance(number, int) else Decimal(edge.default.text)
            assert spec.value(_raw(spec, edge.default)) == exact, edge.unique


def test_spec_defaults_are_the_left_leg_but_for_the_joint_limits() -> None:
    board = tree_board("front_left_leg.tree")
    for spec in SPEC.edges:
        default = board.generic(spec.name).default
        if default is None:
            assert spec.default == 0  # Reference Run
        elif "Upper Limit" in spec.name or "Lower Limit" in spec.name:
            assert abs(spec.default) == 18000  # none: the head's axis 3 keeps these
        else:
            assert spec.default == _raw(spec, default), spec.name


# ---------------------------------------------------------------------- a virtual leg
@dataclass
class Hardware:
    fpga: VirtualFpga
    adc: list[int] = field(default_factory=lambda: [0] * 8)


class Rig:
    """One board: FPGA, ADC, plant and program, a tree's defaults loaded."""

    def __init__(self, tree: str = "front_left_leg.tree", *, plug_board_id: int = 1,
                 params: Sequence[AxisParams] = LEG_JOINTS,
                 marks: Sequence[float | None] = (0.0, 0.0, 0.0)) -> None:
        self.hw = Hardware(VirtualFpga(FpgaVersion(1, 2, 1, 0), plug_board_id))
        head = tree == "camera_head.tree"
        self.plant = LegPlant(self.hw.fpga, self.hw.adc, HEAD_JOINTS if head else params,
                              ground_z=None if head else GROUND_Z, foot_sensor=not head,
                              marks=(0.0, 0.0, None) if head else marks)
        self.model = Lauron4Model(self.hw)
        self.load = 0.0
        board = tree_board(tree)
        for kind, values in ((EdgeKind.CI, self.model.ci), (EdgeKind.PAR, self.model.par)):
            for i, spec in enumerate(SPEC.of(kind)):
                default = board.generic(spec.name).default
                if default is not None:
                    values[i] = _raw(spec, default)

    def _at(self, kind: EdgeKind, name: str) -> tuple[EdgeSpec, int]:
        for i, spec in enumerate(SPEC.of(kind)):
            if spec.name == name:
                return spec, i
        raise KeyError(name)

    def set(self, name: str, value: int | str) -> None:
        """Set a CI or PAR edge (by its generic name) to a value in the edge's units."""
        kind = EdgeKind.CI if name in {e.name for e in SPEC.of(EdgeKind.CI)} else EdgeKind.PAR
        spec, i = self._at(kind, name)
        (self.model.ci if kind is EdgeKind.CI else self.model.par)[i] = spec.raw(
            Decimal(value))

    def so(self, name: str) -> int:
        return self.model.so[self._at(EdgeKind.SO, name)[1]]

    def status(self, axis: int) -> int:
        return self.so("Leg Status(BitMask)") >> 4 * axis & 0xF

    def cycle(self) -> None:
        dt = self.model.loop_us()
        self.plant.advance(dt)
        self.load = self.model.step(dt)

    def run(self, ms: int) -> None:
        for _ in range(ms):
            self.cycle()

    def trace(self, ms: int, name: str) -> list[int]:
        out = []
        for _ in range(ms):
            self.cycle()
            out.append(self.so(name))
        return out

    def pwm(self, k: int) -> int:
        raw = self.hw.fpga.read(Reg.PWM0 + k)
        return raw - 0x10000 if raw & 0x8000 else raw

    def angle(self, k: int) -> float:
        """True angle of joint k in 0.01 deg."""
        return self.plant.joint_angle(k) / DEG * 100


def test_model_and_plant_meet_the_protocols() -> None:
    rig = Rig()
    model: ProgramModel = rig.model
    plant: Plant = rig.plant
    assert model.spec is SPEC and plant is rig.plant
    assert (len(model.ci), len(model.so), len(model.par)) == (11, 15, 30)
    assert model.loop_us() == 1000.0
    rig.set("Cycle Time(us)", 500)
    assert model.loop_us() == 500.0
    made, made_plant = lauron4_model.make(rig.hw)
    assert isinstance(made, Lauron4Model) and isinstance(made_plant, LegPlant)
    assert made.par == [e.default for e in SPEC.of(EdgeKind.PAR)]


def test_position_step_reaches_the_set_point_and_settles() -> None:
    rig = Rig()
    rig.set("Leg Mode", LegMode.POSITION)
    rig.run(20)
    rig.set("Axis2 Position Setpoint", 2000)  # beta up 20 deg
    settled = None
    peak = 0.0
    velocities = []
    for t in range(1500):
        rig.cycle()
        peak = max(peak, rig.angle(1))
        velocities.append(rig.so("Axis2 Velocity"))
        if settled is None and rig.status(1) & Status.SETTLED:
            settled = t + 1
    assert settled is not None and settled <= 1000
    assert abs(rig.so("Axis2 Position") - 2000) <= lauron4_model.SETTLED_COUNTS
    assert peak <= 2002
    assert max(velocities) <= 6000 * 1.02
    assert abs(rig.so("Axis1 Position")) <= 1 and abs(rig.so("Axis3 Position")) <= 1
    assert rig.status(0) & Status.SETTLED and rig.status(2) & Status.SETTLED


def test_velocity_limit_holds() -> None:
    rig = Rig()
    rig.set("Leg Mode", LegMode.POSITION)
    rig.set("Axis1 Position Setpoint", 8000)
    fast = rig.trace(400, "Axis1 Velocity")
    true_fast = rig.plant.joint_velocity(0) / DEG * 100
    assert max(fast) <= 6000 * 1.02 and true_fast == pytest.approx(6000, rel=0.02)
    rig.set("Axis1 Velocity Limit", 2500)  # acts in the next cycle
    slow = rig.trace(300, "Axis1 Velocity")
    assert max(slow[100:]) <= 2500 * 1.05
    assert rig.plant.joint_velocity(0) / DEG * 100 == pytest.approx(2500, rel=0.03)


def test_velocity_mode_brakes_into_the_joint_limit() -> None:
    rig = Rig()
    rig.set("Leg Mode", LegMode.VELOCITY)
    rig.set("Axis1 Velocity Setpoint", 4000)
    rig.run(500)
    assert rig.so("Axis1 Velocity") == pytest.approx(4000, rel=0.05)
    assert rig.status(0) & Status.SETTLED and not rig.status(0) & Status.LIMIT_HIT
    rig.run(2500)
    assert 8990 <= rig.angle(0) <= 9001  # Alpha Upper Limit 90 deg
    assert rig.status(0) & Status.LIMIT_HIT


def _press(torque: int) -> tuple[Rig, list[int]]:
    """Lift beta 15 deg, then press the foot into the ground (set point -10 deg) slowly."""
    rig = Rig()
    rig.set("Leg Mode", LegMode.POSITION)
    rig.set("Axis2 Velocity Limit", 1000)
    rig.set("Axis2 Torque Limit(%)", torque)
    rig.set("Axis2 Position Setpoint", 1500)
    rig.run(1700)
    assert rig.so("Ground Contact") == 0 and rig.so("Foot Force Z") == 0
    rig.set("Axis2 Position Setpoint", -1000)
    return rig, rig.trace(2500, "Axis2 Motor Current")


def test_torque_limit_holds_pressing_the_foot_into_the_ground() -> None:
    full, full_currents = _press(100)
    half, half_currents = _press(50)
    assert max(abs(i) for i in full_currents) <= 4000 * 1.03
    assert max(abs(i) for i in half_currents) <= 2000 * 1.03
    assert half_currents[-1] == pytest.approx(-2000, abs=20)
    assert full_currents[-1] == pytest.approx(-4000, abs=40)
    full_z, half_z = full.so("Foot Force Z"), half.so("Foot Force Z")
    assert half_z == pytest.approx(full_z / 2, rel=0.15)
    assert full.so("Axis2 Position") > -1000 and full.status(1) & Status.SETTLED == 0


def test_compliant_mode_gives_way_under_load() -> None:
    deflection = {}
    for mode in (LegMode.POSITION, LegMode.COMPLIANT):
        rig = Rig()
        rig.set("Leg Mode", mode)
        rig.run(50)
        rig.plant.load[0] = 5.0  # N m on alpha
        rig.run(800)
        deflection[mode] = rig.so("Axis1 Position")
        if mode == LegMode.COMPLIANT:
            rig.plant.load[0] = 0.0
            rig.run(800)
            assert abs(rig.so("Axis1 Position")) <= 2  # a spring: back to the set point
    assert abs(deflection[LegMode.POSITION]) <= 3  # the velocity integral holds it
    # the spring: 5 N m / (5.4 N m/A) over 2.5 mA/(0.01 deg/s) x 8/s = 46 (0.01 deg)
    assert deflection[LegMode.COMPLIANT] == pytest.approx(46, abs=6)
    weak = Rig()
    weak.set("Leg Mode", LegMode.COMPLIANT)
    weak.set("Axis1 Torque Limit(%)", 20)  # 800 mA: 4.3 N m < 5 N m
    weak.run(50)
    weak.plant.load[0] = 5.0
    weak.run(500)
    assert weak.so("Axis1 Position") > 1000  # gave way more than 10 deg
    assert abs(weak.so("Axis1 Motor Current")) <= 800 * 1.05


def test_ground_contact_when_the_leg_is_lowered() -> None:
    rig = Rig()
    rig.set("Leg Mode", LegMode.COMPLIANT)
    rig.set("Axis2 Position Setpoint", 1500)
    rig.run(800)
    assert rig.so("Ground Contact") == 0 and rig.so("Foot Force Z") == 0
    rig.set("Axis2 Position Setpoint", -1000)
    raw_over = contact = None
    for t in range(1, 1000):
        rig.cycle()
        if raw_over is None and (rig.hw.adc[5] - 2048) * 2 > 150:
            raw_over = t
        if contact is None and rig.so("Ground Contact"):
            contact = t
    assert raw_over is not None and contact is not None
    assert 2 <= contact - raw_over <= 8  # the 5 ms foot force filter
    assert rig.so("Foot Force Z") > 150 and rig.so("Axis2 Position") < 0
    assert abs(rig.so("Foot Force Z") - round(rig.plant.force[2] * 10)) <= 2
    rig.set("Ground Contact Threshold(N)", "499.9")
    rig.cycle()
    assert rig.so("Ground Contact") == 0
    rig.set("Ground Contact Threshold(N)", 15)
    rig.set("Axis2 Position Setpoint", 1500)
    rig.run(800)
    assert rig.so("Ground Contact") == 0 and rig.so("Foot Force Z") == 0


def test_reference_run_sets_the_reference_offsets() -> None:
    starts = (10 * DEG, -5 * DEG, -20 * DEG)
    marks = (2 * DEG, 0.0, -30 * DEG)
    rig = Rig(params=[replace(p, start_angle=a) for p, a in zip(LEG_JOINTS, starts, strict=True)],
              marks=marks)
    offsets = (1000, -500, 250)
    for k, offset in enumerate(offsets):
        rig.set(f"Axis{k + 1} Reference Offset", offset)
    rig.set("Leg Mode", LegMode.OFF)
    rig.run(5)
    assert rig.so("Axis1 Position") == 0  # counts from power-up
    rig.set("Reference Run", 1)
    done = None
    for t in range(2000):
        rig.cycle()
        if done is None and rig.so("Leg Status(BitMask)") & 0x111 == 0x111:
            done = t
            positions = [rig.so(f"Axis{k + 1} Position") for k in range(3)]
            true = [rig.angle(k) for k in range(3)]
    assert done is not None and done < 1000
    for k in range(3):
        # the position at the mark is the offset (to a count: found at 2 deg/s)
        assert abs(positions[k] - (true[k] - marks[k] / DEG * 100 + offsets[k])) <= 1.5
    assert rig.pwm(0) == 0 and rig.hw.fpga.read(Reg.OUTPUT_ENABLE) == 0  # Leg Mode OFF
    rig.run(100)
    assert [rig.so(f"Axis{k + 1} Position") for k in range(3)] == positions
    rig.set("Reference Run", 1)  # no rising value: nothing moves
    rig.run(10)
    assert rig.hw.fpga.read(Reg.OUTPUT_ENABLE) == 0


def test_parameter_change_takes_effect_next_cycle() -> None:
    rig = Rig()
    rig.set("Leg Mode", LegMode.POSITION)
    rig.set("Axis3 Position Setpoint", -5000)
    rig.run(5)
    assert abs(rig.pwm(2)) > 2000
    rig.set("PWM Limit", 1000)
    rig.cycle()
    assert abs(rig.pwm(2)) == 1000
    rig.set("Motor Direction(BitMask)", 0x4)
    before = rig.pwm(2)
    rig.cycle()
    assert rig.pwm(2) == -before
    rig.set("Axis3 Current Limit(mA)", 0)  # the axis is no longer in use
    rig.cycle()
    assert rig.pwm(2) == 0 and rig.hw.fpga.read(Reg.OUTPUT_ENABLE) == 0b011


def test_stop_zeroes_outputs_at_once_and_release_is_needed() -> None:
    rig = Rig()
    rig.set("Leg Mode", LegMode.POSITION)
    rig.set("Axis1 Position Setpoint", 3000)
    rig.run(50)
    assert rig.pwm(0) != 0 and rig.hw.fpga.read(Reg.OUTPUT_ENABLE) == 0b111
    rig.model.stop()
    assert [rig.pwm(k) for k in range(3)] == [0, 0, 0]
    assert rig.hw.fpga.read(Reg.OUTPUT_ENABLE) == 0
    rig.run(50)
    assert rig.hw.fpga.read(Reg.OUTPUT_ENABLE) == 0 and rig.pwm(0) == 0
    assert rig.so("Axis1 Position") > 0  # still sensing
    rig.set("Reference Run", 1)  # ignored while stopped
    rig.run(5)
    assert rig.load == lauron4_model.BASE_US + lauron4_model.FOOT_US
    rig.model.release()
    rig.cycle()
    assert rig.pwm(0) != 0 and rig.hw.fpga.read(Reg.OUTPUT_ENABLE) == 0b111
    rig.run(1500)
    assert abs(rig.so("Axis1 Position") - 3000) <= lauron4_model.SETTLED_COUNTS
    assert rig.status(0) & Status.REFERENCED == 0


def test_neutral_fpga_drives_nothing() -> None:
    rig = Rig(plug_board_id=2)  # a UCoM-3M under a 3M configuration
    rig.set("Leg Mode", LegMode.POSITION)
    rig.set("Axis1 Position Setpoint", 3000)
    rig.run(100)
    assert rig.hw.fpga.read(Reg.OUTPUT_ENABLE) == 0 and rig.plant.joint_angle(0) == 0


def test_load_figures() -> None:
    rig = Rig()
    rig.cycle()
    assert rig.load == 130.0  # base + foot sensor, everything off
    rig.set("Leg Mode", LegMode.POSITION)
    rig.cycle()
    assert rig.load == 730.0  # three axes in control
    rig.set("Axis2 Torque Limit(%)", 0)
    rig.cycle()
    assert rig.load == 530.0
    head = Rig("camera_head.tree")
    head.set("Leg Mode", LegMode.POSITION)
    head.cycle()
    assert head.load == 500.0  # two axes, no foot


def test_head_and_right_leg_run_with_their_trees() -> None:
    head = Rig("camera_head.tree")
    head.set("Leg Mode", LegMode.POSITION)
    head.set("Axis1 Position Setpoint", 2000)
    head.set("Axis2 Position Setpoint", -1000)
    velocities = head.trace(1500, "Axis1 Velocity")
    assert max(velocities) <= 4000 * 1.03  # the head's velocity limit
    assert abs(head.so("Axis1 Position") - 2000) <= 10 and head.so("Axis2 Position") == -1000
    assert head.so("Foot Force Z") == 0 and head.so("Ground Contact") == 0
    assert head.so("Supply Voltage(mV)") == 24000
    right_alpha = replace(LEG_JOINTS[0], motor_polarity=-1)  # mirrored alpha drive
    right = Rig("front_right_leg.tree", params=(right_alpha, *LEG_JOINTS[1:]))
    right.set("Leg Mode", LegMode.POSITION)
    right.set("Axis1 Position Setpoint", 1000)
    right.run(800)
    assert abs(right.so("Axis1 Position") - 1000) <= 10
    assert right.pwm(0) <= 0 <= right.so("Axis1 Motor Current") + 100


def test_encoder_direction_bits_undo_reversed_sensors() -> None:
    gamma = replace(LEG_JOINTS[2], joint_sensor_polarity=-1, motor_encoder_polarity=-1)
    rig = Rig(params=(*LEG_JOINTS[:2], gamma))
    rig.set("Encoder Direction(BitMask)", 0x30)  # channels 4 and 5: gamma's sensors
    rig.set("Leg Mode", LegMode.POSITION)
    rig.set("Axis3 Position Setpoint", -2000)
    rig.run(1200)
    assert abs(rig.so("Axis3 Position") + 2000) <= lauron4_model.SETTLED_COUNTS
    assert rig.angle(2) == pytest.approx(-2000, abs=lauron4_model.SETTLED_COUNTS)


def test_out_of_contact_the_joints_are_integrated_apart_exactly() -> None:
    """Out of contact LegPlant integrates each joint over the whole cycle on its own and
    checks the foot's height afterwards; touching down and lifting off again and again, with
    a load and cycles of odd lengths, that gives bit for bit what integrating all three
    joints substep by substep with the ground's forces gives."""
    rigs = Rig(), Rig()
    rigs[1].plant.apart = False
    traces: list[list[object]] = [[], []]
    pressing: list[list[bool]] = [[], []]
    for rig, trace, pressed in zip(rigs, traces, pressing, strict=True):
        rig.set("Leg Mode", LegMode.POSITION)
        rig.set("Axis1 Position Setpoint", 1500)
        for t in range(3000):
            rig.set("Axis2 Position Setpoint", -900 if t // 400 % 2 else 300)  # down and up
            rig.plant.load[2] = 2.0 if t // 300 % 2 else 0.0
            dt = (1000.0, 50.0, 333.0, 50.0, 1250.5, 100.0)[t % 6]
            rig.plant.advance(dt)
            rig.model.step(dt)
            trace.append(([(j.angle, j.speed, j.current) for j in rig.plant.joints],
                          rig.plant.force, rig.plant._anchor, list(rig.model.so),
                          list(rig.hw.adc)))
            pressed.append(rig.plant.force[2] > 0)
    assert traces[0] == traces[1]
    touchdowns = [now and not before
                  for before, now in zip(pressing[0], pressing[0][1:], strict=False)]
    assert sum(touchdowns) >= 3
