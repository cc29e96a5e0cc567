"""The consumers of ``ucom remote run`` (its live view, ``--record``, ``--zenoh``) in a
process of their own, apart from the PC's loop (why: :mod:`ucom_tools.ops.remote.feed`).

The loop's process starts this one (:class:`ConsumerProcess`, ``python -m
ucom_tools.cli.consumers IN OUT``: two pipes; a session of its own, niceness
:data:`NICE`) before it opens the buses, sends it what
to do (a config message) and goes on with its own start; this process opens the
recording and the Zenoh session and answers "ready" (or why it cannot: the exit code and
the message of the error, which the loop's process raises before anything is sent to the
boards).  Once the boards run it gets the part's structure, then the loop's snapshots,
frames and value changes (:class:`~ucom_tools.ops.remote.mirror.Mirror`), shows the live
view on the terminal both share, records and shares; the view's writes and quit, and the
network's writes and stops, go back to the loop.  It ignores Ctrl-C, SIGTERM and SIGHUP:
the loop's process decides the end, and then this one commits the recording, says on
the network that the robot stopped, gives the terminal back, and says how it ended.
"""

from __future__ import annotations

import contextlib
import os
import select
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import can

from ucom_tools.cli.errortext import describe
from ucom_tools.errors import BusError, InputError, UcomError, WriteError
from ucom_tools.ops.remote.faults import BoardFault
from ucom_tools.ops.remote.feed import LoopFeed, Unpacker, pack
from ucom_tools.ops.remote.mirror import Mirror
from ucom_tools.ops.remote.publish import LoopSnapshot
from ucom_tools.protocol.traffic import ERROR, EXTENDED, REMOTE, SENT, SinkEntry
from ucom_tools.wire import mca

if TYPE_CHECKING:
    from ucom_tools.config.topology import BoardKey

READY_S = 30.0
"""How long the loop's process waits for this one to open the recording and the network."""
END_S = 30.0
"""How long it waits, after the boards' stop, for this one to commit the recording."""
NICE = 10
"""This process's niceness: where the machine is short of processor time, the loop and
the buses get it first (the view renders less often, the recording lags behind and
catches up).  Where Linux shares the processors between sessions first (its autogroups,
on by default), a niceness counts only among a session's own processes: there what
puts the loop first is that this process runs in a session of its own, so that what it
uses counts against its session, not the loop's (``benchmarks/consumers.py``, two
cores, two busy processes, the served fleet: the loop missed 10.4 times the cycles it
missed without its consumers while they shared its session, 4.5 times in a session of
their own).  Giving that session a niceness of its own (``/proc/self/autogroup``) did
not help the loop measurably (``benchmarks/record.py``, three runs each, 2026-12-08)
and made the Foxglove delivery later."""


# ---------------------------------------------------------------------- the loop's side
@dataclass(frozen=True)
class ExtraConsumer:
    """A consumer a command adds to a run (``gateway canopen``'s gateway): its ``config``
    goes to the consumers' process under ``name``; the snapshots come at least at
    ``rate_hz``; ``announce`` prints what the process opened for it (its ``ready``
    entry), and ``--json`` carries its stats under ``name``."""

    name: str
    config: dict[str, Any]
    rate_hz: float
    announce: Callable[[Any], None] | None = None


class ConsumerProcess:
    """The loop's handle of the consumers' process: started at once with ``config``
    (what :func:`main` reads); :meth:`feed` is the loop's end of the pipes."""

    def __init__(self, config: dict[str, Any]) -> None:
        to_child, self._child_in = os.pipe()
        self._child_out, from_child = os.pipe()
        try:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "ucom_tools.cli.consumers", str(to_child),
                 str(from_child)], pass_fds=(to_child, from_child), close_fds=True,
                start_new_session=True)  # see NICE
        finally:
            os.close(to_child)
            os.close(from_child)
        self.out_fd, self.in_fd = self._child_in, self._child_out
        os.write(self.out_fd, pack(("config", config)))
        self.ready: dict[str, Any] = {}

    def feed(self, part: Any, *, frames: bool, rate_hz: float) -> LoopFeed:
        return LoopFeed(part, self.out_fd, self.in_fd, frames=frames, rate_hz=rate_hz)

    def wait_ready(self, feed: LoopFeed) -> dict[str, Any]:
        """What the consumers' process opened (the share's endpoint ...); the error it met
        instead, raised here as the loop's own (exit 3: the recording's file; 4: the
        network), before anything is sent to the boards."""
        got = feed.wait_for("ready", READY_S)
        if got is None:
            ended = feed.ended
            if ended is not None:
                raise error_of(*ended)
            raise UcomError("the consumers' process (live view, --record, --zenoh) did not "
                            f"start within {READY_S:g} s")
        self.ready = got[1]
        return self.ready

    def close(self) -> int | None:
        """Let go of the pipes and wait for the process (killed when it does not end)."""
        for fd in (self.out_fd, self.in_fd):
            with contextlib.suppress(OSError):
                os.close(fd)
        try:
            return self.proc.wait(timeout=END_S)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            return self.proc.wait()


