"""``ucom gateway eds``: a robot's joints and node IDs, each joint's object dictionary, its
EDS and the bus.yml, checked by tools no one here wrote: Lely's ``dcfchk`` and ``dcfgen``
(PyPI dcf-tools) and canopen's ``import_od``."""

from __future__ import annotations

import json
import os
import re
import struct
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import canopen
import pytest
from canopen.objectdictionary import ODArray, ODRecord, ODVariable
from click.testing import CliRunner

from ucom_tools.cli.exitcodes import EXIT_BAD_INPUT, EXIT_OK
from ucom_tools.cli.main import cli
from ucom_tools.config import attrtree
from ucom_tools.config import topology as topology_mod
from ucom_tools.config.topology import SOURCE_ROOT
from ucom_tools.edgelists import armar3 as armar3_edges
from ucom_tools.edgelists.model import EdgeKind
from ucom_tools.errors import InputError, TopologyError
from ucom_tools.gateway import dictionary as od
from ucom_tools.gateway import eds, joints
from ucom_tools.gateway.joints import Role
from ucom_tools.virtual.programs import armar3_axis

BIN = Path(sys.executable).parent
ROBOTS = ("armar3", "lauron4")
TARGET = {"armar3": re.compile(r"Motor([ABC]) Target"),
          "lauron4": re.compile(r"Axis([123]) Position Setpoint")}
"""The Target edge of each program's axis (from its edge list's names)."""


@pytest.fixture(scope="module")
def robots() -> dict[str, joints.RobotJoints]:
    return {r: joints.load(r) for r in ROBOTS}


@pytest.fixture(scope="module")
def written(tmp_path_factory: pytest.TempPathFactory,
            robots: dict[str, joints.RobotJoints]) -> dict[str, Path]:
    """Each robot's files as the command writes them, one directory each."""
    out = {}
    for name in ROBOTS:
        d = tmp_path_factory.mktemp(name)
        result = CliRunner().invoke(cli, ["gateway", "eds", name, "-o", str(d)])
        assert result.exit_code == EXIT_OK, result.output
        out[name] = d
    return out


def _tool(name: str) -> str:
    path = BIN / name
    assert path.is_file(), f"{name} is missing: pip install dcf-tools (the test extra)"
    return str(path)


def _expected_axes(robot: str) -> list[tuple[str, int, str, str]]:
    """(bus, board position, axis letter, Target's unique name) of every axis whose Target
    edge the robot's trees rename, in topology order, from the trees themselves."""
    out = []
    for b in attrtree.bind(topology_mod.load(robot)).boards:
        for e in b.board.edges:
            m = TARGET[robot].fullmatch(e.generic)
            if m and e.unique != e.generic:
                axis = m.group(1)
                letter = axis if axis.isalpha() else "ABC"[int(axis) - 1]
                out.append((b.bus, b.spec.position, letter, e.unique))
    return out


# ------------------------------------------------------------------------- joints
@pytest.mark.parametrize("robot", ROBOTS)
def test_the_joints_are_the_axes_whose_target_the_trees_name(
        robot: str, robots: dict[str, joints.RobotJoints]) -> None:
    found = robots[robot].joints
    expected = _expected_axes(robot)
    assert [(j.bus, j.board.position, j.letter, j.unique(Role.TARGET)) for j in found] \
        == expected
    unused = [e for b in attrtree.bind(topology_mod.load(robot)).boards for e in b.board.edges
              if TARGET[robot].fullmatch(e.generic) and e.unique == e.generic]
    assert unused, "the robot has unused motors, which are not joints"
    assert len(found) == len(expected) and not robots[robot].skipped


def test_armar3_joint_names_are_their_target_without_the_suffix(
        robots: dict[str, joints.RobotJoints]) -> None:
    for j in robots["armar3"].joints:
        assert f"{j.name} Target" == j.unique(Role.TARGET)
        assert j.key == "_".join(j.name.lower().split())
    names = {j.name for j in robots["armar3"].joints}
    assert {"Right Eye", "Left Eye", "Upper Neck Pitch"} <= names
    assert "MotorC" not in names


