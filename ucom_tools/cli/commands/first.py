"""``ucom first``: option 14 of dsp_console2can, Get First: which board is first on each
bus's init line; one call of :func:`~ucom_tools.cli.commands.common.probe_command`, as
``last`` is."""

from __future__ import annotations

from ucom_tools.cli.commands.common import probe_command

first_cmd = probe_command("first", 14, False, "Two answers mean the init line is broken "
                          "(exit code 1).")
