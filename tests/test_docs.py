"""The manual pages say what the code does: options that need init, environment variables,
exit codes (each read from the code's own table)."""

from __future__ import annotations

import re
from pathlib import Path

from click.testing import CliRunner

from ucom_tools import compiled
from ucom_tools.cli import exitcodes, menu, options
from ucom_tools.cli.main import cli

MAN = Path(__file__).resolve().parent.parent / "man"


def test_console_page_marks_exactly_the_options_that_need_init() -> None:
    page = (MAN / "ucom-console.1").read_text()
    block = page[page.index(".nf\n  1  Reset All"):]
    block = block[:block.index(".fi")]
    marked = {int(n) for n in re.findall(r"(\d+)\*", block)}
    assert marked == {o.number for o in menu.OPTIONS if o.needs_init}
    for o in menu.OPTIONS:
        assert re.search(rf"\b{o.number}\*?\s+{re.escape(o.title)}\b", block), o.title


def test_ucom_page_marks_the_same_commands_as_needing_init() -> None:
    page = (MAN / "ucom.1").read_text()
    headings = re.findall(r"^\.B .*?\\fR\(([\d, ]+?)(, init)?[;)]", page, re.M)
    marked: dict[int, bool] = {}
    for numbers, init in headings:
        for n in numbers.split(","):
            marked[int(n)] = bool(init)
    for o in menu.OPTIONS:
        if o.command in ("load", "progall", "list-update"):
            continue  # console-only options, or folded into another command
        assert marked.get(o.number) == o.needs_init, (o.number, o.command)


def test_help_of_every_option_command_says_whether_it_needs_init() -> None:
    for o in menu.OPTIONS:
        cmd = cli.commands.get(o.command)
        if cmd is None:
            continue
        text = CliRunner().invoke(cli, [o.command, "--help"]).stdout
        assert ("needs init" in " ".join(text.split())) == o.needs_init, o.command


def test_environment_and_exit_codes_are_documented_once_and_completely() -> None:
    page = (MAN / "ucom.1").read_text()
    env = page[page.index(".SH ENVIRONMENT"):page.index(".SH EXIT STATUS")]
    assert set(re.findall(r"UCOM_[A-Z_]*[A-Z]", env)) == set(options.ENVIRONMENT.values()) | {
        compiled.PURE_ENV}
    status = page[page.index(".SH EXIT STATUS"):page.index(".SH EXAMPLES")]
    assert {int(c) for c in re.findall(r"^\.B (\d+)$", status, re.M)} == set(exitcodes.ALL)