def test_lauron4_legs_are_named_by_their_placement_where_names_repeat(
        robots: dict[str, joints.RobotJoints]) -> None:
    legs = robots["lauron4"].joints
    bare = [str(j.unique(Role.TARGET)).removesuffix(" Position Setpoint") for j in legs]
    for j, name in zip(legs, bare, strict=True):
        repeated = bare.count(name) > 1
        placement = " ".join(w.capitalize() for w in j.board.placement.split())
        assert j.name == (f"{placement} {name}" if repeated else name)
    assert len({j.name for j in legs}) == len(legs)
    assert len({j.key for j in legs}) == len(legs)


@pytest.mark.parametrize("robot", ROBOTS)
def test_nodes_are_numbered_in_topology_order_from_2(
        robot: str, robots: dict[str, joints.RobotJoints]) -> None:
    found = robots[robot].joints
    assert [j.node_id for j in found] == list(range(joints.FIRST_AUTO_NODE,
                                                    joints.FIRST_AUTO_NODE + len(found)))
    assert not any(j.node_given for j in found)


def test_armar3_roles_are_the_edges_its_program_drives_the_axis_with(
        robots: dict[str, joints.RobotJoints]) -> None:
    """Each role's edge is the one the armar3 program's model reads or writes for the
    axis (indices per kind, as in :mod:`ucom_tools.virtual.programs.armar3_axis`)."""
    model = {Role.COMMAND: (EdgeKind.CI, armar3_axis._COMMAND),
             Role.TARGET: (EdgeKind.CI, armar3_axis._TARGET),
             Role.TARGET_VEL: (EdgeKind.CI, armar3_axis._TARGET_VEL),
             Role.RESET_OFFSET: (EdgeKind.CI, armar3_axis._RESET_OFFSET),
             Role.JOINT_SENSOR: (EdgeKind.SO, armar3_axis._JOINT_ENCODER),
             Role.VELOCITY: (EdgeKind.SO, armar3_axis._VELOCITY),
             Role.RESET_ANSWER: (EdgeKind.SO, armar3_axis._RESET_ANSWER),
             Role.SETTLED: (EdgeKind.SO, armar3_axis._SETTLED)}
    pars = {e.name: i for i, e in enumerate(armar3_edges.SPEC.of(EdgeKind.PAR))}
    for j in robots["armar3"].joints:
        for role, (kind, indices) in model.items():
            e = j.edge(role)
            assert e is not None and (e.kind, e.index) == (kind, indices[j.axis]), role
        for role, name in ((Role.RESET_PWM, "Reset {a} PWM"),
                           (Role.MAX_VELOCITY, "Motor{a} Max Velocity (x1000)"),
                           (Role.MIN_POSITION, "Motor{a} Min Position"),
                           (Role.MAX_POSITION, "Motor{a} Max Position")):
            e = j.edge(role)
            assert e is not None and e.kind is EdgeKind.PAR
            assert e.index == pars[name.format(a=j.letter)]
        assert j.unique(Role.JOINT_SENSOR) == f"{j.name} Joint Sensor"


def test_lauron4_has_no_homing_of_its_own_and_one_mode_per_leg(
        robots: dict[str, joints.RobotJoints]) -> None:
    for j in robots["lauron4"].joints:
        assert j.edge(Role.RESET_PWM) is None
        command = j.edge(Role.COMMAND)
        assert command is not None and command.shared and command.kind is EdgeKind.CI
        d = od.build(j)
        assert d.entry(0x6502).default == int(od.SupportedModes.PP | od.SupportedModes.PV
                                              | od.SupportedModes.CSP)
        with pytest.raises(KeyError):
            d.object(0x6098)


