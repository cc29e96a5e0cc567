"""The loop's state for everyone else (issue 34, part 4): one hand-over
(``ops/remote/publish.py``) that the live view, ``--record`` and the Zenoh share read,
never the loop's live structures; the consumers of ``ucom remote run`` in a process of
their own (``ops/remote/feed.py`` -> ``ops/remote/mirror.py``); a lost board's values
stale wherever they are shown.  In process and in virtual time, over the real code path;
the command itself where the consumers' process is what is tested."""

from __future__ import annotations

import contextlib
import csv
import json
import math
import os
import re
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from click.testing import CliRunner

from tests.runtime_rig import programmed, robot_of
from ucom_tools.cli.main import cli
from ucom_tools.config.attrtree.robot import bind
from ucom_tools.config.scenario import FaultKind, InjectedFault
from ucom_tools.ops.remote import RemotePart
from ucom_tools.ops.remote.feed import LoopFeed
from ucom_tools.ops.remote.loop import RECENT_SAMPLES
from ucom_tools.ops.remote.mirror import Mirror
from ucom_tools.ops.remote.publish import LoopHandover, LoopSnapshot
from ucom_tools.virtual.fleet import Fleet

ROOT = Path(__file__).resolve().parent.parent
EYES = ("CAN0", 3)
SENSOR = "Right Eye Joint Sensor"
DEADLINE_S = 30.0


@pytest.fixture
def running() -> Iterator[tuple[Fleet, RemotePart]]:
    fleet = programmed("armar3")
    robot = robot_of(fleet)
    part = RemotePart(robot, bind(robot.topology), on_fault="hold")
    try:
        part.start()
        yield fleet, part
    finally:
        part.close()
        robot.close()


def power_off(fleet: Fleet, seconds: float = 10.0) -> None:
    fleet.inject(InjectedFault(FaultKind("power-off"), *EYES, for_s=seconds))


def until_lost(part: RemotePart, limit_s: float = 1.0) -> None:
    end = part._clock() + limit_s
    while EYES not in part.lost:
        assert part._clock() < end, part.faults
        part.cycle()


@pytest.fixture
def fast_switching() -> Iterator[None]:
    """Python hands its lock from thread to thread as often as it can: a reader that
    could see the loop's structures half-changed does, within a few hundred reads."""
    before = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    try:
        yield
    finally:
        sys.setswitchinterval(before)


# ---------------------------------------------------------------------- the hand-over
def test_the_live_view_renders_on_its_thread_while_the_loop_runs(running,
                                                                 fast_switching) -> None:
    """Its figures (lateness percentiles over the last cycles) came from the loop's own
    lateness deque: 'RuntimeError: deque mutated during iteration' within the first
    few hundred renders (the view of the main branch, rendered the same way: every time
    within a second).  From the hand-over's snapshots: never."""
    from ucom_tools.cli.live import LiveView

    _, part = running
    view = LiveView.local(part)
    errors: list[BaseException] = []
    renders = 0
    done = threading.Event()

    def reader() -> None:
        nonlocal renders
        try:
            while renders < 300:
                if "cycles" in view.render(200):  # (not 'starting ...')
                    renders += 1
        except BaseException as err:
            errors.append(err)
        finally:
            done.set()

    thread = threading.Thread(target=reader)
    thread.start()
    deadline = time.monotonic() + DEADLINE_S
    while not done.is_set() and time.monotonic() < deadline:
        part.cycle()
    thread.join()
    assert not errors, repr(errors[0])
    assert renders == 300 and part.stats.cycles > 300


def test_snapshots_read_by_many_threads_are_whole_and_never_change(running,
                                                                   fast_switching) -> None:
    _, part = running
    handover = LoopHandover.of(part, 1000.0)  # a snapshot every cycle
    bad: list[str] = []
    kept: list[tuple[LoopSnapshot, dict[str, dict[int, bytes]], int, int]] = []
    stop = threading.Event()

    def reader() -> None:
        last, keep = 0, 0
        while not stop.is_set():
            snap = handover.latest
            if snap is None:
                continue
            f = snap.figures
            if snap.number < last:
                bad.append(f"snapshot {snap.number} after {last}")
            last = snap.number
            if len(f.recent()) != min(f.cycles, RECENT_SAMPLES):
                bad.append(f"{len(f.recent())} lateness samples for {f.cycles} cycles")
            if snap.number >= keep:  # one now and then, to look at again at the end
                keep = snap.number + 50
                kept.append((snap, {b: dict(m) for b, m in snap.values.frames.items()},
                             snap.events_total, f.cycles))

    readers = [threading.Thread(target=reader) for _ in range(4)]
    for r in readers:
        r.start()
    part.run(0.5)
    stop.set()
    for r in readers:
        r.join()
    assert not bad, bad[:3]
    assert kept
    for snap, frames, events, cycles in kept:  # as the loop published them, still
        assert {b: dict(m) for b, m in snap.values.frames.items()} == frames
        assert (snap.events_total, snap.figures.cycles) == (events, cycles)
    assert part.decode(kept[-1][0].values)  # values made of it on any thread


