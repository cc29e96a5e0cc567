"""One time base per log (issue 19, A.1): frames received over socketcand are stamped on
this machine's clock (the server's stamps translated by the offset measured on the
connection), so a log of sent and received frames never shows an answer before its
request, whatever the server's clock says; and ``ucom decode`` flags a trace whose times
run backwards instead of decoding it silently."""

from __future__ import annotations

import itertools
import threading
import time
from pathlib import Path

import can
import pytest
from click.testing import CliRunner

from tests.test_socketcand_client import FakeServer, Peer, within
from ucom_tools.cli.main import cli
from ucom_tools.trace.decode import decode_frames, read_trace
from ucom_tools.transport.socketcand import SocketcandBus

LOCAL = "127.0.0.1"
PACING_SLACK_S = 0.01
SKEW_S = 1000.0
"""How far the fake server's clock is ahead of ours."""


def test_frames_from_a_server_with_another_clock_are_stamped_on_ours() -> None:
    go = threading.Event()
    heard = threading.Event()

    def script(peer: Peer) -> None:
        peer.greet()
        go.wait(5)
        peer.say(f"< frame 0C1 {time.time() + SKEW_S:.6f} 00 >")  # as it ends on the bus
        heard.wait(5)
        now = time.time() + SKEW_S  # then three that came 1 ms apart, a while ago
        peer.say("".join(f"< frame 0C{i + 2} {now - 0.050 + i * 0.001:.6f} 00 >"
                         for i in range(3)))
        peer.wait_closed()

    with FakeServer(script) as server:
        bus = within(5, lambda: SocketcandBus("CAN0", LOCAL, server.port))
        try:
            before = time.time()
            go.set()
            first = within(5, lambda: bus.recv(2))
            heard.set()
            burst = [within(5, lambda: bus.recv(2)) for _ in range(3)]
            after = time.time()
        finally:
            bus.shutdown()
    assert first is not None and all(burst)
    assert before <= first.timestamp <= after
    stamps = [m.timestamp for m in burst if m is not None]
    assert first.timestamp - 0.060 <= stamps[0] <= stamps[-1] <= after
    assert [b - a for a, b in itertools.pairwise(stamps)] == \
        [pytest.approx(0.001, abs=2e-6)] * 2  # the bus's spacing is kept
    assert bus.clock_offset == pytest.approx(-SKEW_S, abs=1.0)


def test_a_log_over_socketcand_has_every_answer_after_its_request(
        served_armar3: tuple[str, int], tmp_path: Path) -> None:
    host, port = served_armar3
    log = tmp_path / "init.asc"
    r = CliRunner().invoke(cli, ["init", "-i", "socketcand", "--host", host, "--port",
                                 str(port), "--topology", "armar3", "--log", str(log)])
    assert r.exit_code == 0, r.stderr
    frames = read_trace(log)
    assert len(frames) > 40
    for bus in {f.channel for f in frames}:
        on_bus = [f for f in frames if f.channel == bus]
        for sent, after in itertools.pairwise(on_bus):
            if not sent.is_rx and after.is_rx:  # the request, then what came after it
                # (the served fleet stamps by its paced clock, which may lag the wall clock
                # by a few milliseconds on a busy machine: that much, no more)
                assert after.timestamp >= sent.timestamp - PACING_SLACK_S, (bus, sent, after)
    conv = decode_frames(frames)
    assert not [v for v in conv.violations if v.rule == "time-backwards"]


def test_decode_flags_a_trace_whose_times_run_backwards(tmp_path: Path) -> None:
    trace = tmp_path / "mixed.asc"
    t = time.time()
    with can.Logger(str(trace)) as out:
        out.on_message_received(can.Message(timestamp=t, arbitration_id=0x280, data=b"\1\0",
                                            is_extended_id=False, is_rx=False, channel=0))
        out.on_message_received(can.Message(timestamp=t + 1, arbitration_id=0x0C1,
                                            data=bytes(8), is_extended_id=False, channel=0))
        out.on_message_received(can.Message(timestamp=t + 0.5, arbitration_id=0x0C2,
                                            data=bytes(8), is_extended_id=False, channel=0))
    r = CliRunner().invoke(cli, ["decode", str(trace)])
    assert r.exit_code == 1, r.stderr
    assert "time-backwards" in r.stdout + r.stderr