def error_of(code: int, message: str, key: str | None = None) -> UcomError:
    """The error the consumers' process ended with, for the loop's process to raise."""
    if code == 3:
        return InputError(message, key=key)
    if code == 4:
        return BusError(message)
    if code == 5:
        return WriteError(message)
    return UcomError(message)


# ---------------------------------------------------------------------- this process
def frame_of(bus: str, entry: SinkEntry) -> can.Message:
    ident, data, stamp, flags = entry
    return can.Message(timestamp=stamp, arbitration_id=ident, data=data,
                       is_extended_id=bool(flags & EXTENDED),
                       is_remote_frame=bool(flags & REMOTE),
                       is_error_frame=bool(flags & ERROR), is_rx=not flags & SENT,
                       channel=bus, check=False)


class Consumers:
    """What runs in this process for one run (see the module docstring)."""

    def __init__(self, mirror: Mirror, config: dict[str, Any]) -> None:
        self.mirror = mirror
        self.config = config
        self.recorder: Any = None
        self.share: Any = None
        self.view: Any = None
        self.gateway: Any = None
        self.foxglove: Any = None
        self._canopen: list[Any] = []
        """The gateway's CANopen buses, opened in :meth:`open`."""
        self._stale: dict[BoardKey, tuple[float, bool]] = {}
        """(bus, board) -> since when it is lost (the frames' time base) and whether it
        rejoined, while its values in the recording are stale."""

    def open(self) -> dict[str, Any]:
        """The recording's files and the Zenoh session; what the loop's process prints."""
        c = self.config
        info: dict[str, Any] = {}
        if c.get("foxglove"):  # first: a port in use ends the run before any file
            from ucom_tools.viewers.foxglove_feed import RunFoxglove

            f = c["foxglove"]
            self.foxglove = RunFoxglove(self.mirror, f["host"], f["port"], robot=c["robot"],
                                        allow_writes=f["allow_writes"],
                                        rate_hz=f["publish_hz"])
            info["foxglove"] = {"url": self.foxglove.server.url}
        if c.get("record") and c["record"].lower().endswith(".mcap"):
            from ucom_tools.trace.mcap_record import McapRecorder

            self.recorder = McapRecorder(c["record"], rate_hz=c.get("record_hz"),
                                         loop_hz=c["loop_hz"])
            self.recorder.attach(self.mirror)
        elif c.get("record"):
            from ucom_tools.trace.record import RunRecorder

            self.recorder = RunRecorder(c["record"])
            self.mirror.frame_sinks.append(self._frames)
            self.mirror.change_sinks.append(self._change)
            self.mirror.fault_sinks.append(self._fault)
            self.mirror.snapshot_sinks.append(self._fresh)
        if c.get("zenoh"):
            from ucom_tools.net.share import RobotShare

            z = c["zenoh"]
            self.share = RobotShare(self.mirror, c["robot"], c["loop_hz"],
                                    endpoint=z["endpoint"], config_file=z["config"],
                                    allow_writes=z["allow_writes"],
                                    publish_hz=z["publish_hz"], force=z["force"],
                                    pid=c["pid"])
            info["zenoh"] = {"robot": self.share.robot, "joined": self.share.joined,
                             "where": self.share.where, "publish_hz": self.share.publish_hz}
        if c.get("gateway"):
            info["gateway"] = self._open_gateway(c["gateway"])
        return info

    def _open_gateway(self, g: dict[str, Any]) -> dict[str, Any]:
        """The CANopen buses (BusError: exit 4 before the boards start); the nodes boot
        once the boards run (:meth:`run`)."""
        from ucom_tools.gateway import buses
        from ucom_tools.gateway.bridge import dictionaries

        # built now, while the loop's process still starts the boards: none of this
        # work competes with the running loop for the processor
        self._dictionaries = dictionaries(g["joints"])
        for spec in g["buses"]:
            self._canopen.append((spec, buses.open_bus(spec)))
        return {"buses": [s.text for s in g["buses"]],
                "fits_hz": {s.text: fits for s, fits in self._fits(g).items()}}

    def _fits(self, g: dict[str, Any]) -> dict[Any, float]:
        """Per CANopen bus, the SYNC rate its nodes' default PDOs fit."""
        from ucom_tools.gateway.buses import by_bus
        from ucom_tools.gateway.load import fitting_rate

        specs = g["buses"]
        return {specs[i]: fitting_rate([self._dictionaries[j.node_id] for j in mine])
                for i, mine in by_bus(specs, g["joints"], lambda j: j.bus).items()}

    def _gateway_log(self) -> None:
        """The gateway's warnings (a master lost or back, frames not sent) on the terminal,
        where no live view owns it (the run's --json has them in 'gateway' too)."""
        import logging

        log = logging.getLogger("ucom.gateway")
        if self.config.get("view") or log.handlers:
            return
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("gateway: %(message)s"))
        log.addHandler(handler)
        log.setLevel(logging.INFO)
        log.propagate = False

    def _start_gateway(self) -> None:
        from ucom_tools.gateway.bridge import CanopenBus, Gateway

        g = self.config["gateway"]
        self._gateway_log()
        image = self.mirror.image
        assert image is not None
        self.gateway = Gateway(g["joints"], image, self.mirror,
                               [CanopenBus(bus, spec.text, spec.ucom_buses)
                                for spec, bus in self._canopen], cycle=g["cycle"],
                               dictionaries=self._dictionaries).start()

    def _frames(self, bus: str, entries: list[SinkEntry]) -> None:
        rec = self.recorder
        for entry in entries:
            rec.on_message_received(frame_of(bus, entry))

    def _change(self, t: float, ref: Any, value: Any) -> None:
        self.recorder.value(t, ref.bus, ref.board, ref.prefix, ref.unique, ref.kind.name,
                            value)

    def _fault(self, fault: BoardFault, snap: LoopSnapshot) -> None:
        """A board lost: its values in the recording are stale from then on (until
        :meth:`_fresh` sees them again)."""
        board = (fault.bus, fault.board)
        if fault.event == "lost":
            at = snap.on_stamps(fault.time)
            self.recorder.lost(at, *board)
            self._stale[board] = (at, False)
        elif board in self._stale:
            self._stale[board] = (self._stale[board][0], True)

    def _fresh(self, snap: LoopSnapshot) -> None:
        """The values of a board that was lost, once they are fresh again: its sensor
        values from frames that came after the loss, the values the PC sends it and
        wrote once it rejoined.  The loop reports a value only when it changed: one
        that came back as it was would stay stale in the recording otherwise."""
        if not self._stale or self.mirror.image is None:
            return
        values = self.mirror.image.decode(snap.values)
        for board, (since, rejoined) in list(self._stale.items()):
            waiting = False
            for ref in self.mirror.image.refs:
                if (ref.bus, ref.board) != board:
                    continue
                got = values.get(ref)
                if got is None:
                    continue
                t, value = got
                if (ref.kind is mca.Kind.SO and t <= since) or (
                        ref.kind is not mca.Kind.SO and not rejoined):
                    waiting = True
                    continue
                self.recorder.fresh(max(t, since), ref.bus, ref.board, ref.prefix,
                                    ref.unique, ref.kind.name, value)
            if not waiting:
                del self._stale[board]

    def run(self) -> None:
        """Until the run ends: the live view on the terminal (its quit ends the run), or
        nothing but the recording and the share, which work on their own threads."""
        image = self.mirror.wait_image()
        if image is None:
            return  # the run ended before the boards ran
        if self.share is not None:
            self.share.declare()
        if self._canopen:
            self._start_gateway()
        if self.config.get("view") and not self.mirror.ended.is_set():
            from ucom_tools.cli.live import LiveView

            self.view = LiveView(image, self.mirror, ended=self.mirror.ended)
            self.view.run()
            if not self.mirror.ended.is_set():
                self.mirror.quit()
        while not self.mirror.ended.wait(0.2):
            if self.recorder is not None:
                self.recorder.check()  # a recording that failed ends the run

    def close(self) -> tuple[int, str, str | None]:
        """Say on the network that the robot stopped, commit the recording (or discard
        it where the run never started): (exit code, message, option)."""
        outcome: tuple[int, str, str | None] = (0, "", None)
        if self.gateway is not None:
            self.gateway.close()  # first: a runtime's thread CPU time is known at its end
            self.gateway_stats = self.gateway.stats()
        for _, bus in self._canopen:
            with contextlib.suppress(Exception):
                bus.shutdown()
        if self.foxglove is not None:
            self.foxglove.close()
            self.foxglove_stats = self.foxglove.stats()
        if self.share is not None:
            try:
                self.share.close()
            except Exception as err:  # the recording is committed all the same
                outcome = (4 if isinstance(err, BusError) else 1,
                           f"--zenoh: {err}", None)
        if self.recorder is not None:
            try:
                if self.mirror.lost:
                    self.recorder.discard()
                    return 5, (f"--record: {self.recorder.path}: {self.mirror.lost} frames "
                               "and value changes could not be handed over to the "
                               "recording (this machine did not keep up with it); nothing "
                               "was kept"), None
                if self.mirror.image is None:
                    self.recorder.discard()
                else:
                    self.recorder.close()
            except WriteError as err:
                return 5, describe(err), None
            except BaseException:
                self.recorder.discard()
                raise
        failure = self.mirror.error
        if failure is not None:
            if isinstance(failure, WriteError):
                return 5, describe(failure), None
            return 1, f"the consumers' process failed: {failure!r}", None
        return outcome

    def stats(self) -> dict[str, Any]:
        return {"network": None if self.share is None else self.share.stats(),
                "gateway": getattr(self, "gateway_stats", None),
                "foxglove": getattr(self, "foxglove_stats", None)}


