"""``ucom last``: option 15 of dsp_console2can, Get Last: which board is last on each
bus's init line (found through its init output); one call of
:func:`~ucom_tools.cli.commands.common.probe_command`, as ``first`` is."""

from __future__ import annotations

from ucom_tools.cli.commands.common import probe_command

last_cmd = probe_command("last", 15, True, "Found through its init output, the reverse "
                         "direction of the chain; two answers mean a broken line.")