def test_a_handover_nobody_reads_takes_no_snapshots(running) -> None:
    """What the loop pays when nothing consumes: a countdown (benchmarks/consumers.py
    measures it); snapshots while someone read one within the last second."""
    _, part = running
    handover = LoopHandover.of(part, 100.0)
    part.cycle()
    first = handover.latest  # read: 100 more a second, for a second
    assert first is not None
    part.run(0.5)
    second = handover.latest
    assert second is not None and 45 <= second.number - first.number <= 55
    part.run(2.0)
    taken = handover._latest
    assert taken is not None and 95 <= taken.number - second.number <= 105
    part.run(0.5)
    assert handover._latest is taken  # nobody read for a second: none taken since
    bell = handover.subscribe(100.0)  # a doorbell wants them at 100 Hz
    part.run(0.1)
    got = bell.wait(0)
    assert got is not None and got.number > taken.number
    assert part.stats.cycles - 10 < got.figures.cycles <= part.stats.cycles


# ---------------------------------------------------------------------- another process
class Wired:
    """A part's loop feeding a mirror over real pipes, as ``remote run`` feeds its
    consumers' process (here in one process, the mirror's reader on its thread)."""

    def __init__(self, part: RemotePart, *, frames: bool = True, wait: bool | None = None,
                 ) -> None:
        mirror_in, to_mirror = os.pipe()
        loop_in, mirror_out = os.pipe()
        self.fds = [mirror_in, to_mirror, loop_in, mirror_out]
        self.feed = LoopFeed(part, to_mirror, loop_in, frames=frames, rate_hz=100.0,
                             wait=wait)
        self.mirror = Mirror(mirror_in, mirror_out)
        self.frames: list[tuple[str, int, int]] = []
        self.changes: list[tuple[float, str, object]] = []
        self.faults: list[tuple[str, float | None]] = []
        self.mirror.frame_sinks.append(
            lambda bus, entries: self.frames.extend((bus, e[0], e[3]) for e in entries))
        self.mirror.change_sinks.append(
            lambda t, ref, v: self.changes.append((t, ref.qualified, v)))
        self.mirror.fault_sinks.append(
            lambda f, snap: self.faults.append((f.event, snap.lost_since(f.bus, f.board))))

    def close(self) -> None:
        for fd in self.fds:
            with contextlib.suppress(OSError):
                os.close(fd)


def test_the_consumers_process_sees_what_the_loop_hands_over(running) -> None:
    fleet, part = running
    w = Wired(part)
    try:
        w.mirror.start()
        w.feed.attach_frames()
        w.feed.attach()
        w.feed.send_image()
        image = w.mirror.wait_image(DEADLINE_S)
        assert image is not None and [r.qualified for r in image.refs] == [
            r.qualified for r in part.names]
        answer = w.mirror.write("Right Eye Target", 300, "a test", network=False)
        deadline = time.monotonic() + DEADLINE_S
        while not answer.done():
            assert time.monotonic() < deadline
            part.cycle()  # the loop's thread applies it
        assert answer.result().ok and answer.result().value == 300
        assert part["Right Eye Target"] == 300 and part.writes == []  # not the network's
        part.run(0.3)
        w.feed.flush()
        mine = w.feed.handover.latest
        assert mine is not None
        deadline = time.monotonic() + DEADLINE_S
        while (w.mirror.latest is None or w.mirror.latest.number < mine.number):
            assert time.monotonic() < deadline
            time.sleep(0.01)  # the mirror's reader thread takes the pipe
        theirs = w.mirror.latest
        assert theirs is not None and theirs.number == mine.number
        assert image.decode(theirs.values) == part.decode(mine.values)
        assert theirs.figures == mine.figures and theirs.traffic == mine.traffic
        assert ("Eyes/Right Eye Target", 300) in [(n, v) for _, n, v in w.changes]
        assert any(n == "Eyes/" + SENSOR for _, n, _ in w.changes)
        assert any(bus == "CAN0" and ident >> 6 == 14 for bus, ident, _ in w.frames)
        assert any(flags & 1 for _, _, flags in w.frames)  # sent ones too (CI maps)
        power_off(fleet)
        until_lost(part)
        part.run(0.05)
        w.feed.flush()
        deadline = time.monotonic() + DEADLINE_S
        while not w.faults:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        latest = w.mirror.latest
        assert latest is not None and latest.stale(*EYES)
        since = latest.lost_since(*EYES)
        assert since is not None and [e for e, _ in w.faults] == ["lost"]
        assert w.faults[0][1] == pytest.approx(since, abs=1e-6)
        values = image.decode(latest.values)
        sensor = next(r for r in image.refs if r.unique == SENSOR)
        assert values[sensor][0] <= since  # its last value, from before the loss
    finally:
        w.close()


