"""The paced fleet clock (``fleet serve``): a fleet the machine cannot run in real time
says so, one that keeps up does not."""

from __future__ import annotations

import itertools
import logging
import time
from pathlib import Path

import pytest

from ucom_tools.virtual.bus.clock import LAG_WARN_US, FleetClock, RealtimeDriver
from ucom_tools.virtual.bus.simbus import SimBus

DEADLINE_S = 10.0


def _driven(clock: FleetClock, caplog: pytest.LogCaptureFixture, until: float) -> RealtimeDriver:
    driver = RealtimeDriver(clock, "test fleet (CAN0)")
    with caplog.at_level(logging.WARNING, logger="ucom.bus"):
        driver.start()
        try:
            deadline = time.monotonic() + DEADLINE_S
            while time.monotonic() < deadline and clock.now < until:
                time.sleep(0.01)  # polling the clock's progress, not synchronisation
        finally:
            driver.stop()
    assert clock.now >= until, "the driver did not get there"
    return driver


def test_a_fleet_too_slow_for_the_wall_clock_is_reported(caplog) -> None:
    clock = FleetClock()

    def slow_model(t: float) -> None:  # a 1 ms cycle whose work takes 20 ms of wall time
        time.sleep(0.02)
        clock.at(t + 1000, slow_model)

    clock.at(1000, slow_model)
    driver = _driven(clock, caplog, 80_000)  # 80 cycles: 1.6 s of wall time
    assert driver.worst_lag_us > LAG_WARN_US
    warnings = [r.getMessage() for r in caplog.records if "behind the wall clock" in
                r.getMessage()]
    assert len(warnings) == 1, warnings  # once, not every step
    assert warnings[0].startswith("test fleet (CAN0) runs ")
    assert "cannot run it in real time" in warnings[0]


def test_a_fleet_that_keeps_up_says_nothing_after_a_single_slow_step(caplog) -> None:
    clock = FleetClock()

    def cycle(t: float) -> None:
        if t == 5000:  # once: a program that starts, say
            time.sleep(0.08)
        clock.at(t + 1000, cycle)

    clock.at(1000, cycle)
    driver = _driven(clock, caplog, 1_500_000)  # 1.5 s of 1 kHz cycles
    assert driver.worst_lag_us > LAG_WARN_US  # the slow step was seen ...
    assert not [r for r in caplog.records if "behind the wall clock" in r.getMessage()]
    # ... and caught up with: the fleet is on time again
    assert clock.now >= driver.now_us() - LAG_WARN_US


