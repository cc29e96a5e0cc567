"""The paced fleet clock (``fleet serve``): a fleet the machine cannot run in real time
says so, one that keeps up does not."""

from __future__ import annotations

import itertools
import logging
import time

import pytest

from ucom_tools.virtual.clock import LAG_WARN_US, FleetClock, RealtimeDriver
from ucom_tools.virtual.simbus import SimBus

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


@pytest.mark.parametrize("pause", ["lock", "step"])
def test_a_paused_fleet_does_not_let_its_boards_watchdogs_fire(
        tmp_path, caplog, pause: str) -> None:
    """The served fleet is not run for 150 ms while the PC's loop goes on sending over
    socketcand: ``lock``, another thread holds the fleet's lock (the driver is woken late:
    a busy machine, a virtual machine's host) - it goes on from where it stopped, its
    frames stamped with the wall clock's time after the pause, the pause reported;
    ``step``, a step takes that long (kept from running in the middle of one) - it catches
    up at twice the wall clock's pace.  Either way the boards get the PC's MCA Alive at
    least every two of its intervals (running through the pause at once, they got none for
    150 ms and their watchdogs stopped them although the PC never paused)."""
    import subprocess
    import sys
    import threading

    from tests.helpers import ROOT, head_topology
    from ucom_tools.ops.remote import RemotePart
    from ucom_tools.virtual.fleet import Fleet
    from ucom_tools.virtual.socketcand import FleetServer

    topology = str(head_topology(tmp_path))
    state = tmp_path / "state"
    flash = subprocess.run([sys.executable, "-m", "ucom_tools", "flash",
                            str(ROOT / "firmware_images/armar3.fl.S"), "--virtual", topology,
                            "--state", str(state)], capture_output=True, text=True,
                           timeout=120)
    assert flash.returncode == 0, flash.stderr
    fleet = Fleet.load(topology, state_dir=state, realtime=True)
    server = FleetServer(fleet, "127.0.0.1", 0)
    thread = threading.Thread(target=server.serve_forever, args=(0.05,), daemon=True)
    thread.start()
    ages: list[tuple[float, float]] = []
    alive = _AliveTimes()
    fleet.buses["CAN0"].attach(alive)
    try:
        with caplog.at_level(logging.WARNING, logger="ucom.bus"), RemotePart.open(
                topology, interface="socketcand",
                host="127.0.0.1", port=server.address[1], channels=("CAN0",)) as part:
            part.robot.buses["CAN0"].link.dispatcher.subscribe(
                lambda msg: msg.arbitration_id >> 6 == 14, "SO age",
                on_data=lambda ident, data, stamp: ages.append((time.time(), stamp)))
            for _ in range(200):
                part.cycle()
            driver = fleet.driver
            assert driver is not None
            before = driver.slipped_us
            interval = part.exchanges["CAN0"].plan.alive_interval_us
            released = threading.Event()
            with fleet.clock.lock:
                paused_at = fleet.clock.now

            def hold() -> None:  # the fault itself: the fleet is not run for 150 ms
                if pause == "lock":
                    with fleet.clock.lock:
                        time.sleep(0.15)
                    released.set()
                else:
                    def slow(t: float) -> None:
                        time.sleep(0.15)
                        released.set()
                    with fleet.clock.lock:
                        fleet.clock.at(fleet.clock.now + 100, slow)
            holder = threading.Thread(target=hold)
            holder.start()
            resumed = 0.0
            for _ in range(600):
                part.cycle()
                if not resumed and released.is_set():
                    resumed = time.time()
            holder.join()
            assert resumed and part.stats.longest_gap_s < 0.05  # the PC sent MCA Alive
            stops = [e for e in part.events if e.stopped_motors]
        assert stops == []
        after = [t for t in alive.times if t >= paused_at]
        gaps = [b - a for a, b in itertools.pairwise(after)]
        assert len(after) > 10 and max(gaps) <= 2.5 * interval, (max(gaps), interval)
        if pause == "lock":
            assert driver.slipped_us - before >= 100_000
            later = sorted(now - stamp for now, stamp in ages if stamp > resumed + 0.05)
            assert later and later[len(later) // 2] < 0.05  # not 150 ms in the past
            assert any("was kept from running for " in r.getMessage()
                       for r in caplog.records)
    finally:
        fleet.buses["CAN0"].detach(alive)
        server.shutdown()
        server.server_close()
        thread.join(10)
        fleet.close()
