"""Compatibility of a DSP program with a board (dissertation B.3.2, Tab. B.5/B.6).

Three things must match: the plug-on board (its measured Board-ID), the FPGA
configuration (its version registers) and the DSP program (its image descriptor).
:func:`compare` is the host's pre-flight check, :func:`check` the survey behind
``ucom check``.
"""

from __future__ import annotations

from dataclasses import dataclass

from ucom_tools.ops.enumerate import describe_missing, enumerate_bus, missing_expected
from ucom_tools.ops.robot import Robot
from ucom_tools.plugons import app_name, board_name
from ucom_tools.wire.descriptor import ImageDescriptor
from ucom_tools.wire.fpga import FpgaVersion
from ucom_tools.wire.info import BoardInfo


@dataclass(frozen=True)
class Finding:
    severity: str  # "error" | "warning"
    field: str
    expected: str
    found: str
    message: str


def _board(board_id: int) -> str:
    return f"{board_id} ({board_name(board_id)})"


def compare(desc: ImageDescriptor | None, info: BoardInfo, *, what: str = "image"
            ) -> list[Finding]:
    """What keeps a program with descriptor ``desc`` from running on the board ``info``
    describes: errors (Board-ID, App-ID, FPGA major) and warnings (minor, unchecked)."""
    return judge(desc, info.fpga, info.measured_board_id, what=what)


def fits(desc: ImageDescriptor | None, board_id: int, fpga: FpgaVersion, *,
         what: str = "image") -> list[Finding]:
    """:func:`compare` before anything is sent: the image against the plug-on board
    (``board_id``) and FPGA configuration a topology gives a board (``ucom deploy``'s
    manifest check)."""
    return judge(desc, fpga, board_id, what=what)


def judge(desc: ImageDescriptor | None, fpga: FpgaVersion | None, measured: int, *,
          what: str = "image") -> list[Finding]:
    """The findings of :func:`compare`: the descriptor ``desc`` against an FPGA
    configuration (None: its registers do not decode) and a measured Board-ID."""
    out: list[Finding] = []
    neutral = fpga is not None and measured != fpga.board_id
    if neutral:
        assert fpga is not None
        out.append(Finding(
            "error", "plug-on board", _board(fpga.board_id), _board(measured),
            f"the FPGA is made for Board-ID {_board(fpga.board_id)} but the plug-on board "
            f"is {_board(measured)}: the FPGA is in its neutral state (outputs off)"))
    if desc is None:
        out.append(Finding("warning", "descriptor", "-", "-",
                           f"the {what} has no descriptor: compatibility not checked"))
        return out
    if fpga is None:
        out.append(Finding("error", "FPGA", "-", "unreadable",
                           "the FPGA version registers do not decode"))
        return out
    if desc.board_id != fpga.board_id:
        out.append(Finding("error", "Board-ID", _board(desc.board_id), _board(fpga.board_id),
                           f"the {what} is for Board-ID {_board(desc.board_id)}, the FPGA "
                           f"for {_board(fpga.board_id)}"))
    elif desc.board_id != measured and not neutral:
        out.append(Finding("error", "Board-ID", _board(desc.board_id), _board(measured),
                           f"the {what} is for Board-ID {_board(desc.board_id)}, the plug-on "
                           f"board is {_board(measured)}"))
    if desc.app_id != fpga.app_id:
        out.append(Finding("error", "App-ID", str(desc.app_id), str(fpga.app_id),
                           f"the {what} is App-ID {desc.app_id} "
                           f"({app_name(desc.board_id, desc.app_id)}), the FPGA carries "
                           f"App-ID {fpga.app_id} ({app_name(fpga.board_id, fpga.app_id)})"))
    if desc.fpga_major != fpga.major:
        out.append(Finding("error", "FPGA major", str(desc.fpga_major), str(fpga.major),
                           f"the {what} was built for FPGA {desc.fpga_major}.{desc.fpga_minor}, "
                           f"the FPGA is {fpga.version}"))
    elif desc.fpga_minor != fpga.minor:
        out.append(Finding("warning", "FPGA minor", str(desc.fpga_minor), str(fpga.minor),
                           f"the {what} was built for FPGA {desc.fpga_major}.{desc.fpga_minor}, "
                           f"the FPGA is {fpga.version}; it will run"))
    return out


@dataclass(frozen=True)
class CheckRow:
    """One board in the ``ucom check`` matrix."""

    bus: str
    seq_id: int
    placement: str | None
    serial: int
    plug_board_id: int
    fpga: FpgaVersion | None
    neutral: bool
    program: str | None
    progid: int | None
    descriptor: ImageDescriptor | None
    verdict: str  # ok | warning | mismatch | no program | unknown | missing
    findings: tuple[Finding, ...]

    @property
    def failed(self) -> bool:
        return self.verdict in ("mismatch", "unknown", "missing")


def check(robot: Robot, *, bus: str | None = None) -> list[CheckRow]:
    """Init every bus and judge every board: plug-on board, FPGA, stored DSP program."""
    rows = []
    for h in robot.select(bus):
        enum = enumerate_bus(h)
        expected = len(h.expected.boards) if h.expected is not None else 0
        for spec in missing_expected(h, [b.serial for b in enum.boards], enum.found):
            rows.append(CheckRow(h.name, 0, spec.placement, spec.serial, 15, None, False, None,
                                 None, None, "missing", (Finding(
                                     "error", "board", spec.placement, "no answer",
                                     describe_missing(h.name, spec, expected)),)))
        for b in enum.boards:
            inf = b.info
            if inf is None:
                rows.append(CheckRow(h.name, b.seq_id, b.placement, b.serial, 15, None, False,
                                     None, None, None, "unknown", (Finding(
                                         "error", "Info", "-", "-",
                                         "no Info record (two boards share this seq ID?)"),)))
                continue
            has_program = inf.flash_valid
            if has_program:
                findings = compare(inf.descriptor, inf, what="stored program")
            else:  # no program: only the plug-on board / FPGA pairing can be judged
                findings = [f for f in compare(None, inf) if f.field != "descriptor"]
            if inf.descriptor_corrupt:
                findings.append(Finding("error", "descriptor", "-", "corrupt",
                                        "the stored program's descriptor is corrupt"))
            if any(f.severity == "error" for f in findings):
                verdict = "mismatch"
            elif not has_program:
                verdict = "no program"
            elif findings:
                verdict = "warning"
            else:
                verdict = "ok"
            rows.append(CheckRow(h.name, b.seq_id, b.placement, b.serial, inf.measured_board_id,
                                 inf.fpga, inf.fpga_neutral, inf.name if has_program else None,
                                 inf.progid if has_program else None, inf.descriptor, verdict,
                                 tuple(findings)))
    return rows
