"""``ucom autostart``: option 8 of dsp_console2can, SetAutoStart: start the flash program
after every reset (``--off``: clear the flag); one call of
:func:`~ucom_tools.cli.commands.common.status_command`, as ``prog-enable`` is."""

from __future__ import annotations

from ucom_tools.cli.commands.common import status_command
from ucom_tools.wire.codes import StatusOp

autostart_cmd = status_command("autostart", 8, StatusOp.AUTOSTART)
