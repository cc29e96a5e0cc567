"""Bringing a running board into the cyclic exchange: the start sequence of
``man/ucom-protocol.7`` (RUN TIME, Start sequence), one board at a time.

Start (bootloader) -> MCA Ready -> DumpIO Descr exchange -> mapping check against the
board's attribute-tree block -> PAR and CI defaults of the tree -> Admin Data (watchdog
time, SO maps, CI maps) -> MCA Start.  A board whose edges differ from its tree is not
configured at all (nothing is written to it); a value of the tree that the board's edge
cannot carry is refused before anything is sent.

Before a host starts an exchange it listens (:class:`ExchangeWatch`): MCA Alive or CI
maps it did not send mean that another host runs the exchange on that bus, and a second
start would take its boards from it.
"""

from __future__ import annotations

import operator
import struct
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Final

import can

from ucom_tools.config.attrtree.match import compare, program_of
from ucom_tools.config.attrtree.model import BoardBlock, Edge, TreeEdgeKind
from ucom_tools.config.attrtree.robot import RobotTrees
from ucom_tools.config.topology import BusSpec
from ucom_tools.edgelists.model import EdgeKind
from ucom_tools.errors import BoardError, BusTaken, InputError, UcomTimeoutError
from ucom_tools.ops.edges import spec_of
from ucom_tools.protocol.bootloader import BootloaderClient
from ucom_tools.protocol.link import Link
from ucom_tools.protocol.mca import MASK_TABLE, BoardEdges, McaClient, values_of
from ucom_tools.protocol.periodic import Periodic
from ucom_tools.protocol.plan import BusPlan, CiMapPlan, needs_of, plan
from ucom_tools.protocol.timeouts import DEFAULT, Timeouts
from ucom_tools.protocol.watch import OtherHosts
from ucom_tools.wire import mca
from ucom_tools.wire.codes import ErrorCode
from ucom_tools.wire.ids import ALL, Address, Function, seq

_KIND: Final = {TreeEdgeKind.CI: mca.Kind.CI, TreeEdgeKind.SO: mca.Kind.SO,
                 TreeEdgeKind.PAR: mca.Kind.PAR}


LISTEN_MIN_S: Final = 0.25
"""The shortest listen for another host's exchange: its loop, or the transport between,
may be held by a busy machine for a moment (another host whose watchdog time is long,
500 ms say, keeps its boards running through a stall of a hundred milliseconds; measured:
a second run beside such a host on a loaded machine missed it about once in ten with
a listen of its own watchdog time, 50 ms)."""


class NoProgram(BoardError):
    """A board refused Start: it holds no complete, verified program (Error
    NO_PROGRAM)."""


class ExchangeError(InputError):
    """A board cannot join the exchange (its edges differ from its tree, a default does
    not fit its edge); nothing was written to it."""


@dataclass(frozen=True)
class Configured:
    """A board ready for MCA Start: its described edges and what was written."""

    address: Address
    edges: BoardEdges
    written: dict[str, int]
    """Unique (tree) name -> raw value written."""


def edge_list(edges: BoardEdges) -> list[tuple[EdgeKind, str]]:
    return [(EdgeKind(k), r.name) for k in mca.Kind for r in edges.of(k)]


def on_board(tree: BoardBlock, edges: BoardEdges) -> Iterator[tuple[Edge, mca.Kind, int]]:
    """Every edge of a tree block that matches the board's description ``edges``, with
    its kind and index on the board: the tree counts its edges CI, SO, PAR on, the board
    each kind from 0 (``man/ucom-tree.5``)."""
    first = {k: sum(len(edges.of(j)) for j in mca.Kind if j < k) for k in mca.Kind}
    for e in tree.edges:
        kind = _KIND[e.kind]
        yield e, kind, e.index - first[kind]


