"""man/ucom-protocol.7, RUN TIME, says what the code does: every example frame on the page
decodes to the message the page names and encodes back to the same bytes, the edge tables
are the programs' specs, the run-time errors listed are those the running program sends,
the function codes and field values named are the code's, and the page renders cleanly."""

from __future__ import annotations

import ast
import re
import shutil
import subprocess
from dataclasses import dataclass
from enum import IntEnum
from pathlib import Path

import pytest

from ucom_tools import compiled
from ucom_tools.edgelists import armar3, lauron4
from ucom_tools.edgelists.model import MAX_NAME, EdgeKind, ProgramSpec
from ucom_tools.image.formats import load_image
from ucom_tools.ops.flash import flash
from ucom_tools.ops.flash_types import FlashRequest
from ucom_tools.ops.robot import ConnectSpec, open_robot
from ucom_tools.virtual.board import application, runtime
from ucom_tools.wire import mca
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import ErrorCode, ReportChannel
from ucom_tools.wire.digest import DescrDigest, DigestRequest, digest_of
from ucom_tools.wire.ids import ALL, Address, Direction, Function, seq

PAGE = Path(__file__).resolve().parent.parent / "man" / "ucom-protocol.7"
B3 = seq(3)
ARMAR3_DIGEST = digest_of(mca.EdgeRecord(e.width, e.signed, e.exponent, e.minimum, e.maximum,
                                         e.name, e.unit) for k in EdgeKind
                          for e in armar3.SPEC.of(k))
"""The armar3 program's description digest (the page prints it: 0x0E506B11)."""


# ----------------------------------------------------------------------------- parsing
def _page() -> str:
    return PAGE.read_text()


def _plain(roff: str) -> str:
    """The text of roff source as read: escapes resolved, fonts dropped."""
    text = re.sub(r"\\f[BIRP]", "", roff)
    for escape, char in ((r"\-", "-"), (r"\(mu", "x"), (r"\(*m", "u"), (r"\(->", "->"),
                         (r"\(<-", "<-"), (r"\e", "\\"), (r"\&", "")):
        text = text.replace(escape, char)
    return text


def _section(name: str) -> str:
    page = _page()
    start = page.index(f"\n.SH {name}\n")
    end = page.find("\n.SH ", start + 1)
    return page[start:end if end >= 0 else None]


def _subsection(section: str, name: str) -> str:
    start = section.index(f"\n.SS {name}\n")
    end = section.find("\n.SS ", start + 1)
    return section[start:end if end >= 0 else None]


def _nf_blocks(text: str) -> list[list[str]]:
    return [block.split("\n") for block in re.findall(r"\n\.nf\n(.*?)\n\.fi", text, re.S)]


# ----------------------------------------------------------------------------- examples
@dataclass(frozen=True)
class Example:
    """A frame the page prints: the message it is, and words its description must use."""

    message: object
    address: Address | None
    words: tuple[str, ...]

    @property
    def frame(self) -> tuple[int, bytes]:
        if isinstance(self.message, mca.McaMessage):
            return mca.encode(self.message, self.address)
        assert self.address is not None
        return m.encode(self.message, self.address)  # type: ignore[arg-type]


def _s16(*values: int) -> bytes:
    return b"".join(v.to_bytes(2, "big", signed=True) for v in values)


def _s32(*values: int) -> bytes:
    return b"".join(v.to_bytes(4, "big", signed=True) for v in values)


def _ready(answers: int, echo: bytes, state: mca.RunState = mca.RunState.STOPPED,
           words: tuple[str, ...] = ()) -> Example:
    """MCA Ready of board 3, which runs armar3."""
    counts = tuple(len(armar3.SPEC.of(k)) for k in EdgeKind)
    return Example(mca.McaReady(state, answers, echo, *counts), B3,
                   ("MCA Ready", state.name, *words))


def _set_joint_segments() -> list[Example]:
    e = armar3.SPEC.of(EdgeKind.PAR)[3]
    record = mca.EdgeRecord(e.width, e.signed, e.exponent, e.minimum, e.maximum, e.name,
                            e.unit)
    return [Example(s, B3, ("MCA DumpIO Descr", e.name)) for s in record.segments(mca.Kind.PAR, 3)]


SO_MAP_1 = mca.AdminData.so_map(1, 1, [0, 2, 14, 15])

