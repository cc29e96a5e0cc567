"""A command imports what it needs: ``ucom init`` does not load the fleet server, the
trace decoder or Zenoh (the root's subcommands are imported when looked up), while
``ucom --help`` still lists every one of them."""

from __future__ import annotations

import subprocess
import sys

from click.testing import CliRunner

from ucom_tools.cli.main import SUBCOMMANDS, cli

PROBE = """
import sys
from click.testing import CliRunner
from ucom_tools.cli.main import cli
result = CliRunner().invoke(cli, ["init", "--help"])
assert result.exit_code == 0, result.output
print(" ".join(sorted(m for m in sys.modules)))
"""


def test_a_bootloader_command_does_not_import_the_others() -> None:
    run = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True,
                         check=True)
    loaded = set(run.stdout.split())
    assert "ucom_tools.cli.commands" in loaded
    for heavy in ("zenoh", "ucom_tools.virtual.serve.socketcand",
                  "ucom_tools.virtual.serve.multiserve", "ucom_tools.trace.decode",
                  "ucom_tools.cli.conformance", "ucom_tools.cli.browse"):
        assert heavy not in loaded, heavy


def test_the_root_help_lists_every_subcommand() -> None:
    result = CliRunner().invoke(cli, ["--help"])
    assert result.exit_code == 0
    listed = {line.split()[0] for line in result.output.split("Commands:")[1].splitlines()
              if line.strip()}
    assert listed == set(SUBCOMMANDS)
    assert all(cli.commands[name].name == name for name in SUBCOMMANDS)
