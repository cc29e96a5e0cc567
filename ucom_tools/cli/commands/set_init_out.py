"""``ucom set-init-out``: option 11 of dsp_console2can, SetInitOut: drive (or release) a
board's init output and show its LEDs; one call of
:func:`~ucom_tools.cli.commands.common.pin_command`, as ``set-init-in`` is."""

from __future__ import annotations

from ucom_tools.cli.commands.common import pin_command
from ucom_tools.wire.codes import StatusOp

set_init_out_cmd = pin_command("set-init-out", 11, StatusOp.INIT_OUT)