# -------------------------------------------------------------------- dictionaries
@pytest.mark.parametrize("robot", ROBOTS)
def test_every_edge_of_the_board_is_a_manufacturer_object(
        robot: str, robots: dict[str, joints.RobotJoints]) -> None:
    trees = attrtree.bind(topology_mod.load(robot))
    base = {EdgeKind.PAR: 0x2000, EdgeKind.CI: 0x3000, EdgeKind.SO: 0x4000}
    for j in robots[robot].joints:
        d = od.build(j)
        block = trees.board(j.bus, j.board.position)
        program = j.board.program
        per_kind = dict.fromkeys(EdgeKind, 0)
        for tree_edge, spec in zip(block.edges, program.edges, strict=True):
            entry = d.entry(base[spec.kind] + per_kind[spec.kind])
            per_kind[spec.kind] += 1
            assert entry.name == tree_edge.unique
            expected_type = {(2, True): od.DataType.INTEGER16,
                             (2, False): od.DataType.UNSIGNED16,
                             (4, True): od.DataType.INTEGER32,
                             (4, False): od.DataType.UNSIGNED32}[(spec.width, spec.signed)]
            assert entry.data_type is expected_type
            assert (entry.low, entry.high) == (spec.minimum, spec.maximum)
            default = spec.default if tree_edge.default is None else \
                spec.raw(tree_edge.default.text)
            assert entry.default == default
            assert entry.access is (od.Access.RO if spec.kind is EdgeKind.SO else od.Access.RW)
        assert [o.index for o in d.objects if 0x2000 <= o.index < 0x6000] == sorted(
            b + i for k, b in base.items() for i in range(per_kind[k]))


def test_the_cia402_objects_stand_for_the_axis_edges(
        robots: dict[str, joints.RobotJoints]) -> None:
    for robot in ROBOTS:
        for j in robots[robot].joints:
            d = od.build(j)
            low, high = j.edge(Role.MIN_POSITION), j.edge(Role.MAX_POSITION)
            vmax, target = j.edge(Role.MAX_VELOCITY), j.edge(Role.TARGET)
            assert low and high and vmax and target
            assert d.entry(0x607D, 1).default == low.default
            assert d.entry(0x607D, 2).default == high.default
            assert (d.entry(0x607A).low, d.entry(0x607A).high) == (
                target.spec.minimum, target.spec.maximum)
            scale = 1000 if robot == "armar3" else 1
            assert vmax.spec.unit in ("1000 counts/s", "0.01 deg/s")
            assert d.entry(0x6081).default == vmax.default * scale
            assert d.entry(0x1008).default == j.name
            assert d.entry(0x1018, 4).default == j.board.serial
            assert d.entry(0x1018, 3).default == j.board.progid != 0
            assert d.entry(0x1400, 1).default == 0x200 + j.node_id
            assert d.entry(0x1800, 1).default == 0x180 + j.node_id
            assert d.entry(0x1014).default == 0x80 + j.node_id
            assert d.entry(0x1017).default == 100
            if robot == "armar3":
                assert d.entry(0x6502).default == 0xA5  # PP, PV, HM, CSP
                assert d.entry(0x6098).default == od.HOMING_METHOD


def test_pdos_are_mapped_as_ros2_canopen_maps_a_cia402_drive(
        robots: dict[str, joints.RobotJoints]) -> None:
    d = od.build(robots["armar3"].joints[0])

    def mapped(index: int) -> list[int]:
        n = d.entry(index, 0).default
        assert isinstance(n, int)
        return [int(d.entry(index, i).default) >> 16 for i in range(1, n + 1)]

    assert [mapped(0x1A00 + n) for n in range(4)] == [[0x6041, 0x6061], [0x6064, 0x606C],
                                                      [], []]
    assert [mapped(0x1600 + n) for n in range(4)] == [[0x6040, 0x6060], [0x607A, 0x60FF],
                                                      [], []]
    assert [d.entry(0x1800 + n, 2).default for n in range(2)] == [1, 1]
    for n in (2, 3):
        assert int(d.entry(0x1800 + n, 1).default) & 0x80000000
        assert int(d.entry(0x1400 + n, 1).default) & 0x80000000
    for index in (0x6040, 0x6060, 0x607A, 0x60FF, 0x6041, 0x6061, 0x6064, 0x606C):
        assert d.entry(index).pdo_mappable


# ----------------------------------------------------------------------------- EDS
def _compare(ours: ODVariable, theirs: ODVariable) -> None:
    for attr in ("name", "index", "subindex", "data_type", "access_type", "default", "min",
                 "max", "pdo_mappable", "relative"):
        assert getattr(theirs, attr) == getattr(ours, attr), (hex(ours.index),
                                                              ours.subindex, attr)