def test_a_consumer_that_does_not_keep_up_never_holds_the_loop(running) -> None:
    """On the wall clock the loop writes what the pipe takes, keeps a bounded rest and
    counts what it had to drop; nobody reads the pipe here."""
    from ucom_tools.ops.remote import feed

    _, part = running
    w = Wired(part, wait=False)
    try:
        w.feed.attach_frames()
        w.feed.attach()
        w.feed.send_image()
        limit = feed.PENDING_LIMIT
        feed.PENDING_LIMIT = 64 << 10
        try:
            worst = 0.0
            for _ in range(3000):
                t = time.perf_counter()
                part.cycle()
                worst = max(worst, time.perf_counter() - t)
        finally:
            feed.PENDING_LIMIT = limit
        assert w.feed.lost > 0
        assert w.feed._pending_bytes <= (64 << 10) + 65536  # a message beyond at most
        assert w.feed._resync  # the snapshots not sent: the next one goes whole
        w.mirror.start()  # the consumer catches up: it is whole again
        deadline = time.monotonic() + DEADLINE_S
        while w.feed._resync or w.feed._pending_bytes:
            assert time.monotonic() < deadline
            part.cycle()
        mine = w.feed.handover._latest  # sent (nothing waits): the mirror reads it
        assert mine is not None
        while w.mirror.latest is None or w.mirror.latest.number < mine.number:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        theirs = w.mirror.latest
        assert theirs.number == mine.number and theirs.figures == mine.figures
        assert theirs.values.par == mine.values.par and theirs.lost == mine.lost
        assert worst < 1.0  # never blocked on the full pipe
    finally:
        w.close()


# ---------------------------------------------------------------------- stale everywhere
def test_the_live_view_marks_a_lost_board_and_dims_its_values(running) -> None:
    from ucom_tools.cli.live import LiveView

    fleet, part = running
    view = LiveView.local(part)
    part.run(0.1)
    assert "LOST" not in view.render(300)
    power_off(fleet)
    until_lost(part)
    part.run(0.3)
    text = view.render(300)
    title = next(line for line in text.splitlines() if "Eyes - CAN0 board 3" in line)
    lost = re.search(r"\x1b\[1;31m  LOST (\d+) ms\x1b\[0m", title)  # red, how long
    assert lost and 250 <= int(lost[1]) <= 350, title
    row = next(line for line in text.splitlines() if SENSOR in line)
    age = re.search(r"\x1b\[2m +-?\d+ \((\d+) ms\)\x1b\[0m", row)  # dimmed, its age
    assert age and int(lost[1]) <= int(age[1]) <= 360, row
    assert "1 board(s) lost" in text.splitlines()[0]
    assert view.message.startswith("! CAN0 board 3 (head right) lost at")
    other = next(line for line in text.splitlines() if "Left Eye Joint Sensor" in line)
    assert " (" not in other.split("│")[2]  # the others as ever


