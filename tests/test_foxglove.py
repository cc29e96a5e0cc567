"""The run time live in Foxglove (issue 36, part 2): ``remote run --foxglove`` and ``browse
--foxglove`` as real processes over loopback, read by a client no one here wrote
(``@foxglove/ws-protocol`` with ``ws``, under node: ``tests/foxglove_client.cjs``),
installed by npm into a cache of this machine's temporary directory keyed by their
versions.  Where node or the npm registry is missing, the client's tests skip and say
which.  Every wait has a deadline; nothing sleeps to synchronise."""

from __future__ import annotations

import base64
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.helpers import terminate
from ucom_tools.errors import InputError
from ucom_tools.protocol.traffic import EXTENDED, SENT
from ucom_tools.trace import mcapfile
from ucom_tools.viewers import foxglove_msgs as fm

from .test_zenoh import DEADLINE_S, _free_port, flashed  # noqa: F401

ROOT = Path(__file__).resolve().parent.parent
CLIENT = Path(__file__).resolve().parent / "foxglove_client.cjs"
PACKAGES = ("@foxglove/ws-protocol@0.8.0", "ws@8.23.1")
NODE = shutil.which("node") or ("/usr/bin/node" if os.path.exists("/usr/bin/node") else None)


@pytest.fixture(scope="module")
def node_modules() -> Path:
    """The client's packages, installed once per version into the temporary directory."""
    if NODE is None:
        pytest.skip("node is not installed here: the Foxglove client runs under node")
    npm = shutil.which("npm")
    if npm is None:
        pytest.skip("npm is not installed here: it installs the Foxglove client")
    key = "-".join(p.replace("/", "+").replace("@", "") for p in PACKAGES)
    home = Path(tempfile.gettempdir()) / f"ucom-test-node-{key}"
    if not (home / "node_modules" / "@foxglove" / "ws-protocol").is_dir():
        work = Path(tempfile.mkdtemp(prefix=home.name + ".", dir=home.parent))
        try:
            r = subprocess.run([npm, "install", "--prefix", str(work), "--no-audit",
                                "--no-fund", "--no-save", *PACKAGES], capture_output=True,
                               text=True, timeout=240)
        except subprocess.TimeoutExpired:
            shutil.rmtree(work, ignore_errors=True)
            pytest.skip("npm did not install the Foxglove client within 240 s (no registry?)")
        if r.returncode != 0:
            shutil.rmtree(work, ignore_errors=True)
            pytest.skip("npm could not install the Foxglove client (no registry here?): "
                        + (r.stderr.strip().splitlines() or ["?"])[-1])
        try:
            work.rename(home)  # whole or not at all: another run may have been first
        except OSError:
            shutil.rmtree(work, ignore_errors=True)
    return home / "node_modules"


def _ucom(*args: str, timeout: float = DEADLINE_S) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "ucom_tools", *args], capture_output=True,
                          text=True, timeout=timeout, cwd=ROOT)


class Served:
    """A ``ucom`` process that serves Foxglove on a free loopback port."""

    def __init__(self, tmp: Path, *args: str) -> None:
        self.port = _free_port()
        self.url = f"ws://127.0.0.1:{self.port}"
        self.out, self.err = tmp / f"out-{self.port}", tmp / f"err-{self.port}"
        with open(self.out, "w") as out, open(self.err, "w") as err:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "ucom_tools", *args, "--foxglove",
                 f"127.0.0.1:{self.port}"], stdout=out, stderr=err, cwd=ROOT,
                env={**os.environ, "PYTHONPATH": str(ROOT)}, text=True)

    def wait_listening(self) -> None:
        deadline = time.monotonic() + DEADLINE_S
        while True:
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=1.0).close()
                return
            except OSError:
                assert time.monotonic() < deadline, self.err.read_text()
                try:  # a pause between tries that ends at once where the process ended
                    code = self.proc.wait(timeout=0.05)
                except subprocess.TimeoutExpired:
                    continue
                raise AssertionError(f"ended, exit {code}: {self.err.read_text()}") from None

    def result(self) -> dict[str, Any]:
        assert self.proc.wait(DEADLINE_S * 2) == 0, self.err.read_text()
        return dict(json.loads(self.out.read_text()))