@pytest.mark.parametrize("robot", ROBOTS)
def test_canopen_reads_every_eds_back_as_to_canopen_builds_it(
        robot: str, robots: dict[str, joints.RobotJoints], written: dict[str, Path]) -> None:
    for j in robots[robot].joints:
        ours = od.to_canopen(od.build(j))
        theirs = canopen.import_od(str(written[robot] / f"{j.key}.eds"), j.node_id)
        assert sorted(theirs.indices) == sorted(ours.indices)
        for index in ours.indices:
            a, b = ours[index], theirs[index]
            assert type(a) is type(b) and a.name == b.name
            if isinstance(a, ODVariable):
                _compare(a, b)
                continue
            assert isinstance(a, ODArray | ODRecord) and isinstance(b, ODArray | ODRecord)
            assert sorted(a.subindices) == sorted(b.subindices)
            for sub in a.subindices:
                _compare(a[sub], b[sub])
        mine, read = ours.device_information, theirs.device_information
        for attr in ("vendor_name", "vendor_number", "product_name", "product_number",
                     "revision_number", "simple_boot_up_slave", "nr_of_RXPDO",
                     "nr_of_TXPDO", "allowed_baudrates"):
            assert getattr(read, attr) == getattr(mine, attr), attr
        assert read.granularity and mine.granularity == 8  # canopen reads it as a bool


def test_negative_values_are_decimal_and_unsigned_ones_hex(
        robots: dict[str, joints.RobotJoints], written: dict[str, Path]) -> None:
    eye = next(j for j in robots["armar3"].joints if j.name == "Right Eye")
    text = (written["armar3"] / "right_eye.eds").read_text()
    assert "0x-" not in text and "$NODEID" not in text
    reset = eye.edge(Role.RESET_PWM)
    assert reset is not None and reset.default < 0
    section = text[text.index(f"[{od.manufacturer_index(reset):04X}]"):]
    section = section[:section.index("\n\n")]
    assert f"DefaultValue={reset.default}\n" in section + "\n"
    assert f"LowLimit={reset.spec.minimum}" in section
    assert "[6040]\nParameterName=Controlword\n" in text
    assert f"DefaultValue=0x{0x180 + eye.node_id:X}" in text


def test_the_same_robot_gives_the_same_bytes(robots: dict[str, joints.RobotJoints]) -> None:
    again = joints.load("armar3")
    assert eds.render(again, dcf_path="/x") == eds.render(robots["armar3"], dcf_path="/x")


@pytest.mark.parametrize("robot", ROBOTS)
def test_lely_dcfchk_accepts_every_eds(robot: str, robots: dict[str, joints.RobotJoints],
                                       written: dict[str, Path]) -> None:
    for j in robots[robot].joints:
        for args in ([], ["-n", str(j.node_id)]):
            run = subprocess.run([_tool("dcfchk"), *args, f"{j.key}.eds"],
                                 cwd=written[robot], capture_output=True, text=True)
            assert run.returncode == 0 and not run.stderr, (j.key, run.stderr)


def _concise(path: Path) -> list[tuple[int, int, bytes]]:
    """(index, sub-index, value) of each SDO write in a concise DCF (.bin)."""
    data = path.read_bytes()
    (n,) = struct.unpack_from("<L", data)
    out, at = [], 4
    for _ in range(n):
        index, sub, size = struct.unpack_from("<HBL", data, at)
        out.append((index, sub, data[at + 7:at + 7 + size]))
        at += 7 + size
    assert at == len(data)
    return out


