"""Shared fixtures: each test gets its own fleet and host connection; none leaks out."""

from __future__ import annotations

import os
import signal
import threading
import warnings
from collections.abc import Callable, Iterator

import pytest

from ucom_tools.config.topology import parse
from ucom_tools.protocol.bootloader import BootloaderClient
from ucom_tools.protocol.link import Link
from ucom_tools.virtual import fleet as fleet_mod
from ucom_tools.virtual.canbus import VirtualUcomBus
from ucom_tools.virtual.fleet import Fleet
from ucom_tools.virtual.serve.socketcand import FleetServer


@pytest.fixture
def served_armar3() -> Iterator[tuple[str, int]]:
    """ARMAR-III served over socketcand from this process on 127.0.0.1 (paced): its
    address."""
    fleet = Fleet.load("armar3", realtime=True)
    server = FleetServer(fleet, "127.0.0.1", 0)
    thread = threading.Thread(target=server.serve_forever, args=(0.05,), daemon=True,
                              name="test-served-armar3")
    thread.start()
    try:
        yield server.address
    finally:
        server.shutdown()
        thread.join(timeout=10)


@pytest.fixture(autouse=True)
def _no_leaked_fleets() -> Iterator[None]:
    yield
    leaked = list(fleet_mod._SHARED)
    fleet_mod.forget_shared()
    assert not leaked, f"test left shared fleets behind: {leaked}"


_DISPOSED = (signal.SIGINT, signal.SIGHUP, signal.SIGTERM)


def _ignored() -> set[int]:
    """The signals this process ignores, as the kernel has it (a native library may set
    SIG_IGN behind Python's back); empty where /proc is not there."""
    try:
        with open("/proc/self/status") as f:
            mask = next(int(line.split()[1], 16) for line in f if line.startswith("SigIgn:"))
    except (OSError, StopIteration):
        return set()
    return {s for s in _DISPOSED if mask >> (s - 1) & 1}


def _signals_as_a_shell_leaves_them() -> None:
    """A suite started with the stop signals ignored (a shell's background job ignores
    SIGINT, ``nohup`` SIGHUP) would hand that to every ``ucom`` it starts, which then
    survives them as under nohup: the tests that stop a job by a signal would hang.  The
    tests run with the signals as an interactive shell leaves them."""
    for s in _ignored():
        signal.signal(s, signal.default_int_handler if s == signal.SIGINT else signal.SIG_DFL)


@pytest.fixture(autouse=True)
def _signal_dispositions_restored(request: pytest.FixtureRequest) -> Iterator[None]:
    """A test that leaves SIGINT, SIGHUP or SIGTERM ignored (or handled otherwise) in this
    process is named, and the handlers put back: a child process inherits an ignored
    signal, and ``ucom`` then survives it as under nohup (the signal tests would hang)."""
    before = {s: signal.getsignal(s) for s in _DISPOSED}
    ignored = _ignored()
    yield
    if threading.current_thread() is not threading.main_thread():
        return
    changed = {s for s in _DISPOSED
               if before[s] is not None and signal.getsignal(s) != before[s]}
    changed |= _ignored() - ignored
    for s in changed:
        handler = before[s]
        if handler is None or handler == signal.getsignal(s):  # set behind Python's back
            handler = signal.default_int_handler if s == signal.SIGINT else signal.SIG_DFL
        signal.signal(s, handler)
    if changed:
        names = ", ".join(signal.Signals(s).name for s in sorted(changed))
        warnings.warn(f"{request.node.nodeid} left {names} changed (put back)", stacklevel=1)


class Host:
    """A host connection to one bus of a fleet, with the protocol clients on it."""

    def __init__(self, fleet: Fleet, bus: str) -> None:
        self.fleet = fleet
        self.can = VirtualUcomBus(bus, fleet=fleet)
        self.sim = self.can.sim
        self.link = Link(self.can, bus)
        self.client = BootloaderClient(self.link)

    @property
    def boards(self) -> list:
        return self.fleet.boards[self.sim.name]

    def close(self) -> None:
        self.can.shutdown()


@pytest.fixture
def host() -> Iterator[Callable[..., Host]]:
    opened: list[Host] = []

    def make(topology: str | Fleet = "armar3", bus: str = "CAN0") -> Host:
        fleet = topology if isinstance(topology, Fleet) else Fleet.load(topology)
        h = Host(fleet, bus)
        opened.append(h)
        return h

    yield make
    for h in opened:
        h.close()