def _client(node_modules: Path, url: str, seconds: float, *args: str) -> list[dict[str, Any]]:
    assert NODE is not None
    r = subprocess.run([NODE, str(CLIENT), url, str(seconds), *args], capture_output=True,
                       text=True, timeout=seconds + DEADLINE_S,
                       env={**os.environ, "NODE_PATH": str(node_modules)})
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr
    return [json.loads(line) for line in r.stdout.splitlines()]


def _messages(lines: list[dict[str, Any]], topic: str) -> list[dict[str, Any]]:
    return [d for d in lines if d.get("topic") == topic]


def _run(state: Path, tmp: Path, *extra: str) -> Served:
    copy = tmp / f"state-{time.monotonic_ns()}"
    shutil.copytree(state, copy)
    return Served(tmp, "remote", "run", "armar3", "--virtual", "armar3", "--state",
                  str(copy), "--json", *extra)


@pytest.fixture
def tmp(tmp_path: Path) -> Iterator[Path]:
    yield tmp_path


# ---------------------------------------------------------------------- with the client
def test_a_foxglove_client_plots_the_joints_and_frames_and_sets_the_right_eye(
        flashed: Path, tmp: Path, node_modules: Path) -> None:  # noqa: F811
    run = _run(flashed, tmp, "--for", "12", "--allow-writes")
    try:
        run.wait_listening()
        lines = _client(node_modules, run.url, 5, "/joints", "/CAN0/frames",
                        "/Eyes/values", "/events", "/set", "--set", "Right Eye Target=1000",
                        "--set", "Right Eye Joint Sensor=5")
    except BaseException:
        terminate(run.proc)
        raise
    doc = run.result()
    ads = {d["advertise"]["topic"]: d["advertise"] for d in lines if "advertise" in d}
    assert ads["/joints"]["schemaName"] == "foxglove.JointStates"
    assert ads["/events"]["schemaName"] == "foxglove.Log"
    assert ads["/CAN0/frames"]["schemaName"] == "ucom.CanFrame"
    # a schema for the Publish panel's writes (Lichtblick flags a name it does not know)
    assert ads["/set"]["schemaName"] == "ucom.Set"
    assert json.loads(ads["/set"]["schema"]) == fm.SET_SCHEMA
    # the schemas and topics of a recording (--record run.mcap): one layout for both
    assert json.loads(ads["/CAN0/frames"]["schema"]) == mcapfile.FRAME_SCHEMA
    assert json.loads(ads["/joints"]["schema"]) == mcapfile.JOINTS_SCHEMA
    assert ads["/Eyes/values"]["schemaName"] == "ucom.Values.Eyes"
    assert {"/CAN1/frames", "/CAN3/frames", "/LeftWrist/values", "/Torso/values"} <= set(ads)

    # the frames: whole, stamped, both ways
    frames = _messages(lines, "/CAN0/frames")
    assert len(frames) >= 100
    directions = set()
    for f in frames:
        m = f["message"]
        assert set(m) == set(mcapfile.FRAME_SCHEMA["required"])
        assert len(base64.b64decode(m["data"])) == m["dlc"]
        assert 0 <= m["id"] < 2**11 and not m["extended"] and not m["error"]
        directions.add(m["direction"])
    assert directions == {"rx", "tx"}
    times = [m["message"]["time"] for m in frames]
    assert times == sorted(times)
    # one mapping of the bus time to the wall clock for every frame
    offsets = {int(f["log_time"]) - round(f["message"]["time"] * 1e9) for f in frames}
    assert max(offsets) - min(offsets) <= 1000

    # the joints follow the target the client set, as the run's own values say
    joints = [{j["name"]: j for j in m["message"]["joints"]}
              for m in _messages(lines, "/joints")]
    assert len(joints[-1]) == 27 and "Right Eye" in joints[-1]
    assert abs(joints[-1]["Right Eye"]["position"] - 1000) <= 2
    assert joints[0]["Right Eye"]["position"] == 0
    values = [m["message"] for m in _messages(lines, "/Eyes/values")]
    assert all(v["valid"] for v in values)
    assert {"time", "Right_Eye_Target", "Right_Eye_Joint_Sensor"} <= set(values[-1])
    assert values[-1]["Right_Eye_Target"] == 1000
    seen = {v["Right_Eye_Joint_Sensor"] for v in values}
    assert joints[-1]["Right Eye"]["position"] in seen
    final = {e["name"]: e["value"] for b in doc["boards"] for e in b["edges"]}
    assert final["Right Eye Target"] == 1000
    assert abs(final["Right Eye Joint Sensor"] - 1000) <= 2

    # the writes went through the loop as a local --set does, and each is an event once
    # (the one the loop refused too: the loop's event, not the server's again)
    writes = {(w["name"], w["value"]): w for w in doc["writes"]}
    assert set(writes) == {("Right Eye Target", "1000"), ("Right Eye Joint Sensor", "5")}
    assert writes[("Right Eye Target", "1000")]["result"] == "done"
    assert "only CI/PAR edges can be set" in writes[("Right Eye Joint Sensor", "5")]["result"]
    assert all(w["origin"].startswith("foxglove client ") for w in doc["writes"])
    events = [m["message"]["message"] for m in _messages(lines, "/events")]
    done = [e for e in events if e.startswith("set Right Eye Target = 1000 from foxglove")]
    assert len(done) == 1 and done[0].endswith(": done"), events
    refused = [e for e in events if "Right Eye Joint Sensor = 5" in e]
    assert len(refused) == 1 and "only CI/PAR edges can be set" in refused[0], events
    # named as a recording's /events names them
    assert {m["message"]["name"] for m in _messages(lines, "/events")
            if " from foxglove client " in m["message"]["message"]} == {"writes"}
    # the server's /set: the write it applied
    assert [m["message"] for m in _messages(lines, "/set")] == \
        [{"name": "Right Eye Target", "value": 1000}]

    # only what the client subscribed to was encoded, and its sockets had TCP_NODELAY
    served = doc["foxglove"]
    assert set(served["encoded"]) == {"/joints", "/CAN0/frames", "/Eyes/values",
                                      "/events", "/set"}
    assert served["encoded"]["/CAN0/frames"] >= len(frames)
    # handed over while watched: every bus's (the loop does not sort them by bus)
    assert served["frames_received"] >= served["encoded"]["/CAN0/frames"]
    assert served["writes_applied"] == 1 and served["writes_refused"] == 1
    assert served["nodelay_sockets"] >= 1