def defaults_raw(tree: BoardBlock, edges: BoardEdges, where: str, tree_file: str | None = None,
                 ) -> list[tuple[mca.Kind, int, int, str]]:
    """(kind, per-kind index, raw value, unique name) of every default of ``tree``, in
    tree order; ExchangeError naming the tree line when a value does not fit its edge."""
    out = []
    for e, kind, index in on_board(tree, edges):
        if e.default is None:
            continue
        spec = spec_of(kind, edges.of(kind)[index])
        try:
            raw = spec.raw(e.default.text)
        except ValueError as err:
            raise ExchangeError(f"{where}: default of {e.unique} ({e.generic}) "
                                f"{e.default.text}: {err}",
                                file=tree_file, line=e.default_line or None) from None
        out.append((kind, index, raw, e.unique))
    return out


def configure(client: McaClient, address: Address, where: str, tree: BoardBlock,
              bus_plan: BusPlan, *, tree_file: str | None = None,
              edges: BoardEdges | None = None) -> Configured:
    """Describe, check and configure one STOPPED (or LATCHED) board; it is left stopped."""
    if edges is None:
        edges = client.describe(address)
    mismatch = compare(tree, edge_list(edges))
    if mismatch is not None:
        raise ExchangeError(f"{where} runs a program whose edges differ from its tree: "
                            f"{mismatch.message}", file=tree_file,
                            line=mismatch.line or None)
    values = defaults_raw(tree, edges, where, tree_file)
    written: dict[str, int] = {}
    for kind in (mca.Kind.PAR, mca.Kind.CI):
        write_runs(client, address, kind, [(i, raw) for k, i, raw, _ in values if k is kind],
                    edges.of(kind))
    for _kind, _i, raw, unique in values:
        written[unique] = raw
    board = address.number
    client.admin(address, mca.AdminData(mca.AdminOp.CLEAR_MAPS))
    client.admin(address, mca.AdminData.alive(bus_plan.alive_ms))
    for m in bus_plan.maps_of(board):
        client.admin(address, mca.AdminData.so_map(m.number, m.period, m.edges))
    for c in bus_plan.ci_maps:
        slots = c.slots_of(board)
        if any(s != mca.NO_EDGE for s in slots):
            client.admin(address, mca.AdminData.ci_map(c.number, slots))
    return Configured(address, edges, written)


def write_runs(client: McaClient, address: Address, kind: mca.Kind,
                values: Sequence[tuple[int, int]], records: Sequence[mca.EdgeRecord]) -> None:
    """Write values, consecutive indices together (as few frames as fit)."""
    values = sorted(values)
    i = 0
    while i < len(values):
        j = i + 1
        while j < len(values) and values[j][0] == values[j - 1][0] + 1:
            j += 1
        client.write(address, kind, values[i][0], [raw for _, raw in values[i:j]], records)
        i = j


def plan_bus(bus: BusSpec, trees: RobotTrees, *, alive_ms: int = mca.ALIVE_DEFAULT_MS,
             periods: dict[str, int] | None = None) -> BusPlan:
    """The default exchange of one bus of a robot: every board's program (recognised by
    its tree's edges) with its default periods, for the joints the topology gives it
    (seq ID = position in the init chain).  A board whose tree maps no known program has
    no maps (the mapping check keeps it from starting)."""
    needs = []
    for spec in bus.boards:
        try:
            board = trees.board(bus.name, spec.position)
        except KeyError:
            continue
        program = program_of(board)
        if program is None:
            continue  # the mapping check will name its differences; it does not start
        needs.append(needs_of(spec.position + 1, spec.placement, program,
                              axes=len(spec.joints) or None, periods=periods))
    return plan(bus.name, bus.bitrate, needs, alive_ms=alive_ms)


def _getter(keys: Sequence[tuple[int, int]],
            ) -> Callable[[dict[tuple[int, int], int]], tuple[int, ...]]:
    """``lambda ci: tuple(ci[k] for k in keys)``, as one C call where there are two keys
    or more (``operator.itemgetter``: a CI map's values, every cycle)."""
    if len(keys) >= 2:
        return operator.itemgetter(*keys)
    return lambda ci: tuple(ci[k] for k in keys)


