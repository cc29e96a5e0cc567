"""A command imports what it uses, and ``ucom --help`` imports click and no more.

Guarded by what ``python -X importtime`` shows a real ``ucom`` process import (no timing:
the figures are in the README); the one table of commands (``cli/main.py`` ``COMMANDS``)
is checked against the commands themselves, and the root help made from it against the
one click would make from the imported commands.
"""

from __future__ import annotations

import importlib
import os
import pkgutil
import re
import subprocess
import sys
from dataclasses import dataclass

import click
import pytest
from click.testing import CliRunner

import ucom_tools.cli
from ucom_tools.cli.main import COMMANDS, LazyCommands, UcomGroup, cli

PROBE = """
import sys
import ucom_tools.cli
from ucom_tools.cli.main import main
try:
    main()
finally:
    sys.stderr.write("\\nMODULES " + " ".join(sys.modules) + "\\n")
"""
"""``ucom`` as its entry point runs it, then the modules it ended with (importtime also
lists imports that failed, such as optional modules a library tries)."""

HEAVY = ("bincopy", "elftools", "canopen", "zenoh", "foxglove", "mcap", "numpy",
         "matplotlib", "plotext", "prompt_toolkit", "cantools")
"""Libraries that only some commands use, each costing a noticeable part of a start-up."""

LIGHT = {"ucom_tools", "ucom_tools.compiled", "ucom_tools.native", "ucom_tools.errors",
         "ucom_tools.signals", "ucom_tools.cli", "ucom_tools.cli.main",
         "ucom_tools.cli.exitcodes", "ucom_tools._native__mypyc"}
"""All of ucom-tools that ``ucom --help`` and ``ucom --version`` may import (the last: the
compiled modules' library, through ``signals``, when the run time is compiled)."""

NOT_FOR_A_BOOTLOADER_COMMAND = (
    "ucom_tools.image", "ucom_tools.ops.flash", "ucom_tools.cli.flashrun",
    "ucom_tools.ops.params", "ucom_tools.ops.remote", "ucom_tools.ops.realtime",
    "ucom_tools.cli.params", "ucom_tools.cli.remote", "ucom_tools.cli.fleet",
    "ucom_tools.net", "ucom_tools.gateway", "ucom_tools.conformance", "ucom_tools.viewers",
    "ucom_tools.virtual.serve.socketcand", "ucom_tools.virtual.serve.multiserve",
    "ucom_tools.trace.decode", *HEAVY)
"""What ``ucom init`` and the other options of dsp_console2can do not use (``flash``
imports the image and flash modules when it runs, not for its ``--help``)."""


@dataclass(frozen=True)
class Imports:
    """What one ``ucom`` process imported, and who imported each module first."""

    modules: frozenset[str]
    trace: tuple[tuple[int, str], ...]
    """``-X importtime``'s lines: (depth, module), each module after those it imported."""

    def has(self, name: str) -> bool:
        """``name`` or a module inside it was imported."""
        return any(m == name or m.startswith(name + ".") for m in self.modules)

    def why(self, name: str) -> str:
        """The chain of imports that brought ``name`` (or a module in it) in."""
        for i, (depth, module) in enumerate(self.trace):
            if module == name or module.startswith(name + "."):
                chain = [module]
                for up, importer in self.trace[i + 1:]:
                    if up < depth:
                        chain.append(importer)
                        depth = up
                return " <- ".join(chain)
        return f"{name} (not in the trace)"

    def unwanted(self, names: tuple[str, ...] | list[str]) -> list[str]:
        return [self.why(n) for n in names if self.has(n)]


