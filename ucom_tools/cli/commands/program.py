"""``ucom program``: option 5 of dsp_console2can, Program: program an image into a board's
flash, or with 'all' into every ProgEnabled board, verified like ``ucom flash``; one call
of :func:`ucom_tools.cli.flash.program_command` (the flashing code ``flash`` shares), as
``extram-load`` is."""

from __future__ import annotations

from ucom_tools.cli.flash import program_command
from ucom_tools.cli.menu import BOARD
from ucom_tools.wire.codes import Target

program_cmd = program_command(
    "program", 5, Target.FLASH,
    "Programs IMAGE into board BOARD, or with 'all' into every ProgEnabled board (see "
    "prog-enable); verified like 'flash'.\n\n" + BOARD)