def test_without_allow_writes_a_clients_write_is_refused_and_said(
        flashed: Path, tmp: Path, node_modules: Path) -> None:  # noqa: F811
    run = _run(flashed, tmp, "--for", "8")
    try:
        run.wait_listening()
        lines = _client(node_modules, run.url, 3, "/Eyes/values", "/events",
                        "--set", "Right Eye Target=1000", "--param", "Left Eye Target=50")
    except BaseException:
        terminate(run.proc)
        raise
    doc = run.result()
    assert doc["writes"] == []
    statuses = [d["status"]["message"] for d in lines if "status" in d]
    assert any("Right Eye Target = 1000" in s and "--allow-writes" in s for s in statuses)
    events = [m["message"] for m in _messages(lines, "/events")]
    assert any("refused" in e["message"] and e["level"] == fm.LOG_WARNING for e in events)
    assert sum("Right Eye Target = 1000" in e["message"] for e in events) == 1
    assert [p for d in lines if "parameterValues" in d for p in d["parameterValues"]] == \
        [{"name": "Left Eye Target", "value": 0}]  # as it is: not set
    values = [m["message"] for m in _messages(lines, "/Eyes/values")]
    assert values[-1]["Right_Eye_Target"] == 0
    assert doc["foxglove"]["writes_refused"] == 2
    assert set(doc["foxglove"]["encoded"]) <= {"/Eyes/values", "/events"}
    assert doc["foxglove"]["frames_received"] == 0  # no client watched a bus's frames


