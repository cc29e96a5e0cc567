"""A rejoin checks a board's descriptions by their digest (``man/ucom-protocol.7``, RUN
TIME, Faults, Rejoin, step 2): one MCA DumpIO Descr Request (DLC 1) and one answer
instead of the records, four edges at a time; the records only when the digest differs
(another program: refused, saying where) or does not come (an older program: the
``digest-unknown`` board), counted on the bus in virtual time."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

from tests.runtime_rig import programmed, robot_of
from ucom_tools.config.attrtree.robot import bind
from ucom_tools.config.scenario import FaultKind, InjectedFault
from ucom_tools.ops.remote import RemotePart
from ucom_tools.ops.remote.rejoin import DESCRIBE_AT_A_TIME
from ucom_tools.virtual.board import mutants
from ucom_tools.virtual.fleet import Fleet
from ucom_tools.wire import mca
from ucom_tools.wire.codes import ErrorCode
from ucom_tools.wire.digest import DescrDigest
from ucom_tools.wire.ids import Function

EYES = ("CAN0", 3)
EDGES = 13 + 20 + 38
"""armar3's CI, SO and PAR edges."""


@dataclass
class Tap:
    """Every frame on a bus: (identifier, data), in the order they went."""

    frames: list[tuple[int, bytes]] = field(default_factory=list)

    def on_frame(self, arbitration_id: int, data: bytes, t_end: float) -> None:
        self.frames.append((arbitration_id, bytes(data)))

    def of(self, function: Function, since: int = 0) -> list[tuple[int, bytes]]:
        return [(a, d) for a, d in self.frames[since:] if a >> 6 == function]


@contextmanager
def running(defect: str | None = None) -> Iterator[tuple[Fleet, RemotePart, Tap]]:
    """ARMAR-III under ``hold`` with ``rejoin``; the eyes' board (CAN0, 3) with
    ``defect``; a tap on CAN0."""
    fleet = programmed("armar3")
    fleet.boards["CAN0"][2].defect = defect
    tap = Tap()
    fleet.bus("CAN0").attach(tap)
    robot = robot_of(fleet)
    part = RemotePart(robot, bind(robot.topology), on_fault="hold", rejoin=True)
    try:
        part.start()
        part.run(0.2)
        yield fleet, part, tap
    finally:
        part.close()
        robot.close()


def power_off(fleet: Fleet, seconds: float = 0.2) -> None:
    fleet.inject(InjectedFault(FaultKind.POWER_OFF, *EYES, for_s=seconds))


def test_a_rejoin_asks_the_digest_and_reads_no_description() -> None:
    with running() as (fleet, part, tap):
        start = tap.of(Function.MCA_DUMPIO_DESCR_REQUEST)
        assert [len(d) for _, d in start] == [0] * 3  # the start read them all at once
        since = len(tap.frames)
        power_off(fleet)
        part.run(1.0)
        assert part.lost == {} and part.faults[-1].event == "rejoined"
        asked = tap.of(Function.MCA_DUMPIO_DESCR_REQUEST, since)
        assert asked == [(Function.MCA_DUMPIO_DESCR_REQUEST << 6 | 3, b"\x03")]
        answers = tap.of(Function.MCA_DUMPIO_DESCR, since)
        digest = part.described(*EYES).digest()  # type: ignore[union-attr]
        assert answers == [(Function.MCA_DUMPIO_DESCR << 6 | 3,
                            DescrDigest(digest).encode())]
        assert digest == part.digest(*EYES) == 0x0E506B11  # the page's example
        assert part.exchanges["CAN0"].configured[3].edges == part.described(*EYES)


def test_a_program_without_the_digest_rejoins_through_the_full_read() -> None:
    with running(mutants.DIGEST_UNKNOWN) as (fleet, part, tap):
        since = len(tap.frames)
        power_off(fleet)
        part.run(1.0)
        assert part.lost == {} and part.faults[-1].event == "rejoined"
        asked = [d for _, d in tap.of(Function.MCA_DUMPIO_DESCR_REQUEST, since)]
        assert asked[0] == b"\x03"  # the digest, refused:
        refused = [(a & 0x1F, d[0], d[1]) for a, d in tap.of(Function.ERROR, since)
                   if d[1] == Function.MCA_DUMPIO_DESCR_REQUEST]
        assert refused == [
            (3, ErrorCode.BAD_LENGTH, Function.MCA_DUMPIO_DESCR_REQUEST)]
        # then every record, each asked for on its own, four at a time
        assert sorted(asked[1:]) == sorted(bytes((k, i)) for k in mca.Kind
                                           for i in range((13, 20, 38)[k]))
        assert len(asked) == 1 + EDGES and EDGES > DESCRIBE_AT_A_TIME
        assert not any(d[0] >> 6 == 3 for _, d in tap.of(Function.MCA_DUMPIO_DESCR, since))
        part["Right Eye Target"] = 300  # and it is controlled again
        part.run(0.6)
        assert abs(part["Right Eye Joint Sensor"] - 300) <= 5


def test_a_board_back_with_another_program_is_refused_saying_where() -> None:
    """While it is off, the eyes' board gets a program whose edge names are cut to 16
    characters (``descr-truncated``: its counts are the same, its records not): its
    digest differs, its records are read, and it stays lost, the reason naming the
    first edge that differs."""
    with running() as (fleet, part, tap):
        since = len(tap.frames)
        power_off(fleet)
        fleet.boards["CAN0"][2].defect = mutants.DESCR_TRUNCATED
        part.run(1.0)
        lost = part.lost[EYES]
        assert lost.status == (
            "cannot rejoin: CAN0 board 3 (head right)'s edges are not those it described "
            "at the start (CI 6: 'MotorA Reset Offset' then, 'MotorA Reset Off' now): "
            "another program?"), lost.status
        asked = [d for _, d in tap.of(Function.MCA_DUMPIO_DESCR_REQUEST, since)]
        assert asked[0] == b"\x03" and len(asked) == 1 + EDGES
        got = [d for _, d in tap.of(Function.MCA_DUMPIO_DESCR, since) if d[0] >> 6 == 3]
        assert len(got) == 1 and got[0] != DescrDigest(part.digest(*EYES) or 0).encode()
        assert [f.event for f in part.faults] == ["lost"]