@pytest.mark.parametrize("robot", ROBOTS)
@pytest.mark.parametrize("remote", [False, True], ids=["local", "remote-pdo"])
def test_lely_dcfgen_builds_the_master_dcf_and_each_joints_concise_dcf(
        robot: str, remote: bool, robots: dict[str, joints.RobotJoints],
        written: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "dcf"
    out.mkdir()
    # dcfgen imports pkg_resources, which newer setuptools warn of: not a finding of dcfgen
    env = {**os.environ, "PYTHONWARNINGS": "ignore:pkg_resources is deprecated"}
    run = subprocess.run([_tool("dcfgen"), *(["-r"] if remote else []), "-d", str(out),
                          "bus.yml"], cwd=written[robot], capture_output=True, text=True,
                         env=env)
    assert run.returncode == 0 and not run.stderr, run.stderr
    master = (out / "master.dcf").read_text()
    check = subprocess.run([_tool("dcfchk"), "master.dcf"], cwd=out, capture_output=True,
                           text=True)
    assert check.returncode == 0, check.stderr
    assigned = master[master.index("[1F81Value]"):]
    slaves = dict(line.split("=") for line in assigned[:assigned.index("\n\n")].split("\n")[2:])
    assert sorted(map(int, slaves)) == sorted(j.node_id for j in robots[robot].joints)
    for j in robots[robot].joints:
        assert int(slaves[str(j.node_id)], 0) & 0x01, j.key  # NMT slave assignment: a slave
        assert f"UploadFile={written[robot].resolve() / j.key}.bin\n" in master
        writes = _concise(out / f"{j.key}.bin")
        heartbeat = [v for i, s, v in writes if (i, s) == (0x1016, 1)]
        assert heartbeat == [struct.pack("<L", eds.MASTER_NODE << 16
                                         | 3 * eds.MASTER_HEARTBEAT_MS)]
        maps = [(i, int.from_bytes(v, "little")) for i, s, v in writes
                if i in (0x1600, 0x1601, 0x1A00, 0x1A01) and s > 0]
        assert maps == [(0x1600, 0x60400010), (0x1600, 0x60600008), (0x1601, 0x607A0020),
                        (0x1601, 0x60FF0020), (0x1A00, 0x60410010), (0x1A00, 0x60610008),
                        (0x1A01, 0x60640020), (0x1A01, 0x606C0020)]
    if remote:  # the master maps each node's TPDOs 1-2 to RPDOs of its own
        assert f"NrOfRxPDO={2 * len(robots[robot].joints)}" in master


# ---------------------------------------------------------------- canopen_node
def _topology(tmp_path: Path, extra: dict[str, str]) -> Path:
    """armar3's topology in ``tmp_path`` with ``extra`` lines after a board's placement
    (by placement), its trees by absolute path."""
    text = (SOURCE_ROOT / "ucom_tools/config/topologies/armar3.toml").read_text()
    text = text.replace('tree = "attribute_trees/', f'tree = "{SOURCE_ROOT}/attribute_trees/')
    for placement, line in extra.items():
        anchor = f'placement = "{placement}"\n'
        assert anchor in text
        text = text.replace(anchor, anchor + line + "\n")
    path = tmp_path / "robot.toml"
    path.write_text(text)
    return path


def _line_of(path: Path, placement: str) -> int:
    lines = path.read_text().splitlines()
    start = lines.index(f'placement = "{placement}"')
    return start + next(i for i, s in enumerate(lines[start:], 1)
                        if s.startswith("canopen_node"))


def test_canopen_node_gives_node_ids_and_the_others_take_the_lowest_free(
        tmp_path: Path) -> None:
    path = _topology(tmp_path, {"head right": "canopen_node = { A = 40, B = 2 }",
                                "platform": "canopen_node = { C = 127 }"})
    found = joints.load(str(path)).joints
    given = {(j.board.placement, j.letter): j.node_id for j in found if j.node_given}
    assert given == {("head right", "A"): 40, ("head right", "B"): 2, ("platform", "C"): 127}
    auto = [j.node_id for j in found if not j.node_given]
    free = [n for n in range(2, 128) if n not in given.values()]
    assert auto == free[:len(auto)]
    assert [j.name for j in found] == [j.name for j in joints.load("armar3").joints]


@pytest.mark.parametrize("line, message", [
    ("canopen_node = { A = 0 }", "node ID must be 1..127, got 0"),
    ("canopen_node = { A = 128 }", "node ID must be 1..127, got 128"),
    ("canopen_node = { A = true }", "expected a node ID 1..127, got True"),
    ("canopen_node = { a = 5 }", "'a' is not an axis"),
    ("canopen_node = 5", "expected a table"),
])
def test_a_bad_canopen_node_is_refused_naming_file_and_line(
        tmp_path: Path, line: str, message: str) -> None:
    path = _topology(tmp_path, {"left belly": line})
    with pytest.raises(TopologyError, match=re.escape(message)) as err:
        joints.load(str(path))
    assert err.value.file == str(path) and err.value.line == _line_of(path, "left belly")
    assert err.value.key == "bus[3].board[3].canopen_node"


def test_a_node_id_given_twice_is_refused_at_the_second(tmp_path: Path) -> None:
    path = _topology(tmp_path, {"neck": "canopen_node = { B = 9 }",
                                "torso base joint": "canopen_node = { A = 9 }"})
    with pytest.raises(TopologyError, match="node 9 of axis A of CAN3 board 2 "
                       r"\(torso base joint\) is also axis B of CAN0 board 1 \(neck\)'s"
                       ) as err:
        topology_mod.load(str(path))
    assert err.value.line == _line_of(path, "torso base joint")


@pytest.mark.parametrize("line, message", [
    ("canopen_node = { C = 30 }", "it is no joint: .*head_left.tree does not name its Target "
     r"\('MotorC Target' keeps its generic name\)"),
    ("canopen_node = { D = 30 }", "'armar3 cascaded PID' has axes A-C"),
])
def test_a_canopen_node_for_an_axis_that_is_no_joint_is_refused(
        tmp_path: Path, line: str, message: str) -> None:
    path = _topology(tmp_path, {"head left": line})
    with pytest.raises(TopologyError, match=message) as err:
        joints.load(str(path))
    assert err.value.line == _line_of(path, "head left") and err.value.file == str(path)


def test_a_canopen_node_of_a_board_without_a_tree_is_refused(tmp_path: Path) -> None:
    path = _topology(tmp_path, {"platform": "canopen_node = { A = 30 }"})
    tree = f'tree = "{SOURCE_ROOT}/attribute_trees/armar3/platform.tree"\n'
    path.write_text(path.read_text().replace(tree, ""))
    with pytest.raises(TopologyError, match=r"node 30 for axis A of CAN3 board 1 "
                       r"\(platform\): it has no attribute tree") as err:
        joints.load(str(path))
    assert err.value.line == _line_of(path, "platform")


def test_the_cli_takes_a_topology_file_and_says_which_ids_it_gave(
        tmp_path: Path) -> None:
    path = _topology(tmp_path, {"right belly": "canopen_node = { B = 99 }"})
    result = CliRunner().invoke(cli, ["gateway", "eds", str(path), "-o",
                                      str(tmp_path / "out"), "--json"])
    assert result.exit_code == EXIT_OK, result.output
    nodes = {n["name"]: n for n in json.loads(result.stdout)["nodes"]}
    assert nodes["Right Forearm Rotate"]["node_id"] == 99 and nodes["Right Forearm Rotate"][
        "given"]
    assert [n["name"] for n in nodes.values() if n["given"]] == ["Right Forearm Rotate"]
    bus = (tmp_path / "out" / "bus.yml").read_text()
    assert "right_forearm_rotate:  # Right Forearm Rotate: CAN1 board 3 (right belly), " \
        "axis B\n  node_id: 99\n" in bus


def test_the_master_node_must_be_free(robots: dict[str, joints.RobotJoints]) -> None:
    with pytest.raises(InputError, match="node 2 is Neck Pitch's"):
        eds.bus_yml(robots["armar3"], master_node=2)


# ------------------------------------------------------------------------------ CLI
@pytest.fixture
def run() -> Iterator[CliRunner]:
    yield CliRunner()


def test_the_cli_writes_every_file_and_prints_the_node_table(
        run: CliRunner, tmp_path: Path, robots: dict[str, joints.RobotJoints]) -> None:
    out = tmp_path / "new" / "dir"
    result = run.invoke(cli, ["gateway", "eds", "armar3", "-o", str(out), "--json"])
    assert result.exit_code == EXIT_OK, result.output
    doc = json.loads(result.stdout)
    found = robots["armar3"].joints
    assert [n["node_id"] for n in doc["nodes"]] == [j.node_id for j in found]
    assert [n["name"] for n in doc["nodes"]] == [j.name for j in found]
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [f"{j.key}.eds" for j in found] + ["bus.yml"])
    assert doc["unchanged"] == [] and len(doc["written"]) == len(found) + 1
    text = run.invoke(cli, ["gateway", "eds", "armar3", "-o", str(out)])
    assert text.exit_code == EXIT_OK
    for j in found:
        assert re.search(rf"│ {j.node_id}\*? +│ {j.name} ", text.stdout), j.name
    assert f"0 files written, {len(found) + 1} unchanged" in text.stdout