def ucom_imports(*args: str) -> Imports:
    """Run ``ucom ARGS`` in a fresh interpreter under ``-X importtime``."""
    env = {k: v for k, v in os.environ.items()
           if not k.startswith("UCOM_") or k == "UCOM_PURE_PYTHON"}
    run = subprocess.run([sys.executable, "-X", "importtime", "-c", PROBE, *args],
                         capture_output=True, text=True, env=env, timeout=120)
    assert run.returncode == 0, run.stdout + run.stderr[-3000:]
    modules = frozenset(re.search(r"^MODULES (.*)$", run.stderr, re.M)[1].split())
    trace = tuple((len(m[1]) // 2, m[2]) for m in
                  re.finditer(r"^import time:\s+\d+ \|\s+\d+ \|( *)(\S+)$", run.stderr, re.M))
    assert trace, "no -X importtime lines"
    return Imports(modules, trace)


@pytest.mark.parametrize("args", [["--help"], ["--version"]])
def test_help_and_version_import_click_and_nothing_else(args: list[str]) -> None:
    imports = ucom_imports(*args)
    ours = {m for m in imports.modules if m.split(".")[0] == "ucom_tools"}
    assert ours <= LIGHT, [imports.why(m) for m in sorted(ours - LIGHT)]
    assert not imports.unwanted(["rich", "can", *HEAVY])
    assert imports.has("click")


@pytest.mark.parametrize("args", [["init", "--help"], ["flash", "--help"],
                                  ["program", "--help"],
                                  ["init", "--virtual", "armar3", "--no-info"]])
def test_a_bootloader_command_imports_what_it_uses(args: list[str]) -> None:
    imports = ucom_imports(*args)
    assert imports.has(f"ucom_tools.cli.{COMMANDS[args[0]].module}") and imports.has("can")
    assert not imports.unwanted(list(NOT_FOR_A_BOOTLOADER_COMMAND))
    if "--virtual" in args:
        assert imports.has("ucom_tools.virtual.fleet")  # it did run the command
    else:
        assert not imports.has("ucom_tools.virtual")


def test_remote_run_help_imports_no_server_viewer_or_gateway() -> None:
    imports = ucom_imports("remote", "run", "--help")
    assert imports.has("ucom_tools.cli.remote")
    assert not imports.unwanted(["ucom_tools.gateway", "ucom_tools.virtual",
                                 "ucom_tools.conformance", "ucom_tools.cli.commands",
                                 *HEAVY])


USES = {"gateway": ("canopen",)}
"""The heavy libraries a command's module needs to define its commands."""


OPTION_MODULES = frozenset(f"ucom_tools.cli.{e.module}" for e in COMMANDS.values()
                           if e.module.startswith("commands."))
"""The modules of the console options' commands (``cli/commands/``, a module each)."""


@pytest.mark.parametrize("name", sorted({e.module: n for n, e in COMMANDS.items()}.values()))
def test_no_help_imports_a_library_its_command_does_not_use(name: str) -> None:
    imports = ucom_imports(name, "--help")
    own = f"ucom_tools.cli.{COMMANDS[name].module}"
    assert imports.has(own)
    allowed = USES.get(name, ())
    assert not imports.unwanted([h for h in HEAVY if h not in allowed])
    assert not imports.unwanted(sorted(OPTION_MODULES - {own}))  # only its own option's


def _reachable(command: click.Command) -> list[click.Command]:
    sub = command.commands.values() if isinstance(command, click.Group) else []
    return [command, *(c for s in sub for c in _reachable(s))]


def test_the_table_names_every_command_and_only_commands() -> None:
    for name, entry in COMMANDS.items():
        command = cli.commands[name]
        assert command is getattr(importlib.import_module(f"ucom_tools.cli.{entry.module}"),
                                  entry.attr)
        assert command.name == name
    reachable = {id(c) for name in COMMANDS for c in _reachable(cli.commands[name])}
    reachable.add(id(cli))
    for found in pkgutil.walk_packages(ucom_tools.cli.__path__, "ucom_tools.cli."):
        module = importlib.import_module(found.name)
        stray = [attr for attr, value in vars(module).items()
                 if isinstance(value, click.Command) and id(value) not in reachable]
        assert not stray, f"{found.name}: commands missing from COMMANDS"


@pytest.mark.parametrize("width", [80, 60, 40])
def test_the_root_help_from_the_table_is_the_one_of_the_commands(width: int) -> None:
    """The summaries of ``COMMANDS`` are the commands' own first sentences: the help
    listed without importing them reads as click lists the imported commands."""
    table = LazyCommands(COMMANDS)
    lazy = UcomGroup("ucom", commands=table, params=cli.params, help=cli.help)
    loaded = UcomGroup("ucom", commands={n: cli.commands[n] for n in COMMANDS},
                       params=cli.params, help=cli.help)
    help_texts = [group.get_help(click.Context(group, info_name="ucom", terminal_width=width,
                                               help_option_names=["-h", "--help"]))
                  for group in (lazy, loaded)]
    assert help_texts[0] == help_texts[1]
    assert all(table.listing(n) is not cli.commands[n] for n in COMMANDS)  # none imported
    assert len(help_texts[0].split("Commands:")[1].strip().splitlines()) >= len(COMMANDS)


def test_the_root_help_lists_every_subcommand() -> None:
    result = CliRunner().invoke(cli, ["--help"])
    assert result.exit_code == 0
    listed = {line.split()[0] for line in result.output.split("Commands:")[1].splitlines()
              if line.strip()}
    assert listed == set(COMMANDS)