def _packer(signs: Sequence[tuple[int, bool]]) -> struct.Struct:
    """A struct that packs values of these (width, signed) big-endian, as
    :func:`~ucom_tools.wire.mca.pack_values` does (:func:`~ucom_tools.wire.mca.
    values_struct`; KeyError for a width it has no code for)."""
    packer = mca.values_struct(signs)
    if packer is None:
        raise KeyError(f"no struct code for the widths of {list(signs)}")
    return packer


class ExchangeWatch(OtherHosts):
    """Another host's cyclic exchange: MCA Alive and CI maps (process data) this host did
    not send (``man/ucom-protocol.7``, RUN TIME, Start sequence)."""

    def __init__(self, link: Link) -> None:
        super().__init__(link)
        # an instance field, not a class-level default (see compiled.py)
        self.functions = frozenset({Function.MCA_ALIVE, Function.MCA_CONTROLLER_INPUT})

    def judge(self, arbitration_id: int, data: bytes) -> str | None:
        if arbitration_id >> 6 == Function.MCA_ALIVE:
            return "MCA Alive"
        if arbitration_id & 0x20:  # type bit 1: process data, map number in bits 4-0
            return f"CI map {arbitration_id & 0x1F}"
        return None  # an acknowledged CI write: a console, say, not an exchange

    @staticmethod
    def listen_time(link: Link, alive_ms: int = mca.ALIVE_DEFAULT_MS,
                    floor: float = LISTEN_MIN_S) -> float:
        """How long to listen: the boards' watchdog time (a running exchange sends MCA
        Alive five times in it, :data:`~ucom_tools.protocol.plan.ALIVE_DIVISOR`, and CI
        maps more often) and the transport's margin, at least ``floor`` (on the wall
        clock :data:`LISTEN_MIN_S`; in virtual time no host is held by its machine)."""
        return max(link.budget(alive_ms / 1000, answers=1), floor)

    def check(self, bus: str) -> None:
        """:class:`~ucom_tools.errors.BusTaken` naming what was seen, if another host runs
        an exchange on ``bus``."""
        if self.seen:
            raise BusTaken(f"another host runs the cyclic exchange on {bus} (frames from "
                           f"another host: {self.summary()}); nothing was sent")