EXAMPLES: list[Example] = [
    _ready(Function.MCA_READY, b"\0\0", words=("unsolicited", "13 CI", "20 SO", "38 PAR")),
    Example(mca.DescrRequest(), B3, ("MCA DumpIO Descr Request", "every edge")),
    Example(mca.DescrRequest(mca.Kind.PAR, 3), B3, ("MCA DumpIO Descr Request", "PAR 3")),
    Example(DigestRequest(), B3, ("MCA DumpIO Descr Request", "digest")),
    Example(DescrDigest(ARMAR3_DIGEST), B3, ("kind 3", "0x0E506B11", "CRC-32")),
    *_set_joint_segments(),
    Example(mca.EdgeWrite(mca.Kind.PAR, 0, _s16(1000, 14000, 0)), B3,
            ("MCA Parameter", "PAR 0", "LoopTime(ms)", "1000", "14000")),
    _ready(Function.MCA_PARAMETER, bytes((0, 0x03))),
    Example(mca.EdgeWrite(mca.Kind.PAR, 6, _s32(500)), B3,
            ("MCA Parameter", "PAR 6", "MotorA I", "0.0005", "500", "-6")),
    _ready(Function.MCA_PARAMETER, bytes((6, 0x00))),
    Example(mca.EdgeWrite(mca.Kind.CI, 6, _s16(-12725, -11457)), B3,
            ("MCA Controller Input", "CI 6", "-12725", "-11457")),
    _ready(Function.MCA_CONTROLLER_INPUT, bytes((6, 0xCE))),
    Example(mca.AdminData.alive(50), B3, ("MCA Admin Data", "ALIVE", "50 ms")),
    _ready(Function.MCA_ADMIN_DATA, bytes((mca.AdminOp.ALIVE, 0))),
    Example(SO_MAP_1, B3, ("MCA Admin Data", "SO_MAP", "map 1", "period 1", "Encoder 0",
                           "Velocity B")),
    _ready(Function.MCA_ADMIN_DATA, bytes((mca.AdminOp.SO_MAP, 1))),
    Example(mca.AdminData.ci_map(1, [3, 4, mca.NO_EDGE, mca.NO_EDGE]), seq(2),
            ("MCA Admin Data", "CI_MAP", "map 1", "board 2")),
    Example(mca.AdminData.ci_map(1, [mca.NO_EDGE, mca.NO_EDGE, 3, 4]), B3,
            ("MCA Admin Data", "CI_MAP", "map 1", "board 3")),
    _ready(Function.MCA_ADMIN_DATA, bytes((mca.AdminOp.CI_MAP, 1))),
    Example(mca.McaStart(mca.StartOp.START), B3, ("MCA Start", "START")),
    _ready(Function.MCA_START, bytes((mca.StartOp.START, 0)), mca.RunState.RUNNING),
    Example(mca.Alive(), ALL, ("MCA Alive", "broadcast")),
    Example(mca.MapFrame(Function.MCA_CONTROLLER_INPUT, 1, _s16(100, -100, 1000, -1000)), None,
            ("CI map 1", "100", "-100", "1000", "-1000")),
    Example(mca.MapFrame(Function.MCA_SENSOR_OUTPUT, 1, _s16(1000, -1000, 0, 0)), None,
            ("SO map 1", "Encoder 0", "Velocity A")),
    Example(mca.DumpRequest(mca.Kind.PAR, 5, 3), B3, ("MCA Dump CI", "PAR 5")),
    Example(mca.DumpValues(mca.Kind.PAR, 5, _s32(50_000_000)), B3, ("MCA DSP CI", "50000000")),
    Example(mca.DumpValues(mca.Kind.PAR, 6, _s32(500)), B3, ("MCA DSP CI", "500")),
    Example(mca.DumpValues(mca.Kind.PAR, 7, _s32(0)), B3, ("MCA DSP CI",)),
    Example(m.ReportRequest(ReportChannel.APPLICATION), B3, ("Report Request", "channel 3")),
    Example(m.AppReport(mca.AppStatus(mca.RunState.RUNNING, 700, 1000, 0, 0).encode()), B3,
            ("Report 3", "RUNNING", "700", "1000")),
    Example(mca.EdgeWrite(mca.Kind.PAR, 1, _s16(20000)), B3,
            ("MCA Parameter", "Max PWM", "20000")),
    Example(m.Error(ErrorCode.OUT_OF_RANGE, Function.MCA_PARAMETER, 2 << 8 | 1), B3,
            ("Error", "OUT_OF_RANGE")),
    Example(mca.EdgeWrite(mca.Kind.PAR, 38, _s16(0)), B3, ("MCA Parameter", "PAR 38")),
    Example(m.Error(ErrorCode.UNKNOWN_EDGE, Function.MCA_PARAMETER, 2 << 8 | 38), B3,
            ("Error", "UNKNOWN_EDGE")),
    Example(mca.AdminData.so_map(2, 100, [20]), B3, ("MCA Admin Data", "SO_MAP", "SO 20")),
    Example(m.Error(ErrorCode.BAD_MAP, Function.MCA_ADMIN_DATA, 2), B3, ("Error", "BAD_MAP")),
    Example(m.Error(ErrorCode.WATCHDOG, Function.MCA_ALIVE, 50), B3,
            ("Error", "WATCHDOG", "50 ms")),
    Example(mca.EdgeWrite(mca.Kind.CI, 3, _s16(100)), B3, ("MCA Controller Input", "LATCHED")),
    Example(m.Error(ErrorCode.LATCHED, Function.MCA_CONTROLLER_INPUT, 0), B3,
            ("Error", "LATCHED")),
    Example(mca.EdgeWrite(mca.Kind.PAR, 0, _s16(300)), B3,
            ("MCA Parameter", "LoopTime(ms)", "0.3", "300")),
    _ready(Function.MCA_PARAMETER, bytes((0, 0x01)), mca.RunState.RUNNING),
    Example(m.Error(ErrorCode.OVERRUN, runtime.NO_FUNCTION, 404), B3,
            ("Error", "OVERRUN", "404")),
]


