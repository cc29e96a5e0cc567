"""A PAR (or a CI outside the CI maps, such as an axis's Command) written while the loop
runs, without the loop waiting for its acknowledgement.

:meth:`RemoteValues.set <ucom_tools.ops.remote.values.RemoteValues.set>` writes a PAR, or
a CI that no CI map carries, and waits for the board's acknowledgement (retries
included) on the caller's thread: from the
loop's thread (a ``--set`` from the live view, a write from the network) the loop misses
its cycles meanwhile, a round trip at best, seconds where the board does not answer.  A
consumer that writes such edges while it drives joints (the CANopen gateway: a joint's
Command, a profile velocity, a gain by SDO; switching ARMAR-III's 27 joints off at its
start waited 2-7 ms a write over socketcand, past the boards' 50 ms watchdog) asks with
``wait=False``: the same acknowledged write
(:meth:`McaClient.write <ucom_tools.protocol.mca.McaClient.write>`) then runs as a
:class:`~ucom_tools.protocol.stepped.Stepped` conversation that the loop steps after each
cycle's drain, as it steps a rejoin, on a link and client of its own beside the run
time's.  The value counts as the board's at once (what the PC holds, what a rejoin writes
again); a write the board does not acknowledge puts the value back and is kept in the
run's writes as failed.  Writes of one edge go one after the other, the last one asked
for winning.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

from ucom_tools.errors import BoardError, BusError, UcomTimeoutError
from ucom_tools.ops.realtime import like_the_loop
from ucom_tools.protocol.mca import McaClient
from ucom_tools.protocol.stepped import SteppedJob
from ucom_tools.wire import mca
from ucom_tools.wire.ids import seq

if TYPE_CHECKING:
    from ucom_tools.ops.edges import EdgeRef
    from ucom_tools.ops.exchange import BusExchange
    from ucom_tools.ops.realtime import RealtimeScheduling, ShortSlice
    from ucom_tools.ops.robot import Robot


class ParHost(Protocol):
    """What a PAR write needs of the part (:class:`~ucom_tools.ops.remote.RemotePart`)."""

    @property
    def robot(self) -> Robot: ...
    @property
    def exchanges(self) -> dict[str, BusExchange]: ...
    @property
    def scheduling(self) -> RealtimeScheduling | None: ...
    @property
    def time_slice(self) -> ShortSlice: ...


class ParWrite(SteppedJob):
    """One edge's acknowledged write (a PAR, or a CI outside the maps), stepped by the
    loop (see the module docstring); the loop holds it among its conversations until
    :attr:`done`, then :attr:`ok` or :attr:`how` (why not)."""

    is_rejoin = False
    answered: float | None = None  # (as a rejoin's: a write is never "reached")

    def __init__(self, part: ParHost, ref: EdgeRef, raw: int) -> None:
        self.part = part
        self.ref = ref
        self.bus = ref.bus
        self.board = ref.board
        self.raw = raw
        super().__init__(self._run, f"ucom-par-{ref.bus}-{ref.board}-{ref.index}")

    def _run(self) -> None:
        part, ref = self.part, self.ref
        like_the_loop(part.scheduling, part.time_slice)  # the loop waits for it meanwhile
        x = part.exchanges[ref.bus]
        link = part.robot.buses[ref.bus].side_link()
        client = McaClient(link, x.mca.timeouts, process_data=False)
        edges = x.configured[ref.board].edges
        try:
            client.write(seq(ref.board), ref.kind, ref.index, [self.raw],
                         edges.ci if ref.kind is mca.Kind.CI else edges.par)
            self.ok = True
        except (BoardError, UcomTimeoutError, BusError) as err:
            self.how = str(err)
        finally:
            client.close()
            link.close()


__all__ = ["ParHost", "ParWrite"]
