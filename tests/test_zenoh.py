"""The run time on the robot's network (issue 18): ``ucom remote run --zenoh`` and ``ucom
browse`` as real processes over loopback (and, where the machine lets us, from another
network namespace); the Python API in one process; ``man/ucom-network.7`` against the code.
Every wait has a deadline; nothing sleeps to synchronise."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from ucom_tools.net import keys
from ucom_tools.net.client import RobotClient
from ucom_tools.net.session import config

ROOT = Path(__file__).resolve().parent.parent
DEADLINE_S = 30.0
SENSOR = "Right Eye Joint Sensor"
TARGET = "Right Eye Target"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _ucom(*args: str, timeout: float = DEADLINE_S) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "ucom_tools", *args], capture_output=True,
                          text=True, timeout=timeout, cwd=ROOT)


@pytest.fixture(scope="module")
def flashed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    state = tmp_path_factory.mktemp("armar3")
    r = _ucom("flash", str(ROOT / "firmware_images/armar3.fl.S"), "--virtual", "armar3",
              "--state", str(state), timeout=180)
    assert r.returncode == 0, r.stderr
    return state


class Robot:
    """``ucom remote run armar3 --virtual armar3 --zenoh ...`` in a process of its own."""

    def __init__(self, state: Path, tmp: Path, *extra: str, host: str = "127.0.0.1",
                 prefix: tuple[str, ...] = ()) -> None:
        self.endpoint = f"tcp/{host}:{_free_port()}"
        self.state = tmp / f"state-{os.getpid()}-{id(self)}"
        shutil.copytree(state, self.state)
        self.err_path = tmp / f"robot-{id(self)}.err"
        self.out_path = tmp / f"robot-{id(self)}.out"
        with open(self.err_path, "w") as err, open(self.out_path, "w") as out:
            self.proc = subprocess.Popen(
                [*prefix, sys.executable, "-m", "ucom_tools", "remote", "run", "armar3",
                 "--virtual", "armar3", "--state", str(self.state), "--zenoh", self.endpoint,
                 *extra], stdout=out, stderr=err, cwd=ROOT,
                env={**os.environ, "PYTHONPATH": str(ROOT)})

    def client(self, timeout: float = DEADLINE_S) -> RobotClient:
        """Connected once the robot is there (its liveliness token and structure)."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                return RobotClient.connect(self.endpoint, timeout=2.0)
            except Exception:
                if self.proc.poll() is not None or time.monotonic() > deadline:
                    raise AssertionError(f"no robot on {self.endpoint}: "
                                         + self.err_path.read_text()) from None

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


@pytest.fixture(scope="module")
def robot(flashed: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Robot]:
    """A running robot that takes no writes, with a client that found it."""
    r = Robot(flashed, tmp_path_factory.mktemp("ro"))
    try:
        r.client().close()
        yield r
    finally:
        r.stop()


def test_browse_gets_a_sensor_and_the_structure(robot: Robot) -> None:
    r = _ucom("browse", "--zenoh", robot.endpoint, "--get", SENSOR, "--get", TARGET)
    assert r.returncode == 0, r.stderr
    assert re.search(rf"^{SENSOR} = -?\d+ counts$", r.stdout, re.M), r.stdout
    assert f"{TARGET} = 0 counts" in r.stdout
    r = _ucom("browse", "armar3", "--zenoh", robot.endpoint, "--json")
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)
    s = doc["structure"]
    assert s["v"] == keys.VERSION and s["robot"] == "armar3" and not s["allow_writes"]
    boards = [b for bus in s["buses"] for b in bus["boards"]]
    assert len(boards) == 11
    edge = next(e for b in boards for e in b["edges"] if e["name"] == TARGET)
    assert edge["kind"] == "CI" and edge["unit"] == "counts" and edge["writable"]
    assert edge["key"] == "ucom/armar3/CAN0/3/edge/Right Eye Target"
    assert doc["values"][SENSOR]["value"] is not None


def test_a_write_is_refused_without_allow_writes(robot: Robot) -> None:
    r = _ucom("browse", "--zenoh", robot.endpoint, "--set", f"{TARGET}=1000")
    assert r.returncode == 1, r.stderr
    assert "--allow-writes" in r.stderr
    r = _ucom("browse", "--zenoh", robot.endpoint, "--stop")
    assert r.returncode == 1 and "--allow-writes" in r.stderr


