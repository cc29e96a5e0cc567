"""The run time on the robot's network (issue 18): ``ucom remote run --zenoh`` and ``ucom
browse`` as real processes over loopback (and, where the machine lets us, from another
network namespace); the Python API in one process; ``man/ucom-network.7`` against the code.
Every wait has a deadline; nothing sleeps to synchronise."""

from __future__ import annotations

import contextlib
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

from tests.helpers import terminate
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
        terminate(self.proc)


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


def test_every_running_boards_status_and_leds_are_shared(robot: Robot) -> None:
    seen: dict[tuple[str, int], dict[str, object]] = {}
    done = threading.Event()

    def take(doc: dict[str, object]) -> None:
        seen[(str(doc["bus"]), int(str(doc["board"])))] = doc
        if len(seen) == 11:
            done.set()
    with robot.client() as client:
        sub = client.on_status(take)
        try:
            assert done.wait(DEADLINE_S), sorted(seen)
        finally:
            sub.close()
    for doc in seen.values():  # a running program: green blinks, no CAN error
        assert doc["state"] == "RUNNING_FLASH"
        assert doc["leds"] == {"red": "off", "yellow": "off", "green": "blink"}, doc
        assert (doc["tec"], doc["rec"]) == (0, 0)


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
    from ucom_tools.net.share import open_shared

    state = tmp_path / "state"
    shutil.copytree(flashed, state)
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    with open_shared("armar3", virtual=True, state_dir=state, zenoh=endpoint,
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
    from ucom_tools.ops.remote.image import PartImage
    from ucom_tools.wire import mca

    state = tmp_path / "state"
    shutil.copytree(flashed, state)
    with RemotePart.open("armar3", virtual=True, state_dir=state) as part:
        part.run(0.02)
        part[TARGET] = 1234
        enc = encoders(PartImage.of(part), "armar3")
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
                        "values": {r.unique: keys.number(v) for r, (_, v) in mine.items()},
                        "valid": True}
                assert json.loads(e.sample(snap)) == want
                assert json.loads(e.sample(snap)) == want  # again, from its caches
                lost = json.loads(e.sample(snap, (snap.clock - 0.5, 'silence: "x"')))
                assert lost == {**want, "valid": False,
                                "lost": {"since": round(snap.clock - 0.5, 6),
                                         "seen": 'silence: "x"'}}
                for r, (t, v) in mine.items():
                    assert json.loads(e.edge_sample(r, snap) or b"") == {
                        "v": keys.VERSION, "t": round(t, 6), "name": r.unique,
                        "value": keys.number(v), "valid": True}
                    assert json.loads(e.edge_sample(r, snap, False) or b"")["valid"] is False
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


# ---------------------------------------------------------------------- faults (issue 18, 4)
BROWSER = """
import sys, threading, time
from ucom_tools.net.client import RobotClient
lock = threading.Lock()
def say(*words):
    # one whole line at a time: print() writes its words and its newline separately, so the
    # main thread's "ready" could land inside a line the subscriber's thread was printing
    with lock:
        sys.stdout.write(" ".join(map(str, words)) + "\\n")
        sys.stdout.flush()
client = RobotClient.connect(sys.argv[1], timeout=30)
client.on_alive(lambda up: say("back" if up else "lost", time.monotonic()))
client.subscribe([sys.argv[2]], lambda t, n, v: say("value", t, v))
say("ready")
sys.stdin.read()
client.close()
"""


class Lines:
    """A process's stdout lines as they come, waited for with deadlines."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        self.proc = proc
        self.lines: list[str] = []
        self._cond = threading.Condition()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            with self._cond:
                self.lines.append(line.strip())
                self._cond.notify_all()
        with self._cond:
            self.lines.append("<eof>")
            self._cond.notify_all()

    def wait(self, start: int, word: str, timeout: float) -> int:
        """The index of the first line from ``start`` beginning with ``word``."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                for i in range(start, len(self.lines)):
                    if self.lines[i].split(" ", 1)[0] == word:
                        return i
                left = deadline - time.monotonic()
                if left <= 0 or "<eof>" in self.lines[start:]:
                    raise AssertionError(f"no {word!r} line within {timeout:g} s: "
                                         f"{self.lines[start:][-5:]}")
                self._cond.wait(left)

    def board_time(self, i: int) -> float:
        """The board time of the ``value`` line ``i`` (the robot's clock, in seconds)."""
        return float(self.lines[i].split()[1])


def _ip(*args: str) -> None:
    r = subprocess.run(["ip", *args], capture_output=True, text=True)
    assert r.returncode == 0, f"ip {' '.join(args)}: {r.stderr}"