def main(argv: list[str]) -> int:
    """``python -m ucom_tools.cli.consumers IN OUT``: the file descriptors of the pipes
    from and to the loop's process."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)  # the loop's process decides the end
    with contextlib.suppress(OSError):
        os.nice(NICE)  # the loop first, the gateway's CANopen side too
    in_fd, out_fd = int(argv[0]), int(argv[1])
    config = _read_config(in_fd)
    mirror = Mirror(in_fd, out_fd)
    consumers = Consumers(mirror, config)
    try:
        info = consumers.open()
    except InputError as err:
        mirror.finished(3, err.reason, err.key)
        return 3
    except BusError as err:
        mirror.finished(4, describe(err))
        return 4
    except UcomError as err:
        mirror.finished(1, str(err))
        return 1
    mirror.send_ready(info)
    mirror.start()
    failure: tuple[int, str, str | None] | None = None
    try:
        consumers.run()
    except InputError as err:  # the gateway could not start: the run ends with its error
        failure = (3, err.reason, err.key)
    except BusError as err:
        failure = (4, describe(err), None)
    except UcomError as err:
        failure = (1, str(err), None)
    except Exception as err:  # a fault of this process's own: the run must not go on
        failure = (1, f"the consumers' process failed: {err!r}", None)
    finally:
        code, message, key = consumers.close()
        if failure is not None and not code:
            code, message, key = failure
        mirror.finished(code, message, key, consumers.stats())
    return code


def _read_config(fd: int) -> dict[str, Any]:
    unpacker = Unpacker()
    deadline = time.monotonic() + READY_S
    while time.monotonic() < deadline:
        select.select([fd], [], [], 1.0)
        data = os.read(fd, 1 << 16)
        if not data:
            raise SystemExit(0)  # the loop's process is gone
        for message in unpacker.feed(data):
            if message[0] == "config":
                return dict(message[1])
    raise SystemExit(1)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