def _page_examples() -> list[tuple[tuple[int, bytes], str]]:
    """Every frame of RUN TIME, Examples, with the text of the entry it stands in."""
    examples = _subsection(_section("RUN TIME"), "Examples")
    out = []
    for entry in examples.split("\n.TP\n")[1:]:
        text = " ".join(_plain(entry).split())
        for line in entry.split("\n"):
            hit = re.fullmatch(r"(?:\.B )?\s*0x([0-7][0-9A-F]{2})((?: [0-9A-F]{2})*)\s*", line)
            if hit:
                out.append(((int(hit.group(1), 16), bytes.fromhex(hit.group(2))), text))
    return out


def _decode(arbitration_id: int, data: bytes) -> tuple[Address | None, object]:
    if (arbitration_id >> 6) in mca.MCA_FUNCTIONS:
        return mca.decode(arbitration_id, data)
    return m.decode(arbitration_id, data)


def test_every_example_frame_decodes_to_what_the_page_says_and_encodes_back() -> None:
    printed = _page_examples()
    frames = [frame for frame, _ in printed]
    assert len(frames) == len(set(frames)), "a frame is printed twice"
    expected = {e.frame: e for e in EXAMPLES}
    assert set(frames) == set(expected), (
        f"on the page only: {sorted(set(frames) - set(expected))}; "
        f"not on the page: {sorted(set(expected) - set(frames))}")
    for (arb, data), text in printed:
        example = expected[(arb, data)]
        address, message = _decode(arb, data)
        assert message == example.message, (hex(arb), data.hex())
        assert address == example.address
        again = mca.encode(message, address) if isinstance(message, mca.McaMessage) else \
            m.encode(message, address)  # type: ignore[arg-type]
        assert again == (arb, data)
        for word in example.words:
            assert word in text, f"0x{arb:03X} {data.hex()}: the page does not say {word!r}"


def test_the_descr_example_carries_the_longest_b5_name_whole() -> None:
    segments = [mca.DescrSegment.decode(data) for (arb, data), _ in _page_examples()
                if arb >> 6 == Function.MCA_DUMPIO_DESCR and data[0] >> 6 != 3]
    assert [s.segment for s in segments] == list(range(len(segments)))
    assert segments[-1].last and not any(s.last for s in segments[:-1])
    record = mca.EdgeRecord.decode(b"".join(s.data for s in segments))
    e = armar3.SPEC.of(EdgeKind.PAR)[3]
    assert (record.name, len(record.name)) == ("Set Joint Moving Direction(BitMask)", 35)
    assert (record.width, record.signed, record.exponent, record.minimum, record.maximum,
            record.unit) == (e.width, e.signed, e.exponent, e.minimum, e.maximum, e.unit)