def test_the_cli_refuses_to_overwrite_a_different_file_unless_forced(
        run: CliRunner, tmp_path: Path) -> None:
    assert run.invoke(cli, ["gateway", "eds", "armar3", "-o", str(tmp_path)]).exit_code == 0
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    mine = tmp_path / "bus.yml"
    mine.write_text("master:\n  node_id: 5\n")
    (tmp_path / "neck_roll.eds").unlink()
    result = run.invoke(cli, ["gateway", "eds", "armar3", "-o", str(tmp_path)])
    assert result.exit_code == EXIT_BAD_INPUT
    assert "bus.yml exists with other content; --force replaces it" in result.stderr
    assert mine.read_text() == "master:\n  node_id: 5\n"
    assert not (tmp_path / "neck_roll.eds").exists()  # all or nothing
    forced = run.invoke(cli, ["gateway", "eds", "armar3", "-o", str(tmp_path), "--force"])
    assert forced.exit_code == EXIT_OK, forced.output
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


@pytest.mark.parametrize("args, message", [
    (["no/such/robot.toml"], "no such topology file"),
    (["kairo2"], "no board of KAIRO-II has an attribute tree"),
    (["armar3", "--master-node", "5"], "node 5 is Upper Neck Pitch's"),
])
def test_the_cli_names_bad_input_and_writes_nothing(
        run: CliRunner, tmp_path: Path, args: list[str], message: str) -> None:
    out = tmp_path / "out"
    result = run.invoke(cli, ["gateway", "eds", *args, "-o", str(out)])
    assert result.exit_code == EXIT_BAD_INPUT and message in result.stderr, result.output
    assert not out.exists()


