"""``ucom set-init-in``: option 10 of dsp_console2can, SetInitIn: drive (or release) a
board's init input and show its LEDs; one call of
:func:`~ucom_tools.cli.commands.common.pin_command`, as ``set-init-out`` is."""

from __future__ import annotations

from ucom_tools.cli.commands.common import pin_command
from ucom_tools.wire.codes import StatusOp

set_init_in_cmd = pin_command("set-init-in", 10, StatusOp.INIT_IN)