def test_a_lost_board_is_stale_in_the_recording(tmp_path) -> None:
    """``remote run --record`` (its consumers' process) over a fleet whose head-right
    board loses power at 0.3 s for 0.3 s: a row with valid 0 and its last value for
    each of its edges at the loss, its values valid again after its rejoin; ``remote
    plot`` leaves the gap."""
    from ucom_tools.cli.plot import steps
    from ucom_tools.trace.record import read_values

    state = tmp_path / "state"
    r = CliRunner().invoke(cli, ["flash", str(ROOT / "firmware_images/armar3.fl.S"),
                                 "--virtual", "armar3", "--state", str(state)])
    assert r.exit_code == 0, r.stderr
    scenario = tmp_path / "s.toml"
    scenario.write_text('[[fault]]\nat = 0.3\nbus = "CAN0"\nboard = 3\nkind = "power-off"\n'
                        'for = 0.3\n')
    log = tmp_path / "run.blf"
    r = CliRunner().invoke(cli, [
        "remote", "run", "armar3", "--virtual", "armar3", "--state", str(state),
        "--scenario", str(scenario), "--for", "1.5", "--on-fault", "hold", "--rejoin",
        "--set", "Right Eye Target=200", "--record", str(log), "--json"])
    assert r.exit_code == 0, r.stderr
    faults = json.loads(r.stdout)["faults"]
    assert [f["event"] for f in faults] == ["lost", "rejoined"]
    with open(f"{log}.values.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    stale = [x for x in rows if x["valid"] == "0"]
    assert stale and {(x["bus"], x["board"]) for x in stale} == {("CAN0", "3")}
    names = {x["name"] for x in rows if (x["bus"], x["board"]) == ("CAN0", "3")}
    assert {x["name"] for x in stale} == names  # every edge of it recorded so far
    lost_at = float(stale[0]["timestamp"])
    before = [x for x in rows if x["name"] == SENSOR and float(x["timestamp"]) < lost_at]
    mark = next(x for x in stale if x["name"] == SENSOR)
    assert mark["value"] == before[-1]["value"]  # its last value, marked stale
    back = [x for x in rows if x["name"] == SENSOR and x["valid"] == "1"
            and float(x["timestamp"]) > lost_at]
    assert back  # valid again after the rejoin (written even where the same)
    values = read_values(f"{log}.values.csv")
    s = values.series["Eyes/" + SENSOR]
    (start, until), = s.stale
    assert start == lost_at and until == float(back[0]["timestamp"])
    xs, ys = steps(values, s)
    gap = [x for x, y in zip(xs, ys, strict=True) if math.isnan(y)]
    assert gap and start - values.start <= gap[0] < until - values.start
    neck = values.series["Neck/Neck Pitch Joint Sensor"]
    assert not neck.stale  # the other boards as ever


def test_a_lost_board_is_stale_on_the_network(running) -> None:
    """The Zenoh share: the board's sample says ``valid: false`` and since when it is
    lost (its values the last before the loss), its edge samples ``valid: false``, the
    loss goes out as an event and its liveliness token goes."""
    import socket

    from ucom_tools.net.client import RobotClient
    from ucom_tools.net.share import share

    fleet, part = running
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    share(part, endpoint=endpoint)
    events: list[dict[str, object]] = []
    boards: dict[tuple[str, int], bool] = {}
    part.run(0.05)
    client = RobotClient.connect(endpoint, timeout=DEADLINE_S)
    try:
        edge: list[tuple[object, ...]] = []
        client.on_events(events.append)
        client.on_boards(lambda bus, board, up: boards.__setitem__((bus, board), up))
        client.subscribe([SENSOR], lambda *a: edge.append(a), validity=True)

        def until(what, limit: float = DEADLINE_S) -> None:  # type: ignore[no-untyped-def]
            deadline = time.monotonic() + limit
            while not what():
                assert time.monotonic() < deadline
                part.cycle()

        until(lambda: client.read([SENSOR])[SENSOR].valid and boards.get(EYES)
              and any(a[3] is True for a in edge))
        power_off(fleet)
        until_lost(part)
        until(lambda: not client.read([SENSOR])[SENSOR].valid)
        reading = client.read([SENSOR])[SENSOR]
        assert reading.lost_since is not None and reading.t <= reading.lost_since
        assert reading.seen.startswith("silence")
        assert client.read(["Neck Pitch Joint Sensor"])["Neck Pitch Joint Sensor"].valid
        until(lambda: any(e.get("kind") == "fault" for e in events) and not boards[EYES]
              and edge[-1][3] is False)
        fault = next(e for e in events if e.get("kind") == "fault")
        assert fault["event"] == "lost" and fault["where"] == "CAN0 board 3 (head right)"
        assert fault["t"] == pytest.approx(reading.lost_since, abs=0.002)
    finally:
        client.close()


def test_browse_shows_a_lost_board_and_its_stale_values() -> None:
    from ucom_tools.cli.browse import _stale
    from ucom_tools.cli.browse_view import Keys, Model, render
    from ucom_tools.net.client import reading_of

    structure = {"robot": "armar3", "name": "ARMAR-III", "buses": [{"name": "CAN0",
                 "bitrate": 1000000, "boards": [{"board": 3, "where": "CAN0 board 3",
                 "prefix": "Eyes", "edges": [{"name": SENSOR, "robot_name": SENSOR,
                 "kind": "SO", "unit": "counts", "qualified": "Eyes/" + SENSOR}]}]}]}
    model = Model("tcp/x")
    model.connected(structure, 100.0)
    model.sample({"bus": "CAN0", "board": 3, "t": 50.0, "values": {SENSOR: 7},
                  "valid": True}, 100.0)
    assert model.value("CAN0", 3, SENSOR, 100.5) == (7, 0.5)
    lost = {"bus": "CAN0", "board": 3, "t": 50.0, "values": {SENSOR: 7}, "valid": False,
            "lost": {"since": 50.2, "seen": "silence: none of its SO maps for 5 ms"}}
    model.sample(lost, 101.0)
    model.sample(lost, 102.0)  # again a second later: still lost since the first
    value, age = model.value("CAN0", 3, SENSOR, 103.0)
    assert value == 7 and age == pytest.approx(2.2)  # heard 2 s ago, 0.2 s old then
    text = "\n".join(line.plain for line in render(model, Keys(), 103.0, 20).renderables)
    assert "LOST: silence: none of its SO maps for 5 ms" in text
    row = next(line for line in render(model, Keys(), 103.0, 20).renderables
               if SENSOR in line.plain)
    assert any(str(span.style) == "dim" for span in row.spans)
    reading = reading_of(lost, 50.0, 7)
    assert not reading.valid and reading.age == pytest.approx(0.2)
    assert tuple(reading) == (50.0, 7)  # still the (t, value) pair it always was
    assert _stale(reading, "CAN0 board 3") == (
        " (stale: CAN0 board 3 is lost, silence: none of its SO maps for 5 ms)")
    model.sample({**lost, "valid": True}, 104.0)
    assert "LOST" not in "\n".join(
        line.plain for line in render(model, Keys(), 104.0, 20).renderables)


def test_browse_get_says_a_value_is_stale(tmp_path) -> None:
    """``ucom browse --get`` and ``--json`` of a robot (``remote run --zenoh`` with its
    consumers' process) whose head-right board is lost for good (hold, no rejoin)."""
    import socket

    state = tmp_path / "state"
    r = CliRunner().invoke(cli, ["flash", str(ROOT / "firmware_images/armar3.fl.S"),
                                 "--virtual", "armar3", "--state", str(state)])
    assert r.exit_code == 0, r.stderr
    scenario = tmp_path / "s.toml"
    scenario.write_text('[[fault]]\nat = 0.2\nbus = "CAN0"\nboard = 3\nkind = "power-off"\n'
                        'for = 3600\n')
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    robot = subprocess.Popen(
        [sys.executable, "-m", "ucom_tools", "remote", "run", "armar3", "--virtual",
         "armar3", "--state", str(state), "--scenario", str(scenario), "--on-fault", "hold",
         "--zenoh", endpoint], cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
        text=True)
    try:
        deadline = time.monotonic() + DEADLINE_S
        while True:
            got = subprocess.run(
                [sys.executable, "-m", "ucom_tools", "browse", "--zenoh", endpoint, "--get",
                 SENSOR, "--get", "Neck Pitch Joint Sensor", "--timeout", "5"],
                capture_output=True, text=True, cwd=ROOT, timeout=DEADLINE_S)
            if "stale" in got.stdout or time.monotonic() > deadline:
                break
        assert got.returncode == 0, got.stderr
        line = next(x for x in got.stdout.splitlines() if x.startswith(SENSOR))
        assert re.fullmatch(rf"{SENSOR} = -?\d+ counts \(stale: CAN0 board 3 \(head right\) "
                            r"is lost, silence: none of its SO maps for [\d.]+ ms\)", line), \
            got.stdout
        assert "stale" not in next(x for x in got.stdout.splitlines()
                                   if x.startswith("Neck Pitch Joint Sensor"))
        doc = json.loads(subprocess.run(
            [sys.executable, "-m", "ucom_tools", "browse", "--zenoh", endpoint, "--get",
             SENSOR, "--json"], capture_output=True, text=True, cwd=ROOT,
            timeout=DEADLINE_S).stdout)
        v = doc["values"][SENSOR]
        assert v["valid"] is False and v["lost_since"] >= v["t"]
    finally:
        robot.terminate()
        try:
            robot.wait(DEADLINE_S)
        except subprocess.TimeoutExpired:
            robot.kill()
            robot.wait()
    shutil.rmtree(state, ignore_errors=True)