def test_the_cli_refuses_a_file_as_the_directory(run: CliRunner, tmp_path: Path) -> None:
    target = tmp_path / "file"
    target.write_text("x")
    result = run.invoke(cli, ["gateway", "eds", "armar3", "-o", str(target)])
    assert result.exit_code == EXIT_BAD_INPUT and "is not a directory" in result.stderr


def test_dcf_path_is_the_directory_unless_given(run: CliRunner, tmp_path: Path) -> None:
    assert run.invoke(cli, ["gateway", "eds", "lauron4", "-o", str(tmp_path)]).exit_code == 0
    assert f'dcf_path: "{tmp_path.resolve()}"' in (tmp_path / "bus.yml").read_text()
    other = tmp_path / "other"
    assert run.invoke(cli, ["gateway", "eds", "lauron4", "-o", str(other), "--dcf-path",
                            "", "--master-node", "127"]).exit_code == 0
    text = (other / "bus.yml").read_text()
    assert "options:" not in text and "master:\n  node_id: 127\n" in text


# ---------------------------------------------------------------------------- docs
def test_the_manual_lists_every_object_of_the_dictionaries(
        robots: dict[str, joints.RobotJoints]) -> None:
    page = (SOURCE_ROOT / "man" / "ucom-gateway.7").read_text()
    indices = {o.index for r in ROBOTS for o in od.build(robots[r].joints[0]).objects
               if not 0x2000 <= o.index < 0x6000}
    for index in indices:
        assert f"{index:04X}" in page, f"0x{index:04X}"
    ucom = (SOURCE_ROOT / "man" / "ucom.1").read_text()
    assert ".B ucom gateway eds" in ucom and "canopen_node" in ucom