def test_the_report_example_is_an_application_status() -> None:
    (data,) = [data for (arb, data), _ in _page_examples() if arb >> 6 == Function.REPORT_3]
    status = mca.AppStatus.decode(data)
    assert (status.state, status.load_permille, status.cycle_us) == (
        mca.RunState.RUNNING, 700, 1000)


def _on_page(example: Example) -> tuple[int, bytes]:
    frame = example.frame
    assert frame in {e.frame for e in EXAMPLES}, f"0x{frame[0]:03X} {frame[1].hex()}: not printed"
    return frame


def test_virtual_boards_answer_the_example_requests_with_the_example_frames() -> None:
    """The page's requests, replayed on ARMAR-III's CAN0 (boards 2 and 3 run armar3):
    each answer is the frame the page prints."""
    robot = open_robot(ConnectSpec(virtual="armar3"))
    try:
        image = load_image("firmware_images/armar3.fl.S")
        assert flash(robot, FlashRequest(image)).all_verified
        bus = robot.buses["CAN0"]
        link = bus.client.link
        seen: list[tuple[int, bytes]] = []
        link.dispatcher.subscribe(lambda msg: True, "page examples",
                                  on_frame=lambda msg: seen.append((msg.arbitration_id,
                                                                    bytes(msg.data))))
        quiet = {Function.REPORT_2, Function.MCA_SENSOR_OUTPUT}

        def answers(request: Example | None = None, seconds: float = 0.005,
                    board: int = 3) -> list[tuple[int, bytes]]:
            seen.clear()
            if request is not None:
                link.send_raw(*_on_page(request))
            link.dispatcher.pump(link.clock() + seconds)
            return [f for f in seen if f[0] & 0x1F == board and f[0] >> 6 not in quiet]

        def ready(answered: int, echo: bytes, state: mca.RunState = mca.RunState.STOPPED
                  ) -> list[tuple[int, bytes]]:
            return [_on_page(_ready(answered, echo, state))]

        def error(code: ErrorCode, function: int, detail: int) -> list[tuple[int, bytes]]:
            return [_on_page(Example(m.Error(code, function, detail), B3, ()))]

        def request(message: object, address: Address | None = B3) -> Example:
            return Example(message, address, ())

        assert bus.client.start(seq(2))[0].ok
        seen.clear()
        assert bus.client.start(seq(3))[0].ok
        link.dispatcher.pump(link.clock() + 0.01)
        assert [f for f in seen if f[0] >> 6 == Function.MCA_READY] == ready(
            Function.MCA_READY, b"\0\0")
        records = answers(request(mca.DescrRequest()), seconds=0.1)
        assert len(records) == sum(len(mca.EdgeRecord(
            e.width, e.signed, e.exponent, e.minimum, e.maximum, e.name, e.unit).segments(
            mca.Kind.PAR, 0)) for e in armar3.SPEC.edges)
        assert answers(request(mca.DescrRequest(mca.Kind.PAR, 3))) == [
            _on_page(e) for e in _set_joint_segments()]
        assert answers(request(DigestRequest())) == [
            _on_page(request(DescrDigest(ARMAR3_DIGEST)))]
        par, ci = mca.Kind.PAR, mca.Kind.CI
        for write, echo in (((par, 0, _s16(1000, 14000, 0)), bytes((0, 3))),
                            ((par, 6, _s32(500)), bytes((6, 0))),
                            ((ci, 6, _s16(-12725, -11457)), bytes((6, 0xCE)))):
            edge_write = mca.EdgeWrite(*write)
            assert answers(request(edge_write)) == ready(edge_write.FUNCTION, echo)
        for admin in (mca.AdminData.alive(50), SO_MAP_1,
                      mca.AdminData.ci_map(1, [mca.NO_EDGE, mca.NO_EDGE, 3, 4])):
            assert answers(request(admin)) == ready(Function.MCA_ADMIN_DATA, admin.encode()[:2])
        assert [f[1][:4] for f in answers(request(mca.AdminData.ci_map(
            1, [3, 4, mca.NO_EDGE, mca.NO_EDGE]), seq(2)), board=2)] == [bytes((0, 25, 3, 1))]
        link.send_raw(*mca.encode(mca.EdgeWrite(par, 5, _s32(50_000_000)), B3))  # MotorA P 50
        answers()
        assert answers(request(mca.DumpRequest(par, 5, 3))) == [_on_page(request(
            mca.DumpValues(par, 5 + n, _s32(v)))) for n, v in enumerate((50_000_000, 500, 0))]
        assert answers(request(mca.EdgeWrite(par, 1, _s16(20000)))) == error(
            ErrorCode.OUT_OF_RANGE, Function.MCA_PARAMETER, 2 << 8 | 1)
        assert answers(request(mca.EdgeWrite(par, 38, _s16(0)))) == error(
            ErrorCode.UNKNOWN_EDGE, Function.MCA_PARAMETER, 2 << 8 | 38)
        assert answers(request(mca.AdminData.so_map(2, 100, [20]))) == error(
            ErrorCode.BAD_MAP, Function.MCA_ADMIN_DATA, 2)
        link.send_raw(*mca.encode(mca.McaStart(mca.StartOp.START), seq(2)))
        assert answers(request(mca.McaStart(mca.StartOp.START))) == ready(
            Function.MCA_START, bytes((1, 0)), mca.RunState.RUNNING)
        ci_map = _on_page(request(mca.MapFrame(Function.MCA_CONTROLLER_INPUT, 1,
                                               _s16(100, -100, 1000, -1000)), None))
        so_maps = []
        for cycle in range(1100):
            link.send_raw(*ci_map)
            if cycle % 10 == 0:
                link.send_raw(*_on_page(request(mca.Alive(), ALL)))
            answers(seconds=0.001)
            so_maps += [f for f in seen if f[0] == 0x3A1]
        assert len(so_maps) >= 1099 and {len(data) for _, data in so_maps} == {8}
        for n, targets in ((2, _s16(100, -100)), (3, _s16(1000, -1000))):  # what CI map 1 fed
            link.send_raw(*mca.encode(mca.DumpRequest(ci, 3, 2), seq(n)))
            assert [mca.decode(*f)[1] for f in answers(board=n)] == [
                mca.DumpValues(ci, 3, targets)]
        (report,) = answers(request(m.ReportRequest(ReportChannel.APPLICATION)), 0.001)
        status = mca.AppStatus.decode(report[1])
        assert (status.state, status.cycle_us, status.overruns) == (mca.RunState.RUNNING, 1000, 0)
        assert 700 <= status.load_permille < 710  # the page's 700 plus the frames' few us
        assert answers(seconds=0.08) == error(ErrorCode.WATCHDOG, Function.MCA_ALIVE, 50)
        assert answers(request(mca.EdgeWrite(ci, 3, _s16(100)))) == error(
            ErrorCode.LATCHED, Function.MCA_CONTROLLER_INPUT, 0)
        link.send_raw(*mca.encode(mca.McaStart(mca.StartOp.START), B3))
        link.send_raw(*mca.encode(mca.Alive(), ALL))
        answers(seconds=0.003)
        assert answers(request(mca.EdgeWrite(par, 0, _s16(300))), seconds=0.003) == ready(
            Function.MCA_PARAMETER, bytes((0, 1)), mca.RunState.RUNNING) + error(
            ErrorCode.OVERRUN, runtime.NO_FUNCTION, 404)
    finally:
        robot.close()