@pytest.fixture
def two_hosts() -> Iterator[tuple[list[str], list[str], str, str]]:
    """Two network namespaces (the robot's host, the browser's) joined by a veth pair:
    (the robot's ``ip netns exec`` prefix, the browser's, the robot's address, the
    robot's end of the link).  Names unique to this process; removed afterwards."""
    why = _netns_ok()
    if why is not None:
        pytest.skip(f"two hosts need network namespaces: {why}")
    tag = f"{os.getpid() % 100000}"
    robot_ns, browser_ns = f"uzr{tag}", f"uzb{tag}"
    robot_dev, browser_dev = f"uzr{tag}", f"uzb{tag}"
    subnet = f"10.{233 + os.getpid() % 20}.{os.getpid() // 20 % 250}"
    try:
        _ip("netns", "add", robot_ns)
        _ip("netns", "add", browser_ns)
        _ip("link", "add", robot_dev, "netns", robot_ns, "type", "veth", "peer", "name",
            browser_dev, "netns", browser_ns)
        for ns, dev, host in ((robot_ns, robot_dev, 1), (browser_ns, browser_dev, 2)):
            _ip("-n", ns, "addr", "add", f"{subnet}.{host}/24", "dev", dev)
            _ip("-n", ns, "link", "set", dev, "up")
            _ip("-n", ns, "link", "set", "lo", "up")
        yield (["ip", "netns", "exec", robot_ns], ["ip", "netns", "exec", browser_ns],
               f"{subnet}.1", robot_dev)
    finally:
        for ns in (robot_ns, browser_ns):  # the veth pair goes with its namespaces
            pids = subprocess.run(["ip", "netns", "pids", ns], capture_output=True,
                                  text=True).stdout.split()
            for pid in pids:  # nothing outlives the test in a namespace nobody sees
                with contextlib.suppress(ProcessLookupError, ValueError):
                    os.kill(int(pid), signal.SIGKILL)
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)


def _robot_report(robot: Robot) -> dict[str, object]:
    robot.stop()
    doc = json.loads(robot.out_path.read_text())
    assert isinstance(doc, dict)
    return doc


