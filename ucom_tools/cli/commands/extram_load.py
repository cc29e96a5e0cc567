"""``ucom extram-load``: option 6 of dsp_console2can, ExtRAMLoad: load an image into a
board's external RAM instead of its flash (gone after a reset; ``ucom start --extram``
starts it); one call of :func:`ucom_tools.cli.flash.program_command` (the flashing code
``flash`` shares), as ``program`` is."""

from __future__ import annotations

from ucom_tools.cli.flash import program_command
from ucom_tools.cli.menu import BOARD
from ucom_tools.wire.codes import Target

extram_load_cmd = program_command(
    "extram-load", 6, Target.EXTRAM,
    "Loads IMAGE into external RAM of BOARD instead of flash (gone after reset; start it "
    "with 'start --extram').\n\n" + BOARD)