# ----------------------------------------------------------------------------- edge tables
def _tables(title: str) -> tuple[list[str], list[str]]:
    """The two tables of a program's subsection: interface and encoding rows."""
    sub = _subsection(_section("RUN TIME"), title)
    blocks = [b for b in _nf_blocks(sub) if b and b[0].split()[:1] == ["idx"]]
    assert len(blocks) == 2, f"{title}: expected the interface and the encoding table"
    return blocks[0][1:], blocks[1][1:]


@pytest.mark.parametrize("title, spec", [("The armar3 program", armar3.SPEC),
                                         ("The lauron4 program", lauron4.SPEC)])
def test_edge_tables_are_the_programs_specs(title: str, spec: ProgramSpec) -> None:
    interface, encoding = _tables(title)
    assert len(interface) == len(encoding) == len(spec.edges)
    per_kind = {k: 0 for k in EdgeKind}
    for t, (row_a, row_b, e) in enumerate(zip(interface, encoding, spec.edges, strict=True)):
        a = re.fullmatch(r"\s*(\d+) (CI|SO|PAR)\s+(\d+)\s+(-?\d+)\s+(\d+)  (.+?)"
                         r"(?: \[(.+)\])?", _plain(row_a))
        b = re.fullmatch(r"\s*(\d+) ([su])([24])\s+(-?\d+)\s+(-?\d+)\s+(-?\d+)  (.+)",
                         _plain(row_b))
        assert a and b, (row_a, row_b)
        assert int(a[1]) == int(b[1]) == t
        assert EdgeKind[a[2]] is e.kind and int(a[3]) == per_kind[e.kind]
        assert spec.tree_index(e.kind, int(a[3])) == t
        assert (a[6], a[7] or "", int(a[4]), int(a[5])) == (e.name, e.unit, e.default, e.period)
        assert (b[7], b[2] == "s", int(b[3]), int(b[4]), int(b[5]), int(b[6])) == (
            e.name, e.signed, e.width, e.exponent, e.minimum, e.maximum)
        per_kind[e.kind] += 1


