"""Bringing a lost board back into the running exchange without stopping the loop
(``man/ucom-protocol.7``, RUN TIME, Faults, Rejoin).

While a board is lost, :class:`Rejoin` asks it with Init Request REJOIN (its seq ID and
the serial number the start's init chain gave) every
:data:`~ucom_tools.ops.remote.faults.REJOIN_EVERY_S`; when it answers:

1. MCA Start QUERY.  Error NOT_RUNNING: it is in its bootloader; Start (12) its program
   and take its MCA Ready.  A program that runs (RUNNING, LATCHED, or STOPPED after an
   AutoStart): MCA Start STOP first unless it is STOPPED.
2. Its descriptions must be those it gave at the start, which matched its tree:
   first asked by their digest (MCA DumpIO Descr Request DLC 1, one frame each way:
   :meth:`~ucom_tools.protocol.mca.McaClient.digest`), compared with the digest of the
   start's descriptions (:meth:`RejoinHost.digest`, computed once a board).  Equal: they
   are, nothing more is read.  Different, or no digest (a program that does not know
   the request answers Error, or nothing): the descriptions themselves (MCA DumpIO
   Descr, a few edges at a time, each asked for on its own: the whole description at
   once would hold a running bus, and MCA Alive with it), which must be equal; otherwise
   it stays lost and the PC says why (where they differ).
3. Its present values (MCA Dump CI of its SO and CI edges) seed the CI values the PC
   holds for it (:meth:`~ucom_tools.edgelists.model.ProgramSpec.seed_of`: a position
   target takes its joint sensor's reading, a velocity target 0, a homing command is
   not resumed, a reference-run counter takes the board's own value), before its CI
   maps are set up, so the CI maps never carry an old target to it.
4. Configured as at the start (tree PAR and CI defaults, Admin Data: watchdog, SO and CI
   maps), then the PARs set during the run, then the present values read again (the
   joint may have moved while it was configured, unpowered) and every CI written,
   acknowledged; MCA Start START.  The loop takes it back (its event: ``rejoined``).

A question that is not answered, or a board that goes away again midway, sends it back
to step 0 (asked again); a board whose program differs, or will not start, stays lost.
The conversation runs as a :class:`~ucom_tools.protocol.stepped.Stepped` worker (its
waits stepped by the loop after each cycle's drain, the loop the buses' one reader), on
a link and clients of its own beside the run time's (their own subscriptions, so that
two boards rejoining on one bus do not take each other's answers).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final, Protocol

from ucom_tools.config.attrtree.match import program_of
from ucom_tools.edgelists.model import ProgramSpec, Seed
from ucom_tools.errors import BoardError, BusError, UcomError, UcomTimeoutError
from ucom_tools.ops.exchange import Configured, configure, write_runs
from ucom_tools.ops.realtime import like_the_loop
from ucom_tools.ops.remote.check import tree_file
from ucom_tools.ops.remote.faults import REJOIN_EVERY_S
from ucom_tools.protocol.bootloader import BootloaderClient
from ucom_tools.protocol.mca import BoardEdges, McaClient
from ucom_tools.protocol.stepped import SteppedJob
from ucom_tools.wire import mca
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import ErrorCode, Target
from ucom_tools.wire.ids import Address, Function, seq

if TYPE_CHECKING:
    from ucom_tools.config.attrtree.robot import RobotTrees
    from ucom_tools.ops.edges import EdgeRef, Names
    from ucom_tools.ops.exchange import BusExchange
    from ucom_tools.ops.realtime import RealtimeScheduling, ShortSlice
    from ucom_tools.ops.robot import Robot


class RejoinHost(Protocol):
    """What a rejoin needs of the run-time part it brings a board back into
    (:class:`~ucom_tools.ops.remote.RemotePart`, which makes the rejoins: named here by
    what it offers, so that neither module imports the other)."""

    @property
    def robot(self) -> Robot: ...
    @property
    def exchanges(self) -> dict[str, BusExchange]: ...
    @property
    def trees(self) -> RobotTrees: ...
    @property
    def names(self) -> Names: ...
    @property
    def scheduling(self) -> RealtimeScheduling | None: ...
    @property
    def time_slice(self) -> ShortSlice: ...
    def described(self, bus: str, board: int) -> BoardEdges | None: ...
    def digest(self, bus: str, board: int) -> int | None: ...
    def serial(self, bus: str, board: int) -> int: ...
    def par_values(self, bus: str, board: int) -> list[tuple[EdgeRef, int]]: ...
    def _set_lost_status(self, bus: str, board: int, status: str) -> None: ...


DESCRIBE_AT_A_TIME: Final = 4
"""Edge descriptions asked for at once while the other boards run: some 30 frames, a
few milliseconds of the bus (MCA Alive, which loses arbitration to them, goes out
every 10 ms); the whole description would hold the bus for tens of milliseconds."""


class Refused(UcomError):
    """The board answered but cannot rejoin (another program, one that will not start):
    it stays lost."""


@dataclass(frozen=True)
class Held:
    """What a rejoined board was given: per CI edge (per-kind index) its raw value."""

    ci: dict[int, int]
    started: bool
    """Its program had to be started (it was in its bootloader)."""
    state: mca.RunState
    """The run state its program was in when it answered (before the PC stopped it)."""


class Rejoin(SteppedJob):
    """Brings board ``board`` of bus ``bus`` of ``part`` back (see the module docstring):
    the loop steps it (:meth:`step`) until :attr:`done`; then :attr:`ok`, :attr:`how`
    (what was done, or why not), :attr:`answered` (when it first answered REJOIN, on the
    bus clock)."""

    is_rejoin = True  # (the loop steps PAR writes among its conversations too)
    FAILED = "cannot rejoin: "

    def __init__(self, part: RejoinHost, bus: str, board: int, delay: float = 0.0) -> None:
        self.part = part
        self.bus = bus
        self.board = board
        self.delay = delay
        """Seconds before the first question (boards lost together are asked apart)."""
        self.answered: float | None = None
        self.held: Held | None = None
        super().__init__(self._run, f"ucom-rejoin-{bus}-{board}")

    # ------------------------------------------------------------------ the worker
    def _status(self, text: str) -> None:
        self.part._set_lost_status(self.bus, self.board, text)

    def _run(self) -> None:
        part, n = self.part, self.board
        like_the_loop(part.scheduling, part.time_slice)
        x = part.exchanges[self.bus]
        link = part.robot.buses[self.bus].side_link()
        boot = BootloaderClient(link, x.mca.timeouts)
        client = McaClient(link, x.mca.timeouts, process_data=False)
        serial = part.serial(self.bus, n)
        clock = link.clock
        stepped = self._stepped
        try:
            stepped.sleep(clock, clock() + self.delay)
            while True:
                asked = clock()
                ack = boot.rejoin(n, serial, REJOIN_EVERY_S)
                if ack is None:
                    stepped.sleep(clock, asked + REJOIN_EVERY_S)
                    continue
                if self.answered is None:
                    self.answered = clock()
                self._status("back: being configured")
                try:
                    self.held = self._bring_back(boot, client, seq(n))
                except Refused as err:
                    self.how = f"cannot rejoin: {err}"
                    return
                except (BoardError, UcomTimeoutError) as err:
                    self._status(f"asking it to rejoin (the last attempt: {err})")
                    continue
                self.ok = True
                self.how = self._describe(self.held)
                return
        except BusError as err:
            self.how = f"cannot rejoin: {err}"
        finally:
            client.close()
            link.close()

    def _bring_back(self, boot: BootloaderClient, client: McaClient, address: Address,
                    ) -> Held:
        part, bus, n = self.part, self.bus, self.board
        x = part.exchanges[bus]
        where = x.where(n)
        described = part.described(bus, n)
        spec = x.bus.boards[n - 1]
        block = part.trees.board(bus, spec.position)
        program = program_of(block)
        if described is None or program is None or not program.seeds:
            raise Refused(f"{where}'s program names no joint sensors its targets could "
                          "take: nothing says which values would hold its joints")
        ready, started = self._running_program(boot, client, address, where)
        state = ready.state
        if state is not mca.RunState.STOPPED:
            client.start(address, mca.StartOp.STOP)  # motors off before anything else
        counts = (len(described.ci), len(described.so), len(described.par))
        if (ready.ci, ready.so, ready.par) != counts:
            raise Refused(f"{where} now runs a program with {ready.ci}/{ready.so}/"
                          f"{ready.par} edges, at the start {'/'.join(map(str, counts))}")
        edges = self._edges(client, address, counts, described, where)
        ci = self._seeds(client, address, program, edges)
        x.ci.update({(n, i): raw for i, raw in ci.items()})  # before its CI maps exist
        done = configure(client, address, where, block, x.plan,
                         tree_file=str(tree_file(part.trees, bus, spec.position)),
                         edges=edges)
        written = dict(done.written)
        pars = [(ref.index, raw, ref.unique) for ref, raw in part.par_values(bus, n)
                if written.get(ref.unique) != raw]
        write_runs(client, address, mca.Kind.PAR, [(i, raw) for i, raw, _ in pars],
                   edges.par)
        written.update({unique: raw for _, raw, unique in pars})
        ci = self._seeds(client, address, program, edges)  # again: it may have moved
        x.ci.update({(n, i): raw for i, raw in ci.items()})
        write_runs(client, address, mca.Kind.CI, sorted(ci.items()), edges.ci)
        x.configured[n] = Configured(address, edges, written)
        x.forget_indices()
        after = client.start(address, mca.StartOp.START)
        if after.state is not mca.RunState.RUNNING:
            raise BoardError(f"{where}: MCA Start left it {after.state.name}")
        return Held(ci, started, state)

    def _edges(self, client: McaClient, address: Address, counts: tuple[int, int, int],
               described: BoardEdges, where: str) -> BoardEdges:
        """Its descriptions, when they are those of the start (step 2): by their digest
        if it answers the start's, else read and compared (Refused, saying where they
        differ, if they are not)."""
        digest = client.digest(address)
        if digest is not None and digest == self.part.digest(self.bus, self.board):
            return described
        edges = client.describe(address, counts, at_a_time=DESCRIBE_AT_A_TIME)
        if edges != described:
            raise Refused(f"{where}'s edges are not those it described at the start "
                          f"({_difference(described, edges)}): another program?")
        return edges

    def _running_program(self, boot: BootloaderClient, client: McaClient, address: Address,
                         where: str) -> tuple[mca.McaReady, bool]:
        """Its program's MCA Ready (QUERY), after starting the program if the board is in
        its bootloader; and whether it had to be started."""
        before = len(client.errors)
        try:
            return client.query(address), False
        except BoardError:
            refusal = [e for a, e in client.errors[before:] if a == address
                       and e.function == Function.MCA_START]
            if not refusal or refusal[-1].code is not ErrorCode.NOT_RUNNING:
                raise
        # Start, ended by its program's MCA Ready (which comes only once the program
        # fits: COMPATIBILITY), not by the whole verdict window of Start, which waits
        # for a reset too (150 ms more a board; every board of an emergency stop)
        t = client.timeouts
        boot.link.send(m.Start(Target.FLASH), address)
        early = client.wait_started(address, t.reply + t.startup)
        if isinstance(early, mca.McaReady):
            return early, True
        start = next((r for r in boot.start(address) if r.address == address), None)
        refused = [] if start is None else [e for e in start.errors
                                            if e.function == Function.START]
        if refused:  # its program does not fit (COMPATIBILITY): it will not, asked again
            raise Refused(f"{where}: its program did not start: "
                          + "; ".join(e.describe() for e in refused))
        if start is None or not start.started:
            raise UcomTimeoutError(f"{where}: its program did not start: no answer")
        ready = client.wait_ready(address, client.timeouts.reply)
        if ready is None:
            raise UcomTimeoutError(f"{where}: its program does not answer MCA requests")
        return ready, True

    def _seeds(self, client: McaClient, address: Address, program: ProgramSpec,
               edges: BoardEdges) -> dict[int, int]:
        """The raw value of each CI edge that holds the joints where they stand now."""
        n = self.board
        x = self.part.exchanges[self.bus]
        rules = [program.seed_of(r.name) for r in edges.ci]
        so_index = {r.name: i for i, r in enumerate(edges.so)}
        present = client.dump(address, mca.Kind.SO, 0, len(edges.so), edges.so) \
            if any(s.seed is Seed.SENSOR for s in rules) else []
        own = client.dump(address, mca.Kind.CI, 0, len(edges.ci), edges.ci) \
            if any(s.seed is Seed.BOARD for s in rules) else []
        out: dict[int, int] = {}
        for i, (record, rule) in enumerate(zip(edges.ci, rules, strict=True)):
            if rule.seed is Seed.SENSOR:
                raw = present[so_index[rule.sensor]]
            elif rule.seed is Seed.ZERO:
                raw = 0
            elif rule.seed is Seed.BOARD:
                raw = own[i]
            else:
                raw = rule.kept(x.ci.get((n, i), 0))
            out[i] = min(max(raw, record.minimum), record.maximum)
        return out

    def _describe(self, held: Held) -> str:
        """How it came back, for its event: where it was, and what its joints hold."""
        part, bus, n = self.part, self.bus, self.board
        was = ("its program started from its bootloader" if held.started
               else f"its program was {held.state.name}")
        targets = []
        for ref in part.names:
            if ref.bus == bus and ref.board == n and ref.kind is mca.Kind.CI:
                rule = self._rule(ref.generic)
                if rule is Seed.SENSOR and ref.index in held.ci:
                    targets.append(f"{part.names.name_of(ref)} {held.ci[ref.index]}")
        return (f"{was}; configured as at the start; held where it stands"
                + (": " + ", ".join(targets) if targets else ""))

    def _rule(self, generic: str) -> Seed:
        spec = self.part.exchanges[self.bus].bus.boards[self.board - 1]
        program = program_of(self.part.trees.board(self.bus, spec.position))
        return Seed.KEEP if program is None else program.seed_of(generic).seed


def _difference(start: BoardEdges, now: BoardEdges) -> str:
    """Where two descriptions of a board first differ, e.g. "PAR 3: 'Set Joint Moving
    Direction(BitMask)' then, 'Set Joint Moving' now" (the records when the names agree)."""
    for kind in mca.Kind:
        for i, (a, b) in enumerate(zip(start.of(kind), now.of(kind), strict=True)):
            if a != b:
                was = a.name if a.name != b.name else a
                is_ = b.name if a.name != b.name else b
                return f"{kind.name} {i}: {was!r} then, {is_!r} now"
    return "the same records"


Rejoiner = Callable[[str, int, float], Rejoin]
