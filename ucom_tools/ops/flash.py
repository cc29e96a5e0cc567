"""Programming images into boards: ``ucom flash`` (and console options 5, 6, 20).

A flash is asked for by a :class:`~ucom_tools.ops.flash_types.FlashRequest` and says
what it did in a :class:`~ucom_tools.ops.flash_types.FlashResult`; the job on each bus is
:class:`~ucom_tools.ops.flash_bus.BusJob`.

Per bus, all buses in parallel: init chain with diagnostics, pre-flight checks, boards
running a program back to the bootloader (XReset), ProgEnable, one broadcast transfer,
ProgID verification of every board (and a read-back of its Info), resending only what a
board missed, then AutoStart and Start when asked.  A board is reported programmed only
when it verified.

Another host programming the same bus is noticed (:class:`~ucom_tools.protocol.
programmer.ProgrammingWatch`): :func:`listen_first` before anything is sent (``ucom
flash`` calls it before its reset), and the job itself before it sends to the boards
and before its data; either raises :class:`~ucom_tools.errors.BusError` (exit code 4).

Interrupted at any step (its ``cancel`` event set by Ctrl-C, SIGTERM or SIGHUP, or a
:class:`KeyboardInterrupt` in the thread that runs it), the job stops where it is, puts
each bus's boards back (:func:`~ucom_tools.ops.leave.put_back`: ABORT if the transfer
began, ProgEnable cleared, AutoStart set again on a board its XReset cleared it on and
whose program is intact, every board's Info read) and raises :class:`FlashInterrupted`,
whose result says per board what it was left with (:mod:`ucom_tools.ops.leave`).
"""

from __future__ import annotations

import threading
from dataclasses import replace

from ucom_tools.ops.flash_bus import BusJob
from ucom_tools.ops.flash_types import (
    FINISHED,
    NOT_BEGUN,
    BusFlash,
    FlashInterrupted,
    FlashRequest,
    FlashResult,
    ProgressFn,
    not_begun,
)
from ucom_tools.ops.robot import BusHandle, Robot
from ucom_tools.protocol.watch import ProgrammingWatch, quiet_time


def flash(robot: Robot, request: FlashRequest, *, progress: ProgressFn | None = None,
          cancel: threading.Event | None = None) -> FlashResult:
    """Program the request's image into the selected boards of every selected bus, in
    parallel (:meth:`Robot.each`); ``progress`` is told the bytes sent per bus,
    ``cancel`` stops the job at its next step (every bus's boards put back:
    :class:`FlashInterrupted`).

    Boards whose plug-on board, FPGA (Board-ID, App-ID, major version) do not fit the
    image's descriptor are refused unless ``request.force``; a minor version difference or
    a missing descriptor is a warning."""
    plan = request.transfer()
    cancel = cancel or threading.Event()
    job = BusJob(request, plan, progress, cancel)

    def one(h: BusHandle) -> BusFlash:
        if job.stops:  # an interrupted job begins no other bus
            return not_begun(h, NOT_BEGUN)
        return job.run(h)

    results, interrupt = robot.each_until_stopped(one, request.bus, cancel=cancel)
    stop: BaseException | None = interrupt or next(
        (job.stops[r.bus] for r in results if r.bus in job.stops), None)
    if stop is not None:  # a bus whose job was done when the others were interrupted
        results = [r if r.interrupted else replace(r, interrupted=FINISHED) for r in results]
    result = FlashResult(request.image.name, plan.progid, plan.size_words, request.target,
                         tuple(results))
    if stop is not None:
        raise FlashInterrupted(result) from stop
    return result


def interrupted_before(robot: Robot, request: FlashRequest, phase: str) -> FlashResult:
    """What a flash interrupted before its job began left (``phase``: listening, reading
    the values to keep, the reset): every selected bus
    :func:`~ucom_tools.ops.flash_types.not_begun`."""
    plan = request.image.plan(target=request.target)
    return FlashResult(request.image.name, plan.progid, plan.size_words, request.target,
                       tuple(not_begun(h, phase) for h in robot.select(request.bus)))


def listen_first(robot: Robot, bus: str | None = None) -> None:
    """Listen on the selected buses, all at once, before anything is sent to them: for as
    long as a host that is programming leaves its bus silent (:func:`~ucom_tools.protocol.
    programmer.quiet_time`, a fraction of a second over socketcand).  BusError naming
    what was seen when another host is programming one of them."""
    def one(h: BusHandle) -> None:
        with ProgrammingWatch(h.link) as watch:
            watch.listen(quiet_time(h.link, h.client.timeouts))
            watch.check(h.name, "nothing was sent; try again when it is done")

    robot.each(one, bus)