# ----------------------------------------------------------------------------- errors
def _codes_in(source: str) -> set[str]:
    return set(re.findall(r"ErrorCode\.([A-Z_]+)", source))


def _method_source(module: str, cls: str, method: str) -> str:
    """A method's source from the module's file (the module may run compiled: then
    ``inspect`` has no source)."""
    text = compiled.source_of(module).read_text()
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, ast.ClassDef) and node.name == cls:
            for item in node.body:
                if isinstance(item, ast.FunctionDef) and item.name == method:
                    return ast.get_source_segment(text, item) or ""
    raise AssertionError(f"no {cls}.{method} in {module}")


def test_run_time_errors_listed_are_the_ones_a_running_program_sends() -> None:
    sent = _codes_in(compiled.source_of(runtime.__name__).read_text()) | _codes_in(
        _method_source(application.__name__, "DspProgram", "on_frame"))
    listed = _subsection(_section("RUN TIME"), "Bad input")
    named = set(re.findall(r"Error ([A-Z_]{4,})", _plain(listed)))
    assert named == sent
    assert {"WATCHDOG", "UNKNOWN_EDGE", "OUT_OF_RANGE", "LATCHED", "BAD_MAP"} <= sent


def test_errors_table_is_the_error_code_enum() -> None:
    rows = [line for block in _nf_blocks(_section("ERRORS")) for line in block]
    table = {name: int(value, 16) for value, name in
             (re.match(r"\s*0x([0-9A-F]{2}) ([A-Z_]+)", line).groups()  # type: ignore[union-attr]
              for line in rows if re.match(r"\s*0x[0-9A-F]{2} ", line))}
    assert table == {c.name: c.value for c in ErrorCode}


# ----------------------------------------------------------------------------- names, numbers
def _same_function(label: str, function: Function) -> bool:
    """The page's name (Tab. B.4's spelling) is the code's: ``MCA Dump CI`` = MCA_DUMP_CI,
    ``SetStatus`` = SET_STATUS."""
    def key(text: str) -> str:
        return re.sub(r"[ _]", "", text).upper()
    return key(label) == key(function.name)


def test_function_codes_named_are_tab_b4() -> None:
    entries = re.findall(r"^\.B (\d+)(?:-(\d+))? ([A-Za-z ]+?) \(",
                         _plain(_section("RUN TIME")), re.M)
    named = set()
    for first, last, label in entries:
        if last:
            assert (label, int(first), int(last)) == ("Report", Function.REPORT_0,
                                                      Function.REPORT_3)
            continue
        assert _same_function(label, Function(int(first))), (first, label)
        named.add(Function(int(first)))
    assert set(mca.MCA_FUNCTIONS) <= named
    assert {Function.ERROR, Function.SET_STATUS, Function.REPORT_REQUEST} <= named
    table = _plain(_section("IDENTIFIERS"))
    table = table[table.index("Function codes"):]
    table = table[:table.index(".fi")]
    rows = re.findall(r"(\d+)(?:-\d+)? ([A-Z][A-Za-z ]*?)(?: \(100XX\))?\s+(PC|DSP)"
                      r"(?=\s{2,}|\s*$)", table, re.M)
    assert len(rows) == 25
    for code, label, initiator in rows:
        f = Function(int(code))
        assert _same_function(label, f) or (f is Function.REPORT_0 and label == "Report")
        assert f.direction is (Direction.HOST_TO_BOARD if initiator == "PC"
                               else Direction.BOARD_TO_HOST)


def _entry(section: str, head: str) -> str:
    """One .TP entry of a subsection, from its tag to the next entry."""
    start = section.index(f"\n.B {head} ")
    end = min(i for i in (section.find("\n.TP", start), section.find("\n.SS", start),
                          len(section)) if i >= 0)
    return section[start:end]