def test_the_link_down_for_5_s_the_loop_goes_on_and_the_browser_recovers(
        flashed: Path, tmp_path: Path,
        two_hosts: tuple[list[str], list[str], str, str]) -> None:
    robot_ns, browser_ns, address, robot_dev = two_hosts
    robot = Robot(flashed, tmp_path, "--json", host=address, prefix=tuple(robot_ns))
    browser = subprocess.Popen([*browser_ns, sys.executable, "-c", BROWSER, robot.endpoint,
                                SENSOR], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                               text=True, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    try:
        out = Lines(browser)
        first = out.wait(out.wait(0, "ready", DEADLINE_S), "value", 10)
        down = time.monotonic()
        before = len(out.lines)  # every value received before the outage is in there
        _ip("-n", robot_ns[-1], "link", "set", robot_dev, "down")
        try:
            lost = out.wait(first, "lost", 5.0)  # the lease (3 s) within the 5 s
        finally:
            left = 5.0 - (time.monotonic() - down)
            if left > 0:
                time.sleep(left)  # the scenario: the link stays down 5 s
            _ip("-n", robot_ns[-1], "link", "set", robot_dev, "up")
        up = time.monotonic()
        back = out.wait(lost, "back", 10.0)
        after = out.wait(back, "value", 5.0)
        # a fresh value, not one from before the outage: newer on the robot's clock than
        # every value received before the link went down.  (Not by so many seconds: the
        # robot's fleet runs in virtual time, whose pace is not the wall clock's; seen at
        # 0.4 of it on a loaded machine and at 1.2 with the compiled run time, and nearly
        # still while the link was down.)
        newest = max(out.board_time(i) for i in range(before)
                     if out.lines[i].startswith("value "))
        assert out.board_time(after) > newest, (newest, out.lines[first:after + 1])
        assert time.monotonic() - up < 10
    finally:
        if browser.stdin is not None:
            browser.stdin.close()
        try:
            browser.wait(timeout=10)
        except subprocess.TimeoutExpired:
            browser.kill()
        robot.stop()  # also when the test failed: not a loop left in a deleted namespace
    doc = _robot_report(robot)
    run = doc["run"]
    assert isinstance(run, dict)
    # virtual time: the loop's cycles followed the boards' clock the whole time, and not
    # one board's watchdog stopped it (the boards kept running)
    assert run["missed"] == 0, run
    assert not [e for e in doc["events"] if "watchdog" in json.dumps(e)], doc["events"]


@pytest.fixture(scope="module")
def writable(flashed: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Robot]:
    """A running robot that takes writes (--allow-writes)."""
    r = Robot(flashed, tmp_path_factory.mktemp("rw"), "--allow-writes")
    try:
        r.client().close()
        yield r
    finally:
        r.stop()


WRITER = """
import sys
from ucom_tools.net.client import RobotClient
client = RobotClient.connect(sys.argv[1], timeout=30)
print("ready", flush=True)
k = 0
while True:  # writes back to back: a kill -9 comes in the middle of one
    client.write(sys.argv[2], 500 + k % 100)
    k += 1
    print("wrote", k, flush=True)
"""


def test_a_browser_killed_mid_write_leaves_the_robot_and_the_next_writer_fine(
        writable: Robot) -> None:
    writer = subprocess.Popen([sys.executable, "-c", WRITER, writable.endpoint, TARGET],
                              stdout=subprocess.PIPE, text=True, cwd=ROOT,
                              env={**os.environ, "PYTHONPATH": str(ROOT)})
    try:
        out = Lines(writer)
        out.wait(out.wait(0, "ready", DEADLINE_S), "wrote", 10)
        out.wait(len(out.lines), "wrote", 10)  # writing on, one write after another
    finally:
        writer.kill()  # SIGKILL, between sending a query and taking its answer
        writer.wait(timeout=10)
    with writable.client() as client:
        assert client.alive()
        answer = client.write(TARGET, 777)
        assert answer["ok"] and answer["value"] == 777
        t0 = client.read([SENSOR])[SENSOR][0]
        deadline = time.monotonic() + 10
        while client.read([SENSOR])[SENSOR][0] <= t0:  # the boards run on
            assert time.monotonic() < deadline, "no new sensor value after the kill"
    r = _ucom("browse", "--zenoh", writable.endpoint, "--set", f"{TARGET}=778")
    assert r.returncode == 0, r.stderr
    assert writable.proc.poll() is None
    assert "Traceback" not in writable.err_path.read_text()


def test_malformed_requests_from_a_raw_zenoh_client_are_answered_with_errors(
        writable: Robot) -> None:
    import zenoh

    with writable.client() as client:
        client.write(TARGET, 100)  # a known value before
    session = zenoh.open(config(connect=[writable.endpoint], connect_timeout_s=10))
    events: list[dict[str, object]] = []
    last = threading.Event()

    def on_event(sample: zenoh.Sample) -> None:
        events.append(json.loads(sample.payload.to_bytes()))
        if events[-1].get("value") == "101":
            last.set()
    sub = session.declare_subscriber("ucom/armar3/events", on_event)

    def ask(key: str, payload: bytes) -> list[tuple[bool, dict[str, object]]]:
        out = []
        for r in session.get(key, payload=payload, timeout=5.0):
            reply = r.ok if r.ok is not None else r.err
            assert reply is not None
            assert str(reply.encoding).startswith("application/json")
            out.append((r.ok is not None, json.loads(reply.payload.to_bytes())))
        return out

    try:
        bad = [b"not json", b"\xff\xfe", b"[1, 2]", b'{"v": 2, "name": "x", "value": 1}',
               b'{"v": 1, "name": 5, "value": 1}', b'{"v": 1, "name": "x", "value": [1]}',
               b'{"v": 1, "name": "Right Eye Target", "value": true}']
        for payload in bad:
            answers = ask("ucom/armar3/set", payload)
            assert len(answers) == 1 and not answers[0][0], (payload, answers)
            assert answers[0][1]["error"] == "refused", (payload, answers)
        for name, value, why in (("No Such Edge", 1, "no edge called"),
                                 ("Right Eye Joint Sensor", 1, ""),
                                 (TARGET, 1e400, "")):
            doc = json.dumps({"v": 1, "name": name, "value": value, "origin": "raw"})
            answers = ask("ucom/armar3/set", doc.encode())
            assert len(answers) == 1 and not answers[0][0], (name, answers)
            assert answers[0][1]["error"] == "refused" and why in str(answers[0][1]["message"])
        # samples put where the robot only publishes, and keys it does not have: nothing
        session.put("ucom/armar3/set", b"garbage")
        session.put("ucom/armar3/CAN0/3/edge/Right Eye Target", b'{"v":1,"value":5}')
        session.put("ucom/armar3/CAN0/3/values", b"\x00")
        assert ask("ucom/armar3/no/such/key", b"{}") == []
        with writable.client() as client:  # and the robot is as it was
            assert client.read([TARGET])[TARGET][1] == 100
            assert client.write(TARGET, 101)["ok"]
        assert last.wait(5.0), events
        kinds = {(e["kind"], e.get("result") == "done") for e in events}
        assert kinds <= {("write", True), ("write", False)}, events  # no stop, no error
        assert writable.proc.poll() is None
    finally:
        sub.undeclare()
        session.close()


def test_a_browser_in_another_network_namespace_reads_the_robot(
        flashed: Path, tmp_path: Path,
        two_hosts: tuple[list[str], list[str], str, str]) -> None:
    robot_ns, browser_ns, address, _ = two_hosts
    robot = Robot(flashed, tmp_path, host=address, prefix=tuple(robot_ns))
    try:
        r = subprocess.run([*browser_ns, sys.executable, "-m", "ucom_tools", "browse",
                            "--zenoh", robot.endpoint, "--get", SENSOR, "--timeout", "20"],
                           capture_output=True, text=True, timeout=DEADLINE_S, cwd=ROOT,
                           env={**os.environ, "PYTHONPATH": str(ROOT)})
        assert r.returncode == 0, r.stderr + robot.err_path.read_text()
        assert r.stdout.startswith(f"{SENSOR} = ")
    finally:
        robot.stop()
