"""Bundled topologies and the errors a malformed topology file gets."""

from __future__ import annotations

from pathlib import Path

import pytest

from ucom_tools.config import topology
from ucom_tools.errors import TopologyError


@pytest.mark.parametrize("name, buses", [
    ("armar3", {"CAN0": 3, "CAN1": 3, "CAN2": 3, "CAN3": 2}),
    ("lauron4", {"CAN0": 7}),
    ("kairo2", {"CAN0": 11}),
    ("odete", {"CAN0": 3}),
    ("puma200", {"CAN0": 3}),
    ("rosi", {"CAN0": 1}),
])
def test_bundled_topologies(name: str, buses: dict[str, int]) -> None:
    topo = topology.load(name)
    assert {b.name: len(b.boards) for b in topo.buses} == buses
    serials = [x.serial for b in topo.buses for x in b.boards]
    assert len(set(serials)) == len(serials)


def test_armar3_placements_follow_table_5_2() -> None:
    topo = topology.load("armar3")
    assert [x.placement for x in topo.bus("CAN0").boards] == ["neck", "head left", "head right"]
    assert [x.placement for x in topo.bus("CAN3").boards] == ["platform", "torso base joint"]
    assert all(x.board == "3M" for b in topo.buses for x in b.boards)


GOOD = '''name = "t"

[[bus]]
name = "CAN0"

[[bus.board]]
placement = "a"
board = "3M"
'''


@pytest.mark.parametrize("text, line, key, reason", [
    (GOOD.replace('board = "3M"', 'board = "9M"'), 8, "bus[1].board[1].board",
     "unknown plug-on board"),
    (GOOD.replace('name = "CAN0"', 'name = "CAN0"\nbitrate = 333'), 5, "bus[1].bitrate",
     "expected one of"),
    (GOOD + 'fixed_id = 40\n', 9, "bus[1].board[1].fixed_id", "must be 1..31"),
    (GOOD + 'colour = "red"\n', 9, "bus[1].board[1].colour", "unknown key"),
    (GOOD.replace('placement = "a"\n', ''), 6, "bus[1].board[1].placement", "missing"),
    (GOOD + 'powered = "yes"\n', 9, "bus[1].board[1].powered", "true or false"),
    (GOOD + 'init_link = "cut"\n', 9, "bus[1].board[1].init_link", "\"ok\" or \"broken\""),
    (GOOD + 'program = "nowhere.S"\n', 9, "bus[1].board[1].program", "no such S-record"),
    ('name = "t"\n', None, "bus", "missing"),
    (GOOD + '\n[[bus]]\nname = "CAN0"\n', 11, "bus[2].name", "defined twice"),
    (GOOD.replace('name = "t"', 'name = "t"\n[timing]\nlow_water = 500'), 3,
     "timing.low_water", "low_water < high_water"),
])
def test_malformed_topology_names_file_line_and_key(tmp_path: Path, text: str,
                                                    line: int | None, key: str,
                                                    reason: str) -> None:
    path = tmp_path / "robot.toml"
    path.write_text(text)
    with pytest.raises(TopologyError) as info:
        topology.load(str(path))
    err = info.value
    assert (err.file, err.line, err.key) == (str(path), line, key)
    assert reason in err.reason
    assert str(err).startswith(f"{path}:{line}: {key}: " if line else f"{path}: {key}: ")


def test_toml_syntax_error_names_the_line(tmp_path: Path) -> None:
    path = tmp_path / "bad.toml"
    path.write_text('name = "x"\n[[bus]\n')
    with pytest.raises(TopologyError) as info:
        topology.load(str(path))
    assert info.value.line == 2


def test_missing_file_names_the_bundled_ones() -> None:
    with pytest.raises(TopologyError, match="bundled ones: armar3"):
        topology.load("armar4")


def test_board_limit_per_bus(tmp_path: Path) -> None:
    board = '[[bus.board]]\nplacement = "x"\nboard = "3M"\n'
    text = 'name = "t"\n[[bus]]\nname = "CAN0"\n' + board * 32
    path = tmp_path / "big.toml"
    path.write_text(text)
    with pytest.raises(TopologyError, match="at most 31 boards"):
        topology.load(str(path))


@pytest.mark.parametrize(("channels", "want"), [
    ([], "CAN2"), (["vcan7"], "vcan7"), (["a", "b", "c", "d"], "c")])
def test_only_one_bus_takes_its_own_channel(channels: list[str], want: str) -> None:
    from ucom_tools.ops.robot import _only
    armar3 = topology.load("armar3")
    chosen, expected = _only(armar3, "CAN2", channels)
    assert chosen == [want] and expected == [armar3.bus("CAN2")]


def test_only_one_bus_refuses_an_unknown_bus_or_a_channel_count_that_fits_nothing() -> None:
    from ucom_tools.errors import InputError
    from ucom_tools.ops.robot import _only
    armar3 = topology.load("armar3")
    with pytest.raises(InputError, match="has no bus 'CAN9'; its buses: CAN0, CAN1"):
        _only(armar3, "CAN9", [])
    with pytest.raises(InputError, match="bus CAN1 chosen with 2 channels"):
        _only(armar3, "CAN1", ["a", "b"])


def test_the_bundled_trees_are_found_in_a_checkout_or_where_a_wheel_put_them(
        tmp_path: Path) -> None:
    checkout, env = tmp_path / "checkout", tmp_path / "env"
    (checkout / "attribute_trees").mkdir(parents=True)
    (env / "share" / "ucom-tools" / "attribute_trees").mkdir(parents=True)
    assert topology.bundled_root(checkout, (str(env),)) == checkout
    installed = tmp_path / "site-packages"  # a wheel: no trees beside the package
    installed.mkdir()
    assert topology.bundled_root(installed, ("/nonexistent", str(env))) == \
        env / "share" / "ucom-tools"
    assert topology.bundled_root(installed, ("/nonexistent",)) == installed
    # this checkout: the bundled robots' trees and images are where the topologies say
    assert (topology.SOURCE_ROOT / "attribute_trees" / "armar3" / "neck.tree").is_file()
    assert (topology.SOURCE_ROOT / "firmware_images" / "armar3.fl.S").is_file()


def test_pyproject_installs_every_bundled_tree_and_image() -> None:
    import tomllib
    root = topology.SOURCE_ROOT
    data = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"][
        "data-files"]
    listed = {p for patterns in data.values() for pat in patterns for p in root.glob(pat)}
    shipped = {p for d in ("attribute_trees", "firmware_images")
               for p in (root / d).rglob("*") if p.is_file()}
    assert shipped and listed == shipped
