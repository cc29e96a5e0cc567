"""The DSP program a virtual UCoM starts from flash or ExtRAM.

On start it applies the compatibility policy of B.3.2: it reads the FPGA's version
registers and the measured Board-ID through the X: memory window and compares them with
the image descriptor it was built with (P:7DE0):

- Board-ID (of the FPGA or of the plug-on board) or App-ID differ: Error INCOMPATIBLE to
  the PC, the program ends, the board is back in its bootloader;
- FPGA major version differs: Error VERSION_MISMATCH, the program aborts and the board
  resets (that reset does not honour AutoStart, so a board cannot loop);
- minor version differs: a warning text report, the program runs normally.

An image without a descriptor runs with a warning that nothing was checked.  A program
that passed runs its model (found by the descriptor's program name, see
:mod:`ucom_tools.virtual.programs.catalogue`) under an
:class:`~ucom_tools.virtual.board.runtime.McaRuntime`:
it announces itself with MCA Ready and serves the run-time protocol.
"""

from __future__ import annotations

from typing import Final

from ucom_tools.errors import FrameError
from ucom_tools.plugons import board_name
from ucom_tools.virtual.board.port import ProgramHost
from ucom_tools.virtual.board.runtime import McaRuntime
from ucom_tools.virtual.programs.catalogue import make as make_model
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import CheckField, ErrorCode, Target
from ucom_tools.wire.descriptor import ImageDescriptor
from ucom_tools.wire.fpga import FPGA_BASE, FpgaVersion, Reg
from ucom_tools.wire.ids import Address, Function

STARTUP_US: Final = 200.0
"""Time from Start until the program has read the FPGA and decided."""


class DspProgram:
    """A started program: checks compatibility, then runs (announcing itself)."""

    def __init__(self, board: ProgramHost, target: Target, name: str, progid: int, *,
                 defect: str | None = None) -> None:
        self.board = board
        self.target = target
        self.name = name
        self.progid = progid
        self.defect = defect
        """The board's defect (:mod:`~ucom_tools.virtual.board.mutants`), handed to the run time."""
        self.runtime: McaRuntime | None = None

    def start(self, t: float) -> None:
        self.board.at(t + STARTUP_US, self._check)

    def _check(self, t: float) -> None:
        board = self.board
        if not board.running(self):
            return  # reset or power loss in the meantime
        xmem = board.xmem
        fpga = FpgaVersion.decode(xmem.read(FPGA_BASE + Reg.VERSION1),
                                  xmem.read(FPGA_BASE + Reg.VERSION2))
        measured = xmem.read(FPGA_BASE + Reg.BOARD_ID) & 0x0F
        try:
            desc = board.descriptor(self.target)
        except FrameError:
            board.report_text(t, f"program '{self.name}': image descriptor corrupt; "
                                 "compatibility not checked")
            desc = None
        if desc is None:
            board.report_text(t, f"program '{self.name}' running without an image descriptor: "
                                 "compatibility with board and FPGA not checked")
            self._running(t)
            return
        mismatch = _mismatch(desc, fpga, measured)
        if mismatch is not None:
            field, expected, found = mismatch
            detail = (field << 16) | (expected << 8) | found
            if field is CheckField.FPGA_MAJOR:
                board.send(t, m.Error(ErrorCode.VERSION_MISMATCH, Function.START, detail))
                board.report_text(t, f"program '{self.name}' aborted: built for FPGA "
                                     f"{desc.fpga_major}.{desc.fpga_minor}, the FPGA is "
                                     f"{fpga.version}; resetting")
                board.end_program(t, reset=True)
            else:
                board.send(t, m.Error(ErrorCode.INCOMPATIBLE, Function.START, detail))
                why = _explain(field, expected, found)
                board.report_text(t, f"program '{self.name}' ended: {why}")
                board.end_program(t, reset=False)
            return
        if desc.fpga_minor != fpga.minor:
            board.report_text(t, f"warning: program '{self.name}' was built for FPGA "
                                 f"{desc.fpga_major}.{desc.fpga_minor}, the FPGA is "
                                 f"{fpga.version}; running")
        self._running(t, desc.name)

    def _running(self, t: float, program: str = "") -> None:
        board = self.board
        board.report_text(t, f"program '{self.name}' running (ProgID 0x{self.progid:08X})")
        spec, model, plant = make_model(program, board, board.placement, board.plant)
        if plant is not None:
            board.bind_plant(plant, t)  # the board's plant, resumed (or a new one)
        self.runtime = McaRuntime(board, spec, model, plant, t, defect=self.defect)

    def end(self) -> None:
        """The board leaves the program (reset, power loss, its own end)."""
        if self.runtime is not None:
            self.runtime.end()

    def on_frame(self, function: int, address: Address, data: bytes, t: float) -> None:
        """A generic MCA frame for this board."""
        if self.runtime is not None:
            self.runtime.on_frame(function, data, t)
        elif not address.is_broadcast:
            self.board.error(t, ErrorCode.NOT_RUNNING, function)

    def takes_ci_map(self, number: int) -> bool:
        """Whether the program takes CI map ``number`` (its run time defined it)."""
        runtime = self.runtime
        return runtime is not None and number in runtime.ci_maps

    def on_map(self, number: int, data: bytes, t: float) -> None:
        """A CI process-data frame."""
        if self.runtime is not None:
            self.runtime.on_map(number, data, t)

    def leds(self, t: float) -> dict[str, str]:
        if self.runtime is not None:
            return self.runtime.leds(t)
        return {"red": "off", "yellow": "off", "green": "blink"}
def _mismatch(desc: ImageDescriptor, fpga: FpgaVersion, measured: int
              ) -> tuple[CheckField, int, int] | None:
    if desc.board_id != fpga.board_id:
        return CheckField.FPGA_BOARD_ID, desc.board_id, fpga.board_id
    if desc.board_id != measured:
        return CheckField.PLUG_BOARD_ID, desc.board_id, measured
    if desc.app_id != fpga.app_id:
        return CheckField.APP_ID, desc.app_id, fpga.app_id
    if desc.fpga_major != fpga.major:
        return CheckField.FPGA_MAJOR, desc.fpga_major, fpga.major
    return None


def _explain(field: CheckField, expected: int, found: int) -> str:
    if field in (CheckField.FPGA_BOARD_ID, CheckField.PLUG_BOARD_ID):
        where = "the FPGA is made for" if field is CheckField.FPGA_BOARD_ID else \
            "the plug-on board is"
        return (f"built for Board-ID {expected} ({board_name(expected)}), {where} "
                f"Board-ID {found} ({board_name(found)})")
    return f"built for App-ID {expected}, the FPGA carries App-ID {found}"
