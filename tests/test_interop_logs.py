"""Logs that python-can's own tools read and convert right (issue 19, A.2-A.3): the
formats ucom writes are those it reads back, a format without a channel column is
refused for several buses, a PEAK trace's header names its own file, and bus names
survive ``can.logconvert`` (python-can's command line tool, run as a user runs it)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import can
import pytest
from click.testing import CliRunner, Result

from ucom_tools.cli.main import cli
from ucom_tools.trace.decode import decode_frames, read_trace
from ucom_tools.trace.logs import channel_names


def ucom(*args: str) -> Result:
    return CliRunner().invoke(cli, list(args))


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("logs")
    out = {}
    for ext in (".asc", ".trc", ".blf", ".log"):
        path = d / f"init{ext}"
        r = ucom("init", "--virtual", "armar3", "--log", str(path))
        assert r.exit_code == 0, r.stderr
        out[ext] = path
    return out


def logconvert(src: Path, dst: Path) -> None:
    r = subprocess.run([sys.executable, "-m", "can.logconvert", str(src), str(dst)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr


@pytest.mark.parametrize("source", [".asc", ".trc", ".blf"])
def test_bus_names_survive_logconvert(logs: dict[str, Path], tmp_path: Path,
                                      source: str) -> None:
    converted = tmp_path / "converted.log"
    logconvert(logs[source], converted)
    channels = {m.channel for m in can.LogReader(str(converted))}
    assert channels  # python-can's names: can0.. from .asc, can1.. from .trc
    r = ucom("decode", str(converted), "--trees", "armar3", "--bus", "CAN0", "--json")
    assert r.exit_code == 0, r.stderr
    with_robot = ucom("decode", str(converted), "--trees", "armar3", "--json")
    assert with_robot.exit_code == 0, with_robot.stderr
    assert [b["name"] for b in json.loads(with_robot.stdout)["buses"]] == \
        ["CAN0", "CAN1", "CAN2", "CAN3"]
    if source != ".trc":  # without the robot a .trc's count from 1 cannot be known
        names = sorted(b.name for b in decode_frames(read_trace(converted)).buses)
        assert names == ["CAN0", "CAN1", "CAN2", "CAN3"]


def test_the_channel_rule() -> None:
    robot = ["CAN0", "CAN1", "CAN2", "CAN3"]
    assert channel_names([0, 1, 3], robot) == {0: "CAN0", 1: "CAN1", 3: "CAN3"}
    assert channel_names(["can0", "can2"], robot) == {"can0": "CAN0", "can2": "CAN2"}
    assert channel_names(["can1", "can2", "can3", "can4"], robot) == {
        "can1": "CAN0", "can2": "CAN1", "can3": "CAN2", "can4": "CAN3"}
    assert channel_names([None], ["CAN0"]) == {None: "CAN0"}
    assert channel_names([None], robot) == {None: "CAN"}
    assert channel_names(["vcan7"], []) == {"vcan7": "CAN7"}
    assert channel_names(["left arm"], robot) == {"left arm": "left arm"}


def test_a_trc_header_names_the_final_file(logs: dict[str, Path]) -> None:
    header = logs[".trc"].read_text().splitlines()[:8]
    assert f";   {logs['.trc']}" in header
    assert not any("/." in line for line in header)


@pytest.mark.parametrize("ext", [".txt", ".txt.gz"])
def test_a_format_we_cannot_read_back_is_not_written(tmp_path: Path, ext: str) -> None:
    r = ucom("init", "--virtual", "armar3", "--log", str(tmp_path / f"x{ext}"))
    assert r.exit_code == 3 and "cannot read it back" in r.stderr
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("ext", [".csv", ".db"])
def test_a_format_without_channels_is_refused_for_several_buses(tmp_path: Path,
                                                                ext: str) -> None:
    r = ucom("init", "--virtual", "armar3", "--log", str(tmp_path / f"x{ext}"))
    assert r.exit_code == 3
    assert "has no channel column: the frames of CAN0, CAN1, CAN2, CAN3" in r.stderr
    assert list(tmp_path.iterdir()) == []