def test_a_second_loop_of_the_same_robot_is_refused(robot: Robot, flashed: Path,
                                                    tmp_path: Path) -> None:
    r = _ucom("remote", "run", "armar3", "--virtual", "armar3", "--state", str(flashed),
              "--zenoh", robot.endpoint, "--for", "0.5")
    assert r.returncode == 4, r.stderr
    assert "robot 'armar3' already runs its loop" in r.stderr
    assert f"pid {robot.proc.pid}" in r.stderr


def test_no_robot_on_the_endpoint_is_exit_4_naming_it() -> None:
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    r = _ucom("browse", "--zenoh", endpoint, "--get", SENSOR, "--timeout", "1")
    assert r.returncode == 4
    assert endpoint in r.stderr


def test_an_allowed_write_moves_the_joint_and_a_bad_one_names_the_range(
        flashed: Path, tmp_path: Path) -> None:
    robot = Robot(flashed, tmp_path, "--allow-writes")
    try:
        client = robot.client()
        try:
            r = _ucom("browse", "--zenoh", robot.endpoint, "--set", f"{TARGET}=1000")
            assert r.returncode == 0, r.stderr
            assert f"{TARGET} = 1000 counts: set" in r.stdout
            r = _ucom("browse", "--zenoh", robot.endpoint, "--set", f"{TARGET}=100000")
            assert r.returncode == 3
            assert "-32768..32767" in r.stderr
            r = _ucom("browse", "--zenoh", robot.endpoint, "--set", "Right Eye Targt=1")
            assert r.returncode == 3 and "did you mean 'Right Eye Target'" in r.stderr
            last = None
            for _t, _name, value in client.watch([SENSOR], DEADLINE_S):
                last = value
                if abs(value - 1000) <= 5:
                    break
            assert last is not None and abs(last - 1000) <= 5, last
            # killed: its liveliness token is gone within 2 s
            gone = threading.Event()
            sub = client.on_gone(gone.set)
            robot.proc.kill()
            robot.proc.wait(timeout=10)
            assert gone.wait(2.0), "the robot's liveliness token outlived its process"
            sub.close()
        finally:
            client.close()
    finally:
        robot.stop()


def test_the_python_api_shares_a_part_in_one_process(flashed: Path, tmp_path: Path) -> None:
    from ucom_tools.ops.remote import RemotePart

    state = tmp_path / "state"
    shutil.copytree(flashed, state)
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    with RemotePart.open("armar3", virtual=True, state_dir=state, zenoh=endpoint,
                         allow_writes=True, publish_hz=50) as part:
        part.run(0.05)
        answers: list[object] = []

        def remote() -> None:
            with RobotClient.connect(endpoint, timeout=10) as c:
                answers.append(c.read([TARGET]))
                answers.append(c.write(TARGET, 321))
        t = threading.Thread(target=remote)
        t.start()
        deadline = time.monotonic() + DEADLINE_S
        while t.is_alive() and time.monotonic() < deadline:
            part.cycle()
        t.join(1)
        assert not t.is_alive()
        assert answers[1] == {"v": 1, "ok": True, "done": "set", "name": TARGET,
                              "value": 321, "range": "-32768..32767 counts",
                              "unit": "counts"}
        assert part[TARGET] == 321
        assert part.writes[-1].done and "pid" in part.writes[-1].origin
        assert part.share.publish_hz == 50


def test_precompiled_samples_are_what_the_decoded_values_give(flashed: Path,
                                                             tmp_path: Path) -> None:
    """The publishing thread encodes a board's sample from precompiled parts
    (net/encode.py); it must be the same JSON document as keys.dumps of
    RemotePart.decode, for every board and every edge's own key."""
    from ucom_tools.net.encode import encoders
    from ucom_tools.ops.remote import RemotePart
    from ucom_tools.wire import mca

    state = tmp_path / "state"
    shutil.copytree(flashed, state)
    with RemotePart.open("armar3", virtual=True, state_dir=state) as part:
        part.run(0.02)
        part[TARGET] = 1234
        enc = encoders(part, "armar3")
        assert len(enc) == 11
        for _ in range(3):
            part.cycle()
            snap = part.snapshot()
            values = part.decode(snap)
            for (bus, board), e in enc.items():
                mine = {r: tv for r, tv in values.items() if (r.bus, r.board) == (bus, board)}
                stamps = [t for r, (t, _) in mine.items() if r.kind is mca.Kind.SO]
                want = {"v": keys.VERSION, "robot": "armar3", "bus": bus, "board": board,
                        "t": round(max(stamps, default=snap.clock), 6),
                        "values": {r.unique: keys.number(v) for r, (_, v) in mine.items()}}
                assert json.loads(e.sample(snap)) == want
                assert json.loads(e.sample(snap)) == want  # again, from its caches
                for r, (t, v) in mine.items():
                    assert json.loads(e.edge_sample(r, snap) or b"") == {
                        "v": keys.VERSION, "t": round(t, 6), "name": r.unique,
                        "value": keys.number(v)}
        assert any(r.spec.exponent < 0 for r in values)  # edges with decimals too