@pytest.mark.parametrize("enum, head", [
    (mca.RunState, "20 MCA Ready"), (mca.StartOp, "21 MCA Start"),
    (mca.Kind, "22 MCA DumpIO Descr Request"), (mca.AdminOp, "25 MCA Admin Data")])
def test_field_values_named_are_the_codes(enum: type[IntEnum], head: str) -> None:
    text = _plain(_entry(_subsection(_section("RUN TIME"), "Messages"), head))
    names = "|".join(member.name for member in enum)
    pairs = re.findall(rf"\b(0x[0-9A-F]{{2}}|\d+) ({names})\b", text)
    assert {name for _, name in pairs} == {member.name for member in enum}
    for value, name in pairs:
        assert int(value, 0) == enum[name].value, (value, name)


def test_constants_named_are_the_codes() -> None:
    text = " ".join(_plain(_section("RUN TIME")).split())
    for phrase in (
        f"{mca.ALIVE_MIN_MS}-{mca.ALIVE_MAX_MS} ms",
        f"default {mca.ALIVE_DEFAULT_MS} ms",
        f"0x{mca.NO_EDGE:02X} (NO_EDGE)",
        f"map number 1-{mca.MAX_MAP}",
        f"{mca.MAP_SLOTS} slots",
        f"{mca.DESCR_SEGMENT} record bytes",
        f"at most {MAX_NAME} characters",
        f"0x{mca.FLAG_OVERRUN:02X} a cycle overran",
        f"0x{mca.FLAG_LATCHED_BY_WATCHDOG:02X} latched by the watchdog",
        f"every {runtime.BLINK_CYCLES} cycles",
        f"{runtime.OVERRUN_FLASH_US / 1000:g} ms after an overrun",
        f"{runtime.REPORT_EVERY}th",
        f"blocks of {runtime.LOAD_WINDOW} cycles",
        f"{runtime.FRAME_COST_US:g} us per frame",
        f"function byte 0x{runtime.NO_FUNCTION:02X}",
    ):
        assert phrase in text, phrase


def test_description_no_longer_defers_the_run_time() -> None:
    head = _plain(_page()[:_page().index("\n.SH BUS")])
    assert "later revision" not in head
    assert "RUN TIME" in head
    order = re.findall(r"^\.SH (.+)$", _page(), re.M)
    assert order.index("RUN TIME") == order.index("COMPATIBILITY") + 1
    assert order.index("ERRORS") == order.index("RUN TIME") + 1


# ----------------------------------------------------------------------------- rendering
@pytest.mark.skipif(shutil.which("groff") is None, reason="groff is not installed")
def test_page_renders_without_warnings() -> None:
    done = subprocess.run(["groff", "-man", "-Tutf8", "-ww", "-z", str(PAGE)],
                          capture_output=True, text=True, check=False)
    assert done.returncode == 0 and not done.stderr.strip(), done.stderr


def test_the_bus_budget_figures_are_the_planners() -> None:
    """The worked example's loads are what the planner computes for the bundled robots."""
    from ucom_tools.config.attrtree.robot import bind
    from ucom_tools.config.topology import load
    from ucom_tools.ops.exchange import plan_bus

    def pct(x: float) -> str:
        return f"{100 * x:.1f} %"

    budget = _plain(_subsection(_section("RUN TIME"), "Bus budget"))
    armar3 = load("armar3")
    trees = bind(armar3)
    can0 = plan_bus(armar3.bus("CAN0"), trees)
    can3 = plan_bus(armar3.bus("CAN3"), trees)
    lauron = load("lauron4")
    leg_bus = plan_bus(lauron.buses[0], bind(lauron))
    words = " ".join(budget.split())
    assert f"Nominal {pct(can0.nominal)}, worst case {pct(can0.worst)}" in words
    assert f"{pct(can3.nominal)} ({pct(can3.worst)} worst)" in words
    assert f"{len(leg_bus.so_maps)} SO maps and {len(leg_bus.ci_maps)} CI maps: " \
        f"{pct(leg_bus.nominal)} nominal, {pct(leg_bus.worst)} worst" in words
    assert f"{can0.total().nominal_bits_per_s / 1000:.1f}" in budget
    assert f"{round(can0.total().frames_per_s)}" in budget
