"""The manual pages say what the code does: options that need init, environment variables,
exit codes (each read from the code's own table)."""

from __future__ import annotations

import re
from pathlib import Path

import click
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


def _leaf_commands(groups: bool = False) -> dict[tuple[str, ...], click.Command]:
    """Every command of ``ucom`` by its words (``("fleet", "serve")``), groups walked
    (and named too with ``groups``, the root as ``()``); hidden ones (old names kept for
    scripts, tests/test_old_names.py) are not."""
    found: dict[tuple[str, ...], click.Command] = {}

    def walk(cmd: click.Command, words: tuple[str, ...]) -> None:
        if isinstance(cmd, click.Group):
            if groups:
                found[words] = cmd
            ctx = click.Context(cmd)
            for name in cmd.list_commands(ctx):
                sub = cmd.get_command(ctx, name)
                assert sub is not None, name
                if not sub.hidden:
                    walk(sub, (*words, name))
        else:
            found[words] = cmd

    walk(cli, ())
    return found


def _synopsis_commands(synopsis: str) -> set[tuple[str, ...]]:
    """The commands the SYNOPSIS names: ``.B ucom fleet show`` and the alternatives after
    it (``|`` then ``.B serve``), which belong to the same group."""
    found: set[tuple[str, ...]] = set()
    group: tuple[str, ...] = ()
    for line in synopsis.replace("\\-", "-").splitlines():
        if m := re.fullmatch(r"\.B ucom ([a-z-]+(?: [a-z-]+)*)", line):
            words = tuple(m.group(1).split())
            found.add(words)
            group = words[:-1]
        elif (m := re.fullmatch(r"\.B ([a-z-]+)", line)) and m.group(1) != "ucom":
            found.add((*group, m.group(1)))
    return found


def test_every_command_has_a_description_in_its_help() -> None:
    for words, cmd in _leaf_commands(groups=True).items():
        assert (cmd.help or "").strip(), f"ucom {' '.join(words)} has no description"
        text = CliRunner().invoke(cli, [*words, "--help"]).stdout
        first = " ".join(cmd.help.strip().splitlines()[0].split())
        assert first in " ".join(text.split()), f"ucom {' '.join(words)} --help: {text[:300]}"


def test_the_synopsis_names_every_command_and_breaks_only_between_them() -> None:
    page = (MAN / "ucom.1").read_text()
    synopsis = page[page.index(".SH SYNOPSIS"):page.index(".SH DESCRIPTION")]
    named = _synopsis_commands(synopsis)
    missing = {words for words in _leaf_commands() if words not in named
               and not (MAN / f"ucom-{words[0]}.1").exists()}  # or a page of its own
    assert not missing, f"man/ucom.1 SYNOPSIS lacks: {sorted(' '.join(w) for w in missing)}"
    unknown = named - set(_leaf_commands(groups=True))
    assert not unknown, f"man/ucom.1 SYNOPSIS names no such command: {sorted(unknown)}"
    glued = [line for line in synopsis.splitlines() if re.search(r"\S\.br\b", line)]
    assert not glued, f"a .br glued to the text before it: {glued}"