def test_browse_serves_a_shared_robot_to_foxglove(
        flashed: Path, tmp: Path, node_modules: Path) -> None:  # noqa: F811
    from .test_zenoh import Robot

    robot = Robot(flashed, tmp, "--allow-writes")
    try:
        robot.client().close()
        browse = Served(tmp, "browse", "--zenoh", robot.endpoint, "--for", "8",
                        "--allow-writes", "--json")
        try:
            browse.wait_listening()
            lines = _client(node_modules, browse.url, 4, "/joints", "/Eyes/values",
                            "--set", "Right Eye Target=800")
        except BaseException:
            terminate(browse.proc)
            raise
        doc = browse.result()
    finally:
        robot.stop()
    joints = [{j["name"]: j for j in m["message"]["joints"]}
              for m in _messages(lines, "/joints")]
    assert abs(joints[-1]["Right Eye"]["position"] - 800) <= 2
    values = [m["message"] for m in _messages(lines, "/Eyes/values")]
    assert values[-1]["Right_Eye_Target"] == 800
    assert doc["foxglove"]["writes_applied"] == 1
    ads = {d["advertise"]["topic"] for d in lines if "advertise" in d}
    assert "/CAN0/frames" not in ads  # the frames stay on the robot's host


# ---------------------------------------------------------------------- no client
def test_nothing_is_encoded_while_no_client_subscribes(flashed: Path,  # noqa: F811
                                                       tmp: Path) -> None:
    run = _run(flashed, tmp, "--for", "1")
    doc = run.result()
    served = doc["foxglove"]
    assert served["encoded_total"] == 0 and served["encoded"] == {}
    assert served["url"] == f"ws://127.0.0.1:{run.port}"
    assert "Right Eye" in served["joints"] and served["frames_dropped"] == 0
    assert served["frames_received"] == 0  # nobody watches them: the loop keeps them


def test_a_port_in_use_ends_the_run_before_the_boards_start(flashed: Path,  # noqa: F811
                                                            tmp: Path) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        r = _ucom("remote", "run", "armar3", "--virtual", "armar3", "--state",
                  str(flashed), "--for", "1", "--foxglove", f"127.0.0.1:{port}")
    assert r.returncode == 4, r.stderr
    assert f"the Foxglove server on 127.0.0.1:{port}: cannot serve there" in r.stderr
    assert "in use" in r.stderr and "Traceback" not in r.stderr
    assert "cycles at" not in r.stdout + r.stderr  # the loop never ran


@pytest.mark.parametrize("address", ["8765", "localhost:", "127.0.0.1:70000", ":8765",
                                     "a b:1"])
def test_a_bad_address_is_refused_before_anything_starts(address: str) -> None:
    r = _ucom("remote", "run", "armar3", "--virtual", "armar3", "--for", "1",
              "--foxglove", address)
    assert r.returncode == 3, r.stderr
    assert "--foxglove" in r.stderr and "HOST:PORT" in r.stderr
    r = _ucom("browse", "--foxglove", address)
    assert r.returncode == 3 and "HOST:PORT" in r.stderr, r.stderr


# ---------------------------------------------------------------------- the messages
def test_addresses_parse() -> None:
    assert fm.parse_address("127.0.0.1:8765") == ("127.0.0.1", 8765)
    assert fm.parse_address("[::1]:0") == ("::1", 0)
    assert fm.parse_address("robot-pc:9000") == ("robot-pc", 9000)
    with pytest.raises(InputError, match="HOST:PORT"):
        fm.parse_address("::1")


def test_a_frame_message_is_the_json_of_its_schema() -> None:
    doc = json.loads(fm.frame_json((0x1A5, b"\x01\x02\xff", 12.5, SENT | EXTENDED)))
    assert doc == {"time": 12.5, "id": 0x1A5, "extended": True, "remote": False,
                   "error": False, "direction": "tx", "dlc": 3,
                   "data": base64.b64encode(b"\x01\x02\xff").decode()}
    assert set(doc) == set(fm.FRAME_SCHEMA["properties"])


def test_the_bus_time_is_mapped_once_to_the_wall_clock() -> None:
    clock = fm.WallClock()
    before = time.time()
    clock.anchor(100.0, time.monotonic())
    after = time.time()
    clock.anchor(5000.0)  # only the first counts
    assert before * 1e9 - 1e6 <= clock.ns(100.0) <= after * 1e9 + 1e6
    assert clock.ns(101.5) - clock.ns(100.0) == pytest.approx(1.5e9, abs=1e3)
    wall = fm.WallClock()  # a bus time base that is the wall clock already: kept as it is
    wall.anchor(time.time() - 0.2)
    assert wall.ns(1_700_000_000.5) == 1_700_000_000_500_000_000
