"""Serve each bus of a fleet from a process of its own (``ucom fleet serve``, the default
``--processes auto`` for a topology with more than one bus).

Why: a served fleet is paced to the wall clock by one driver thread per process
(:class:`~ucom_tools.virtual.bus.clock.RealtimeDriver`), and Python runs one thread at a time
per process.  ARMAR-III has 11 boards on 4 buses, each board running its exchange at
1 kHz; in one process that is more than one core's work, the fleet falls behind real time
and the boards' watchdogs fire.  Served from one process per bus, the buses run on as
many cores as there are.

Why it is the same fleet: within a bus nothing changes - its boards and clients share
one simulated bus in one process, as before.  Buses never interact (each board is on
exactly one bus).  And the project's rule "one fleet clock" (every bus and board of a
fleet on one time base) holds across the processes: paced, a fleet's time base is the
wall clock, ``time.monotonic()``, which is the same clock in every process of the system;
each process steps its bus at the pace of that clock, so the buses stay in step by
construction, as they do in one process.  The frame timestamps clients get are the wall
clock's (``time.time()`` at the frame's end) on every bus alike: each process sets its
fleet's epoch so that virtual time maps to the wall clock.  Only the virtual time's
origin (when a process powered its boards) differs between buses, and nothing compares
virtual times of two buses.

How::

    main process                                  one process per bus (spawned)
    listens on HOST:PORT, counts clients          a Fleet of its bus only, paced
    accepts, greets  < hi >                       serves handed-over clients with
    reads up to the client's  < open BUS >  --->  Connection.resume: < ok >, rawmode,
    (errors answered as Connection does)   socket  frames ... exactly as in one process
                                           + bytes
                                           read after
    slot free again  <------------------ "done"

The main process hands the connected socket itself over (``SCM_RIGHTS`` on a Unix
``SOCK_SEQPACKET`` pair, one long-lived control channel per process, one message per
connection together with the bytes the client sent after its open), so frames go
straight between client and bus process.  Elements before the open get the same answers
as from one process (:func:`~ucom_tools.virtual.serve.elements.check_open` and the
texts of :mod:`~ucom_tools.virtual.serve.connection`); ``--max-clients`` counts the
connections of every bus: a slot is taken at accept and freed when the client leaves
before opening, or when its bus process reports the connection ended.

In modules by job: this one starts and stops the whole (:class:`MultiServer`) and
chooses the processes (:func:`bus_groups`, :func:`auto_processes`);
:mod:`~ucom_tools.virtual.serve.multiserve_dispatch` is the main process's server up to a
client's open; :mod:`~ucom_tools.virtual.serve.multiserve_bus` is a bus process and the main
process's handle of it.

The processes are started with ``spawn`` (never ``fork`` after threads exist), with SIGINT
ignored: Ctrl-C reaches the whole process group, and the main process stops them in
order (closing the clients, stopping the driver, so the boards' state files are complete;
they are written atomically anyway).  SIGTERM to the main process does the same.  A bus
process stops by itself when the main process is gone (its control channel closes), and
on SIGTERM.  One that ends while serving makes the whole serve stop with
:class:`~ucom_tools.errors.BusError` naming its bus (exit code 4).  Bus processes log to
stderr with the main process's format and level.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from ucom_tools.config.topology import Topology
from ucom_tools.errors import BusError
from ucom_tools.signals import Terminated
from ucom_tools.virtual.serve.multiserve_bus import LOG_FORMAT, BusConfig, BusProcess
from ucom_tools.virtual.serve.multiserve_dispatch import ClientRouter
from ucom_tools.virtual.serve.outbox import MAX_QUEUED_FRAMES
from ucom_tools.virtual.serve.socketcand import MAX_CLIENTS

__all__ = ["LOG_FORMAT", "START_TIMEOUT_S", "STOP_TIMEOUT_S", "MultiServer", "auto_processes",
           "bus_groups", "sigterm_interrupts", "usable_cores"]

log = logging.getLogger("ucom.serve")

START_TIMEOUT_S = 60.0
"""How long a bus process may take from its start to serving (imports, its boards)."""
STOP_TIMEOUT_S = 5.0
"""How long a bus process may take to stop once asked; then it is killed."""


class MultiServer:
    """Every bus of a topology served from a process of its own, behind one TCP port.

    ``MultiServer(...)`` listens (``OSError`` when it cannot), :meth:`start` starts the
    bus processes and waits until each serves its bus (raising the first one's error,
    e.g. :class:`~ucom_tools.errors.InputError` for an unusable state file), and
    :meth:`serve_until_interrupted` serves until Ctrl-C or SIGTERM; it raises
    :class:`~ucom_tools.errors.BusError` naming the bus when a bus process ended."""

    def __init__(self, topology: Topology, host: str = "127.0.0.1", port: int = 0, *,
                 state_dir: Path | None = None, max_clients: int = MAX_CLIENTS,
                 max_queued_frames: int = MAX_QUEUED_FRAMES,
                 log_level: int = logging.WARNING,
                 switch_interval: float | None = None,
                 fleet_options: Mapping[str, Any] | None = None,
                 processes: int | None = None) -> None:
        self.topology = topology
        self._failed = threading.Event()
        self.failure: str | None = None
        self.buses: dict[str, BusProcess] = {}
        """The process of each bus."""
        self.processes: list[BusProcess] = []
        self.dispatcher = ClientRouter(host, port, self.buses, topology.name,
                                     max_clients=max_clients, topology=topology)
        for group in bus_groups(topology, processes):
            worker = BusProcess(BusConfig(topology, group, state_dir, max_queued_frames,
                                          log_level, switch_interval,
                                          dict(fleet_options or {})), self._ended)
            self.processes.append(worker)
            self.buses.update(dict.fromkeys(group, worker))
        self._thread: threading.Thread | None = None
        self._closed = False

    @property
    def address(self) -> tuple[str, int]:
        return self.dispatcher.address

    def pids(self) -> dict[str, int | None]:
        """The process of each bus."""
        return {bus: worker.pid for bus, worker in self.buses.items()}

    def start(self, timeout: float = START_TIMEOUT_S) -> None:
        """Start the bus processes and wait until every one serves its buses."""
        for worker in self.processes:
            worker.start()
        deadline = time.monotonic() + timeout
        for worker in self.processes:
            if not worker.ready.wait(max(0.0, deadline - time.monotonic())):
                raise BusError(f"the process of {worker.label} did not start serving in "
                               f"{timeout:g} s")
            if worker.error is not None:
                raise worker.error
        self._thread = threading.Thread(target=self.dispatcher.serve_forever, args=(0.2,),
                                        name="ucom-socketcand", daemon=True)
        self._thread.start()

    def serve_until_interrupted(self) -> None:
        """Serve until Ctrl-C or SIGTERM, then stop everything and raise the interrupt on
        (the command's exit code says how it ended); BusError when a bus process ended
        meanwhile."""
        try:
            with sigterm_interrupts():
                while not self._failed.wait(0.2):
                    pass
        finally:
            self.close()
        if self.failure is not None:
            raise BusError(self.failure)

    def close(self) -> None:
        """Stop listening, stop every bus process (their clients are closed), wait for
        them (idempotent)."""
        if self._closed:
            return
        self._closed = True
        if self._thread is not None:
            self.dispatcher.shutdown()
            self._thread.join(2.0)
        self.dispatcher.server_close()
        for worker in self.processes:
            worker.stop()
        for worker in self.processes:
            worker.join(STOP_TIMEOUT_S)

    def __enter__(self) -> MultiServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _ended(self, worker: BusProcess) -> None:
        if worker.stopping or not worker.ready.is_set() or worker.error is not None:
            return  # asked to stop, or failed to start (start() reports that)
        if self.failure is None:
            whose = (f"bus {worker.label}: its" if len(worker.buses) == 1 else
                     f"buses {worker.label}: their")
            self.failure = (f"{whose} process (pid {worker.pid}) ended "
                            f"({worker.how_it_ended()}); stopped serving {self.topology.name}")
        self._failed.set()


def usable_cores() -> int:
    """The cores this process may run on: its CPU affinity where the system keeps one
    (``os.sched_getaffinity``, Linux), else ``os.cpu_count()``; at least 1."""
    affinity = getattr(os, "sched_getaffinity", None)
    if affinity is not None:
        with contextlib.suppress(OSError):
            return max(1, len(affinity(0)))
    return max(1, os.cpu_count() or 1)


def auto_processes(topology: Topology) -> int:
    """``--processes auto``: one process per bus, but no more than there are cores to
    run them (a process per bus beyond that only adds switching)."""
    return max(1, min(len(topology.buses), usable_cores()))


def bus_groups(topology: Topology, processes: int | None = None) -> list[tuple[str, ...]]:
    """The buses of each process: one bus each (``processes`` None), else ``processes``
    groups (at most one per bus) with as even a share of the boards as can be, each
    group's buses in topology order."""
    specs = list(topology.buses)
    count = len(specs) if processes is None else max(1, min(processes, len(specs)))
    groups: list[list[int]] = [[] for _ in range(count)]
    boards = [0] * count
    for index in sorted(range(len(specs)), key=lambda i: -len(specs[i].boards)):
        lightest = min(range(count), key=lambda g: (boards[g], len(groups[g]), g))
        groups[lightest].append(index)
        boards[lightest] += len(specs[index].boards)
    return sorted((tuple(specs[i].name for i in sorted(group)) for group in groups),
                  key=lambda names: [s.name for s in specs].index(names[0]))


@contextlib.contextmanager
def sigterm_interrupts() -> Iterator[None]:
    """SIGTERM raises :class:`~ucom_tools.signals.Terminated` (a KeyboardInterrupt)
    meanwhile, as Ctrl-C does (in the main thread)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum: int, frame: Any) -> None:
        raise Terminated(signum)

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
