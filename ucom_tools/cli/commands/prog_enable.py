"""``ucom prog-enable``: option 4 of dsp_console2can, SetProgEnable: enable (``--off``:
disable) programming of a board or all; one call of
:func:`~ucom_tools.cli.commands.common.status_command`, as ``autostart`` is."""

from __future__ import annotations

from ucom_tools.cli.commands.common import status_command
from ucom_tools.wire.codes import StatusOp

prog_enable_cmd = status_command("prog-enable", 4, StatusOp.PROG_ENABLE)