@pytest.mark.parametrize("exponent", [-1, -3, -6, 0, 2])
def test_a_value_with_decimals_is_written_as_keys_number_writes_it(exponent: int) -> None:
    from decimal import Decimal
    from types import SimpleNamespace

    from ucom_tools.net.encode import conv_of, write

    conv, _ = conv_of(SimpleNamespace(spec=SimpleNamespace(exponent=exponent)))  # type: ignore[arg-type]
    for raw in (-2**31, -12345, -1000, -5, 0, 7, 1000, 123456789, 2**32 - 1):
        assert json.loads(write(conv, raw)) == keys.number(Decimal(raw).scaleb(exponent))


def test_sessions_are_peers_without_multicast_on_loopback() -> None:
    c = config(listen=[keys.DEFAULT_ENDPOINT])
    assert json.loads(c.get_json("scouting/multicast/enabled")) is False
    assert json.loads(c.get_json("mode")) == "peer"
    assert json.loads(c.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"]


@pytest.mark.parametrize("name", ["Right Eye Target", "a/b", "50%", "*x$?#", "", "ä ö"])
def test_escaped_names_are_one_chunk_and_come_back(name: str) -> None:
    chunk = keys.escape(name)
    assert chunk and not set(chunk) & set("/*$?#")
    assert keys.unescape(chunk) == name


def test_the_network_page_names_every_key_the_code_uses() -> None:
    page = (ROOT / "man/ucom-network.7").read_text()
    section = page[page.index(".SH KEY EXPRESSIONS"):page.index(".SH PAYLOADS")]
    found = set(re.findall(r"^\.B (ucom/\S+)$", section, re.M))
    code = {k.replace("{robot}", "<robot>").replace("{bus}", "<bus>")
            .replace("{board}", "<board>").replace("{name}", "<name>")
            for k in keys.KEYS.values()}
    assert code <= found, code - found
    assert found <= code, found - code
    assert f'"v": {keys.VERSION}' in page.replace("\\(dq", '"')


def _netns_ok() -> str | None:
    if os.geteuid() != 0 or shutil.which("ip") is None:
        return "needs root and ip(8)"
    probe = subprocess.run(["ip", "netns", "add", "ucomzprobe"], capture_output=True, text=True)
    if probe.returncode != 0:
        return f"no network namespaces here: {probe.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", "ucomzprobe"], capture_output=True)
    return None


@pytest.mark.skipif(_netns_ok() is not None, reason=str(_netns_ok()))
def test_a_browser_in_another_network_namespace_reads_the_robot(flashed: Path,
                                                                tmp_path: Path) -> None:
    ns, here, there = "ucomz", "ucomz0", "ucomz1"

    def ip(*args: str) -> None:
        r = subprocess.run(["ip", *args], capture_output=True, text=True)
        assert r.returncode == 0, f"ip {' '.join(args)}: {r.stderr}"
    subprocess.run(["ip", "netns", "del", ns], capture_output=True)
    subprocess.run(["ip", "link", "del", here], capture_output=True)
    robot = None
    try:
        ip("netns", "add", ns)
        ip("link", "add", here, "type", "veth", "peer", "name", there)
        ip("link", "set", there, "netns", ns)
        ip("addr", "add", "10.231.0.1/24", "dev", here)
        ip("link", "set", here, "up")
        ip("netns", "exec", ns, "ip", "addr", "add", "10.231.0.2/24", "dev", there)
        ip("netns", "exec", ns, "ip", "link", "set", there, "up")
        ip("netns", "exec", ns, "ip", "link", "set", "lo", "up")
        robot = Robot(flashed, tmp_path, host="10.231.0.1")
        robot.client().close()
        r = subprocess.run(["ip", "netns", "exec", ns, sys.executable, "-m", "ucom_tools",
                            "browse", "--zenoh", robot.endpoint, "--get", SENSOR],
                           capture_output=True, text=True, timeout=DEADLINE_S, cwd=ROOT,
                           env={**os.environ, "PYTHONPATH": str(ROOT)})
        assert r.returncode == 0, r.stderr
        assert r.stdout.startswith(f"{SENSOR} = ")
    finally:
        if robot is not None:
            robot.stop()
        subprocess.run(["ip", "netns", "del", ns], capture_output=True)
        subprocess.run(["ip", "link", "del", here], capture_output=True)