class BusExchange:
    """The PC side of one bus's cyclic exchange (``man/ucom-protocol.7``, RUN TIME):
    brings its boards up (:meth:`bring_up`), then sends the CI maps at their periods and
    MCA Alive at a fifth of the watchdog time as periodic tasks of the bus's dispatcher,
    and keeps the latest SO values.  Whoever waits on the bus (:meth:`pump`, a console
    command) keeps the periodic frames going."""

    def __init__(self, link: Link, bus: BusSpec, trees: RobotTrees, *,
                 alive_ms: int = mca.ALIVE_DEFAULT_MS, timeouts: Timeouts = DEFAULT,
                 periods: dict[str, int] | None = None) -> None:
        self.link = link
        self.bus = bus
        self.trees = trees
        self.boot = BootloaderClient(link, timeouts)
        self.mca = McaClient(link, timeouts)
        self.plan = plan_bus(bus, trees, alive_ms=alive_ms, periods=periods)
        self.configured: dict[int, Configured] = {}
        self.ci: dict[tuple[int, int], int] = {}
        """(board, CI index) -> the raw value the CI maps carry."""
        self._tasks: list[Periodic] = []
        self._ci_frames: list[tuple[CiMapPlan, list[tuple[int, int]], list[tuple[int, bool]]]] \
            = []
        self._ci_fast: list[tuple[int, struct.Struct]] = []
        self._alive = can.Message(arbitration_id=mca.encode(mca.Alive(), ALL)[0], data=b"",
                                  is_extended_id=False)
        self._indices: dict[tuple[int, int, str], int] = {}
        """(board, kind, generic name) -> the edge's index (:meth:`index`), as found in
        the boards' descriptions; emptied when a board is configured again."""
        self._mapped: frozenset[tuple[int, int]] = frozenset(
            s for c in self.plan.ci_maps for s in c.slots if s is not None)
        """(board, CI index) of every CI a CI map carries (:meth:`set_ci`)."""

    # ------------------------------------------------------------------ start sequence
    def where(self, n: int) -> str:
        spec = self.bus.boards[n - 1] if 0 < n <= len(self.bus.boards) else None
        return f"{self.bus.name} board {n}" + (f" ({spec.placement})" if spec else "")

    def start_programs(self, numbers: Sequence[int]) -> dict[int, mca.McaReady]:
        """Bootloader Start of each board; the MCA Ready its program sends when it is up
        (boards that do not announce themselves are asked)."""
        readies: dict[int, mca.McaReady] = {}
        for n in numbers:
            answers = self.boot.start(seq(n))
            if not answers:  # it went away between its check and its start
                raise UcomTimeoutError(f"{self.where(n)}: no answer to Start")
            started = answers[0]
            if not started.started:
                why = "; ".join(e.describe() for e in started.errors) or "no answer"
                empty = bool(started.errors) and all(
                    e.code is ErrorCode.NO_PROGRAM for e in started.errors)
                raise (NoProgram if empty else BoardError)(
                    f"{self.where(n)}: its program did not start: {why}")
            ready = self.mca.wait_ready(seq(n), self.mca.timeouts.reply)
            if ready is None:
                raise UcomTimeoutError(f"{self.where(n)}: its program does not answer MCA "
                                       "requests (not a run-time program?)")
            readies[n] = ready
        return readies

    def configure_all(self, numbers: Sequence[int]) -> None:
        """Configure each of these boards with its tree block (:meth:`configure_board`)."""
        for n in numbers:
            spec = self.bus.boards[n - 1]
            self.configure_board(n, self.trees.board(self.bus.name, spec.position),
                                 tree_file=str(spec.tree) if spec.tree else None)

    def configure_board(self, n: int, block: BoardBlock, *, tree_file: str | None = None,
                        edges: BoardEdges | None = None) -> Configured:
        """Configure board ``n`` with its tree ``block`` (:func:`configure`; ``edges``: its
        description when it was already fetched), then seed the CI values the exchange
        sends it from the first cycle on: for every CI the board describes, the tree's
        default where it has one, else 0 (or the value set before, on a restart).  The
        one place this is decided, for :meth:`bring_up` and for
        :class:`~ucom_tools.ops.remote.RemotePart`."""
        c = configure(self.mca, seq(n), self.where(n), block, self.plan,
                      tree_file=tree_file, edges=edges)
        self.configured[n] = c
        self._indices.clear()
        for index in range(len(c.edges.ci)):
            self.ci.setdefault((n, index), 0)
        for unique, raw in c.written.items():
            e = block.edge(unique)
            if e.kind is TreeEdgeKind.CI:
                self.ci[(n, e.index)] = raw
        return c

    def start_exchange(self, *, periodic: bool = True) -> None:
        """Start the periodic frames (``periodic``: as tasks of the dispatcher; otherwise
        the caller sends them with :meth:`send_cycle`), then MCA Start START on every
        configured board."""
        self._prepare_ci()
        if periodic:
            self._start_tasks()
        for n in self.configured:
            state = self.mca.start(seq(n)).state
            if state is not mca.RunState.RUNNING:
                raise BoardError(f"{self.where(n)}: MCA Start left it {state.name}")

    def bring_up(self, numbers: Sequence[int] | None = None) -> None:
        numbers = list(numbers or [b.position + 1 for b in self.bus.boards])
        self.start_programs(numbers)
        self.configure_all(numbers)
        self.start_exchange()

    # ------------------------------------------------------------------ cyclic
    def _prepare_ci(self) -> None:
        self._ci_frames = []
        for c in self.plan.ci_maps:
            used = [s for s in c.slots if s is not None]
            signs = [(2, self.configured[b].edges.ci[i].signed) if b in self.configured
                     else (2, True) for b, i in used]
            self._ci_frames.append((c, used, signs))
        self._ci_fast = [(mca.MapFrame(Function.MCA_CONTROLLER_INPUT, c.number, bytes(2))
                          .arbitration_id(), _packer(signs)) for c, _, signs in self._ci_frames]
        """Per CI map: its identifier, and a struct that packs its values (16 bit each)."""
        self._alive = can.Message(arbitration_id=mca.encode(mca.Alive(), ALL)[0], data=b"",
                                  is_extended_id=False)
        self._ci_sent = [-1e9] * len(self._ci_frames)
        """When each CI map was last sent (bus clock), by index."""
        self._ci_last: list[tuple[tuple[int, ...], bytes] | None] = \
            [None] * len(self._ci_frames)
        """Each CI map's values last sent and their payload (values that did not change
        are not packed again)."""
        self._alive_sent = -1e9
        self._ci_cyclic = [(k, c.interval_us / 1e6, ident, packer, _getter(used), c.number,
                            signs)
                           for k, ((c, used, signs), (ident, packer))
                           in enumerate(zip(self._ci_frames, self._ci_fast, strict=True))]
        """What :meth:`send_cycle` needs of each CI map, looked up once: its index, its
        interval in seconds, identifier, packer, the values of its slots (from
        :attr:`ci`), number and signs."""
        self._alive_interval = self.plan.alive_interval_us / 1e6

    def send_cycle(self, now: float) -> int:
        """One cycle of a PC loop at ``now`` (bus clock, seconds): every CI map whose
        interval has passed since it was last sent, and MCA Alive likewise; frames sent.
        Due by time, not by cycle count, so a loop that skips cycles still keeps them."""
        margin = 1e-4  # a cycle that comes a little early still counts
        ci, ci_sent, ci_last = self.ci, self._ci_sent, self._ci_last
        mask_table = MASK_TABLE
        frames: list[tuple[int, bytes]] = []
        due: list[int] = []  # the CI maps of frames, by index (-1: MCA Alive)
        try:
            for k, interval, ident, packer, values_of_ci, number, signs in self._ci_cyclic:
                if now - ci_sent[k] + margin >= interval:
                    values = values_of_ci(ci)
                    last = ci_last[k]
                    if last is not None and last[0] == values:
                        data = last[1]
                    else:
                        try:  # _ci_data(), inlined
                            data = packer.pack(*values).translate(mask_table)
                        except struct.error:
                            data = self._ci_data(number, signs, packer, values)
                        ci_last[k] = (values, data)
                    frames.append((ident, data))
                    due.append(k)
            if now - self._alive_sent + margin >= self._alive_interval:
                frames.append((self._alive.arbitration_id, b""))
                due.append(-1)
        finally:  # one call for the cycle's frames (those before an error too), each
            link = self.link  # noted as sent once the link has taken it
            before = link.frames_sent
            try:
                link.send_frames(frames)
            finally:
                for k in due[:link.frames_sent - before]:
                    if k < 0:
                        self._alive_sent = now
                    else:
                        ci_sent[k] = now
        return len(frames)

    @staticmethod
    def _ci_data(number: int, signs: list[tuple[int, bool]], packer: struct.Struct,
                 values: Sequence[int]) -> bytes:
        """A CI map's payload as the wire carries it (masked); a value that does not fit
        raises the FrameError :func:`~ucom_tools.wire.mca.pack_values` gives."""
        try:
            return mca.mask(packer.pack(*values))
        except struct.error:
            return mca.MapFrame(Function.MCA_CONTROLLER_INPUT, number,
                                mca.pack_values(signs, values)).encode()

    def start_alive(self) -> None:
        """MCA Alive as a periodic task of the dispatcher (until :meth:`stop_tasks`)."""
        alive = [(self._alive.arbitration_id, b"")]
        self._tasks.append(self.link.dispatcher.every(
            self.plan.alive_interval_us / 1e6, lambda: alive, f"{self.bus.name} MCA Alive"))

    def _start_tasks(self) -> None:
        self.stop_tasks()
        d = self.link.dispatcher
        by_interval: dict[float, list[int]] = {}
        for k, (c, _, _) in enumerate(self._ci_frames):
            by_interval.setdefault(c.interval_us, []).append(k)
        for interval, indices in sorted(by_interval.items()):
            self._tasks.append(d.every(interval / 1e6, self._ci_messages(indices),
                                       f"{self.bus.name} CI maps every {interval:g} us"))
        self.start_alive()

    def _ci_messages(self, indices: list[int]) -> Callable[[], list[tuple[int, bytes]]]:
        """The CI maps ``indices`` as a periodic task's frames (identifier, data)."""
        def frames() -> list[tuple[int, bytes]]:
            out = []
            ci, ci_last, cyclic = self.ci, self._ci_last, self._ci_cyclic
            for k in indices:  # values that did not change are not packed again
                _, _, ident, packer, values_of_ci, number, signs = cyclic[k]
                values = values_of_ci(ci)
                last = ci_last[k]
                if last is not None and last[0] == values:
                    data = last[1]
                else:
                    data = self._ci_data(number, signs, packer, values)
                    ci_last[k] = (values, data)
                out.append((ident, data))
            return out
        return frames

    def stop_tasks(self) -> None:
        for t in self._tasks:
            self.link.dispatcher.cancel(t)
        self._tasks = []

    @property
    def tasks(self) -> list[Periodic]:
        return list(self._tasks)

    def pump(self, until: float) -> None:
        """Run the exchange (receive, send what is due) until ``until`` on the bus clock."""
        self.link.dispatcher.pump(until)

    def index(self, n: int, kind: mca.Kind, name: str) -> int:
        """The index of board ``n``'s edge of ``kind`` called ``name`` (generic), as it
        described it; KeyError if it has none (looked up once: set_ci runs per value)."""
        key = (n, int(kind), name)
        found = self._indices.get(key)
        if found is not None:
            return found
        records = self.configured[n].edges.of(kind)
        for i, r in enumerate(records):
            if r.name == name:
                self._indices[key] = i
                return i
        raise KeyError(f"{self.where(n)} has no {kind.name} edge {name!r}")

    def forget_indices(self) -> None:
        """Look the edges' indices up again (:meth:`index`): a board was configured anew."""
        self._indices.clear()

    def ci_mapped(self, n: int, index: int) -> bool:
        """Does CI edge ``index`` of board ``n`` travel in a CI map (sent every cycle)?"""
        return (n, index) in self._mapped

    def set_ci(self, n: int, name: str, raw: int) -> None:
        """The raw value CI edge ``name`` (generic) of board ``n`` gets from now on: in its
        CI map if it has one, else written with acknowledgement now."""
        i = self.index(n, mca.Kind.CI, name)
        self.ci[(n, i)] = raw
        if (n, i) not in self._mapped:
            self.mca.write(seq(n), mca.Kind.CI, i, [raw], self.configured[n].edges.ci)

    def so(self, n: int, name: str) -> int | None:
        """The latest raw value of SO edge ``name`` (generic) of board ``n`` from its map
        (None: not cyclic, or nothing arrived yet)."""
        i = self.index(n, mca.Kind.SO, name)
        records = self.configured[n].edges.so
        for m in self.plan.maps_of(n):
            if i in m.edges and m.number in self.mca.image.frames:
                values = values_of(self.mca.image.frames[m.number],
                                   [records[j] for j in m.edges])
                return values[m.edges.index(i)]
        return None

    def stop(self) -> None:
        """Stop every board's exchange (motors off) and the periodic frames: the orderly
        end (a PC that just vanishes is caught by the boards' watchdogs)."""
        try:
            for n in self.configured:
                self.mca.start(seq(n), mca.StartOp.STOP)
        finally:
            self.stop_tasks()

    def close(self) -> None:
        self.stop_tasks()
        self.mca.close()