def chain_topology(n: int, *, extra: dict[int, str] | None = None, timing: str = "") -> Fleet:
    """A one-bus fleet of ``n`` three-motor boards; ``extra[i]`` adds TOML lines to board i."""
    extra = extra or {}
    text = f'name = "chain{n}"\n{timing}\n[[bus]]\nname = "CAN0"\nbitrate = 1000000\n'
    for i in range(n):
        text += f'\n[[bus.board]]\nplacement = "slot {i + 1}"\nboard = "3M"\n{extra.get(i, "")}\n'
    return Fleet(parse(text, f"<chain{n}>"))


_TERMINAL = ("COLUMNS", "LINES")
"""What ucom's output reads for its width: a worker of pytest-xdist (``-n``) gets them set
(to 80x24) on its way up; the tests see the environment pytest was started with."""
_WORKER_SCORES: dict[str, bool] = {}
_WORKER_CATCHES: set[str] = set()


@pytest.hookimpl(optionalhook=True)
def pytest_configure_node(node) -> None:
    """(pytest-xdist, in the controller) what a worker needs from here."""
    node.workerinput["ucom_terminal_env"] = {k: os.environ.get(k) for k in _TERMINAL}


_LONGEST_FIRST = (
    "test_deploy.py", "test_gateway_canopen.py", "test_zenoh.py", "test_mcap.py",
    "test_conformance_restore.py", "test_dbc_interop.py",
    "test_dbc.py", "test_runtime.py", "test_zenoh_config.py", "test_shared_bus.py",
    "test_remote.py", "test_multiserve.py", "test_network.py", "test_files.py",
    "test_socketcand.py", "test_remote_network.py", "test_browse_tty.py", "test_signals.py",
    "test_conformance.py", "test_decode.py", "test_conformance_mutants.py")
"""The modules that take longest (``--durations``, serial; a minute and more for the first
down to about ten seconds), handed out first under pytest-xdist (``--dist loadfile
--no-loadscope-reorder``: a module stays on one worker, so its module-scoped fleets are
built once): the last module a worker takes is then a short one, and the two workers end
together.  A module not named here only comes later; none is left out."""


def pytest_collection_modifyitems(config, items) -> None:
    """(in a pytest-xdist worker) the longest modules first (:data:`_LONGEST_FIRST`); a
    module's own tests keep their order, and a serial run its whole order."""
    if hasattr(config, "workerinput"):
        rank = {name: i for i, name in enumerate(_LONGEST_FIRST)}
        items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


def pytest_configure(config) -> None:
    _signals_as_a_shell_leaves_them()
    if hasattr(config, "workerinput"):
        for k, v in config.workerinput.get("ucom_terminal_env", {}).items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def pytest_sessionfinish(session) -> None:
    """(in a pytest-xdist worker) hand the mutation score to the controller."""
    if hasattr(session.config, "workeroutput"):
        try:
            from tests.test_conformance_mutants import CATCHES, SCORE
        except ImportError:
            return
        session.config.workeroutput["ucom_mutation_score"] = dict(SCORE)
        session.config.workeroutput["ucom_mutation_catches"] = sorted(CATCHES)


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node, error) -> None:
    """(pytest-xdist, in the controller) a worker's mutation score."""
    out = getattr(node, "workeroutput", {})
    _WORKER_SCORES.update(out.get("ucom_mutation_score", {}))
    _WORKER_CATCHES.update(out.get("ucom_mutation_catches", ()))


def pytest_terminal_summary(terminalreporter, exitstatus, config) -> None:
    """The conformance suite's mutation score, when its mutants ran (here or in the
    workers of pytest-xdist)."""
    try:
        from tests.test_conformance_mutants import CATCHES, SCORE
    except ImportError:
        return
    score = _WORKER_SCORES or SCORE
    documented = len(_WORKER_CATCHES) if _WORKER_SCORES else len(CATCHES)
    if score:
        caught = sum(score.values())
        missed = sorted(f for f, ok in score.items() if not ok)
        terminalreporter.write_line(
            f"conformance mutation score: {caught}/{len(score)} mutants caught "
            f"({documented} documented)" + (f"; missed: {', '.join(missed)}" if missed
                                            else ""))