def test_a_lagging_paced_fleet_takes_a_hosts_frame_in_its_own_present(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A host frame is ready at the wall clock's time - unless the fleet is behind the
    wall clock: then at its present (plus HOST_AHEAD_US), or the boards would see a host
    that went quiet (their watchdogs fire on a slow machine)."""
    from ucom_tools.config.topology import load
    from ucom_tools.virtual import fleet as fleet_module
    from ucom_tools.virtual.fleet import HOST_AHEAD_US, Fleet

    fleet = Fleet(load("tests/data/armar3_can0.toml"), realtime=True)
    try:
        sim = fleet.buses["CAN0"]
        driver = fleet._driver
        assert driver is not None
        seen: list[tuple[float, float]] = []
        real_send = fleet_module._send

        def send(sim: SimBus, sender: object, t: float, ident: int, data: bytes,
                 extended: bool) -> None:
            seen.append((t, fleet.clock.now))  # when the frame is ready, and the fleet's now
            real_send(sim, sender, t, ident, data, extended)

        # (the simulated bus may be compiled: its methods cannot be replaced, Fleet's
        # module function that hands it a host's frame can)
        monkeypatch.setattr(fleet_module, "_send", send)

        def tick(t: float) -> None:  # a fleet with work every millisecond (its programs)
            fleet.clock.at(t + 1000, tick)

        with fleet.clock.lock:
            fleet.clock.at(fleet.clock.now + 1000, tick)
        host = object()
        fleet.send_paced(sim, host, 0x7C0, b"\x01", timeout=1.0)  # keeping up
        lag = 0.5e6
        driver.t0 -= lag / 1e6  # the wall clock runs 0.5 s ahead of the fleet from now
        fleet.send_paced(sim, host, 0x7C0, b"\x02", timeout=1.0)
        deadline = time.monotonic() + DEADLINE_S
        while len(seen) < 2 and time.monotonic() < deadline:
            time.sleep(0.01)  # polling the driver's progress, not synchronisation
        assert len(seen) == 2
        (t1, now1), (t2, now2) = seen
        assert now1 <= t1 <= now1 + HOST_AHEAD_US  # on time: at the wall clock's time
        assert t2 == now2 + HOST_AHEAD_US < driver.now_us() - lag / 2  # not 0.5 s ahead
    finally:
        fleet.close()


class _AliveTimes:
    """A node on a simulated bus: the virtual end times of the MCA Alive frames on it."""

    def __init__(self) -> None:
        self.times: list[float] = []

    def on_frame(self, arbitration_id: int, data: bytes, t_end: float, *extra: object) -> None:
        if arbitration_id >> 6 == 26:  # MCA Alive
            self.times.append(t_end)

    def on_extended_frame(self, arbitration_id: int, data: bytes, t_end: float) -> None:
        pass


@pytest.fixture(scope="module")
def head(tmp_path_factory: pytest.TempPathFactory) -> tuple[str, Path]:
    """ARMAR-III's head (CAN0) as a robot of its own, flashed: its topology and state."""
    import subprocess
    import sys

    from tests.helpers import ROOT, head_topology
    where = tmp_path_factory.mktemp("head")
    topology = str(head_topology(where))
    flash = subprocess.run([sys.executable, "-m", "ucom_tools", "flash",
                            str(ROOT / "firmware_images/armar3.fl.S"), "--virtual", topology,
                            "--state", str(where / "state")], capture_output=True, text=True,
                           timeout=120)
    assert flash.returncode == 0, flash.stderr
    return topology, where / "state"


def _premise(gap_s: float, watchdog_s: float) -> None:
    """The tests below need the PC's own loop to keep sending MCA Alive: a machine that
    kept it away for the watchdog time makes the boards stop rightly."""
    if gap_s >= watchdog_s:
        pytest.skip(f"this machine kept the PC's loop away for {gap_s * 1e3:.0f} ms (the "
                    f"watchdog: {watchdog_s * 1e3:.0f} ms): the premise does not hold")


def test_a_served_fleet_stopped_by_the_system_does_not_stop_its_boards(head) -> None:
    """``fleet serve`` is stopped for 300 ms (SIGSTOP: what a busy machine or a virtual
    machine's host does to it, in a wait or in the middle of a step) while the PC's loop
    goes on sending over socketcand: the fleet must not run its boards through the pause
    faster than the wall clock, or they see no MCA Alive for as long and their watchdogs
    stop them although the PC never paused (before: every board, every time)."""
    import os
    import signal
    import subprocess
    import sys

    from tests.helpers import terminate
    from ucom_tools.ops.remote import RemotePart
    topology, state = head
    server = subprocess.Popen([sys.executable, "-m", "ucom_tools", "fleet", "serve", topology,
                               "--state", str(state), "--port", "0"], text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        assert server.stdout is not None
        line = server.stdout.readline()
        assert line.startswith("listening on 127.0.0.1:"), line
        port = int(line.rsplit(":", 1)[1])
        with RemotePart.open(topology, interface="socketcand", host="127.0.0.1", port=port,
                             channels=("CAN0",)) as part:
            for _ in range(300):
                part.cycle()
            os.kill(server.pid, signal.SIGSTOP)  # the fault itself
            stopped_at = time.monotonic()
            resumed = False
            for _ in range(1000):
                part.cycle()
                if not resumed and time.monotonic() - stopped_at >= 0.3:
                    os.kill(server.pid, signal.SIGCONT)
                    resumed = True
            stops = [e for e in part.events if e.stopped_motors]
            gap = part.stats.longest_gap_s
        _premise(gap, 0.05)
        assert stops == []
    finally:
        if server.poll() is None:
            os.kill(server.pid, signal.SIGCONT)
        terminate(server)


def test_a_slow_step_is_caught_up_at_twice_the_wall_clocks_pace(head) -> None:
    """One step of the served fleet takes 150 ms (kept from running in the middle of it)
    while the PC's loop goes on: the fleet catches up at most at twice the wall clock's
    pace, so its boards get the PC's MCA Alive at least every two of the PC's intervals
    (running through the lag at once, they got none for 150 ms and stopped)."""
    from tests.helpers import served_in_process
    from ucom_tools.ops.remote import RemotePart
    from ucom_tools.virtual.bus.clock import CATCH_UP_RATE
    topology, state = head
    alive = _AliveTimes()
    with served_in_process(topology, state) as (fleet, port):
        fleet.buses["CAN0"].attach(alive)
        with RemotePart.open(topology, interface="socketcand", host="127.0.0.1",
                             port=port, channels=("CAN0",)) as part:
            for _ in range(200):
                part.cycle()
            interval = part.exchanges["CAN0"].plan.alive_interval_us

            def slow(t: float) -> None:
                time.sleep(0.15)  # the fault itself
            with fleet.clock.lock:
                paused_at = fleet.clock.now
                fleet.clock.at(paused_at + 100, slow)
            for _ in range(600):
                part.cycle()
            stops = [e for e in part.events if e.stopped_motors]
            gap = part.stats.longest_gap_s
        _premise(gap, 0.05)
        assert stops == []
        after = [t for t in alive.times if t >= paused_at]
        gaps = [b - a for a, b in itertools.pairwise(after)]
        # the PC's own lateness stretches its intervals; the pause must not add to them
        bound = CATCH_UP_RATE * (interval + gap * 1e6) + interval
        assert len(after) > 10 and max(gaps) <= bound, (max(gaps), bound)
