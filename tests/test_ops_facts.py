"""The operations say facts, the command line and the console word them (issue 37):
ops/options raises NotInitialised naming the bus only, cli/menu.init_advice words it."""

from __future__ import annotations

import ast
import re
from collections.abc import Callable
from pathlib import Path

import pytest

from ucom_tools.cli.menu import OPTIONS, init_advice
from ucom_tools.ops import options as ops
from ucom_tools.ops.robot import ConnectSpec, Robot, open_robot
from ucom_tools.wire.codes import StatusOp

OPS = Path(__file__).resolve().parent.parent / "ucom_tools" / "ops"


@pytest.mark.parametrize("call", [
    lambda r: ops.info(r, ops.parse_ref("2")),
    lambda r: ops.reset(r, ops.parse_ref("2")),
    lambda r: ops.set_status(r, ops.parse_ref("all"), StatusOp.PROG_ENABLE, 1),
    lambda r: ops.set_seqid(r, ops.parse_ref("1"), 5),
    lambda r: ops.start(r, ops.parse_ref("all")),
])
def test_an_operation_before_init_raises_the_bus_and_no_advice(
        call: Callable[[Robot], object]) -> None:
    robot = open_robot(ConnectSpec(virtual="rosi"))
    try:
        with pytest.raises(ops.NotInitialised) as caught:
            call(robot)
    finally:
        robot.close()
    assert caught.value.bus == "CAN0"
    assert str(caught.value) == "CAN0: no board has a seq ID yet"


def test_the_advice_names_the_option_and_differs_on_the_command_line_and_console() -> None:
    for o in OPTIONS:
        if not o.needs_init:
            continue
        cli = init_advice("CAN1", o.number)
        console = init_advice("CAN1", o.number, console=True)
        head = (f"CAN1: no board has a seq ID yet. Option {o.number} ({o.title}) works only "
                "after a successful init chain (option 2): ")
        assert cli.startswith(head + "run 'ucom init' first") and "add --init" in cli
        assert console.startswith(head + "run option 2 (Init) first")
        assert "--init" not in console and "'ucom init'" not in console
        assert ("'ucom flash' runs it itself" in cli) == (o.number in (5, 6))


def test_no_string_in_ops_tells_the_user_to_run_a_ucom_command_first() -> None:
    for path in sorted(OPS.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Constant) and isinstance(node.value, str):
                assert "run 'ucom" not in node.value, path.name


# ------------------------------------------------------------ no options below cli/
PACKAGE = OPS.parent
OPTION = re.compile(r"(?<![\w-])--[a-z]")
"""A command-line option (``--bus``) inside a string."""
NOT_YET: dict[str, str] = {}
"""Modules below cli/ still to be converted (issue 37): each still names an option (the
test says when one no longer does, to take it off)."""
ALLOWED: dict[str, tuple[str, str]] = {
    "net/share.py": ("--allow-writes", "the refusal of a write goes to another host (ucom "
                                       "browse), which cannot word it: it names the option "
                                       "the robot's loop runs without"),
    "viewers/foxglove.py": ("--allow-writes", "the same, to a Foxglove app's status line"),
    "viewers/foxglove_msgs.py": ("--allow-writes", "the set service's description, shown "
                                                   "in a Foxglove app"),
}
"""Texts below cli/ that name an option and must: messages to another host or program
that has no command line of its own to word them.  Nothing else: below cli/ no
protocol token or file format has the form of an option."""


def _docstrings(tree: ast.AST) -> set[int]:
    """The ids of the docstrings of ``tree``: modules, classes, functions, and the strings
    that document an attribute (right after an assignment)."""
    found: set[int] = set()
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if not isinstance(body, list):
            continue
        for i, stmt in enumerate(body):
            doc = isinstance(stmt, ast.Expr) and isinstance(stmt.value, ast.Constant) \
                and isinstance(stmt.value.value, str)
            after_assign = i > 0 and isinstance(body[i - 1], ast.Assign | ast.AnnAssign)
            if doc and (i == 0 or after_assign):
                found.add(id(stmt.value))
    return found


def _options_named(path: Path) -> list[str]:
    """Each string constant of ``path`` that names an option (docstrings exempt), and
    each ``key=`` (argument or default) that starts with ``-``."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    docs = _docstrings(tree)
    named = [f"{node.lineno}: {node.value!r}" for node in ast.walk(tree)
             if isinstance(node, ast.Constant) and isinstance(node.value, str)
             and id(node) not in docs and OPTION.search(node.value)]
    for node in ast.walk(tree):
        values = [k.value for k in node.keywords if k.arg == "key"] \
            if isinstance(node, ast.Call) else []
        if isinstance(node, ast.arguments):
            params = list(zip(node.args[len(node.args) - len(node.defaults):],
                              node.defaults, strict=True))
            params += [(a, d) for a, d in zip(node.kwonlyargs, node.kw_defaults, strict=True)
                       if d is not None]
            values = [d for a, d in params if a.arg == "key"]
        named += [f"{v.lineno}: key {v.value!r}" for v in values
                  if isinstance(v, ast.Constant) and isinstance(v.value, str)
                  and v.value.startswith("-")]
    return named


def test_no_string_below_cli_names_a_command_line_option() -> None:
    wrong: dict[str, list[str]] = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        name = path.relative_to(PACKAGE).as_posix()
        if name.startswith("cli/"):
            continue
        named = _options_named(path)
        if name in ALLOWED:
            text = ALLOWED[name][0]
            assert named and all(text in n and n.count("--") == 1 for n in named), named
            continue
        if name in NOT_YET:
            assert named, f"{name} names no option any more: take it off NOT_YET"
        elif named:
            wrong[name] = named
    assert not wrong, wrong


def test_the_guard_sees_an_option_in_a_message_a_key_and_a_default(tmp_path: Path) -> None:
    bad = tmp_path / "bad.py"
    for source in ('raise InputError("give --bus NAME")\n', 'raise InputError("x", key="-o")\n',
                   'def f(key: str = "--rate") -> None: ...\n',
                   'fileio.Batch(key="--journal")\n'):
        bad.write_text(source)
        assert _options_named(bad), source
    bad.write_text('"""Module doc: --bus is fine here."""\nX = 1\n"""And --rate here."""\n'
                   'raise InputError("no bus", key="bus")\n')
    assert _options_named(bad) == []


# ------------------------------------------------------- the command line words them
def test_a_python_caller_is_told_the_parameter_the_command_line_its_option() -> None:
    from ucom_tools.cli.errortext import describe
    from ucom_tools.errors import InputError
    from ucom_tools.ops.remote.part import RemotePart

    with pytest.raises(InputError) as caught:
        RemotePart.open("armar3", virtual=True, rate_hz=0, start=False)
    err = caught.value
    assert err.key == "rate_hz" and str(err) == "rate_hz: rate must be 1..10000 Hz, not 0"
    assert describe(err, "remote") == "--rate: rate must be 1..10000 Hz, not 0"


@pytest.mark.parametrize(("spec", "python", "command_line"), [
    (ConnectSpec(), "interface: no CAN interface given",
     "--interface: no CAN interface given: use --virtual NAME for the virtual fleet, or "
     "-i/--interface (e.g. socketcan, pcan, socketcand) with -c/--channel"),
    (ConnectSpec(interface="virtual"), "channels: no channel given",
     "--channel: no channel given: use -c/--channel (repeat it for several buses) or "
     "--topology FILE"),
    (ConnectSpec(interface="socketcand", channels=("CAN0",), port=1),
     "host: the socketcand interface needs a host and a port",
     "--host: the socketcand interface needs a host and a port: give --host HOST --port "
     "PORT, the address the socketcand server (ucom fleet serve, socketcand) listens on"),
])
def test_a_missing_input_is_named_and_the_command_line_says_how_to_give_it(
        spec: ConnectSpec, python: str, command_line: str) -> None:
    from ucom_tools.cli.errortext import describe
    from ucom_tools.errors import MissingInput

    with pytest.raises(MissingInput) as caught:
        open_robot(spec)
    assert str(caught.value) == python
    assert describe(caught.value, "init") == command_line


def test_every_key_the_command_line_words_is_one_of_its_options() -> None:
    import click

    from ucom_tools.cli.errortext import ADVICE_IN, MISSING, MISSING_IN, OPTIONS
    from ucom_tools.cli.main import cli

    def options(command: click.Command) -> set[str]:
        found = {o for p in command.params if isinstance(p, click.Option) for o in p.opts}
        if isinstance(command, click.Group):
            for name in command.list_commands(click.Context(command)):
                sub = command.get_command(click.Context(command), name)
                assert sub is not None
                found |= options(sub)
        return found

    every = options(cli)
    assert set(OPTIONS.values()) <= every, set(OPTIONS.values()) - every
    for advice in [*MISSING.values(), *MISSING_IN.values(), *ADVICE_IN.values()]:
        named = set(re.findall(r"(?<![\w-])--?[a-z][a-z-]*", advice))
        assert named and named <= every, (advice, named - every)


def test_trace_and_conformance_name_their_inputs_and_the_command_line_words_them(
        tmp_path: Path) -> None:
    """The keys of trace/ and conformance/ (the DBC file, the decoder's trees, a case
    pattern) and how ``ucom dbc``, ``ucom decode`` and ``ucom conformance`` word them."""
    from ucom_tools.cli.errortext import describe
    from ucom_tools.conformance.runner import select
    from ucom_tools.errors import InputError, OutputExists
    from ucom_tools.trace import dbc
    from ucom_tools.trace.decode import load_trees

    (tmp_path / "old.dbc").write_text("x")
    with pytest.raises(OutputExists) as exists:
        dbc.write(tmp_path / "old.dbc")
    assert str(exists.value) == f"dbc_file: {tmp_path / 'old.dbc'} exists"
    assert describe(exists.value, "dbc") == \
        f"--output: {tmp_path / 'old.dbc'} exists; --force replaces it"
    with pytest.raises(InputError) as trees:
        load_trees(["a.tree"])
    assert trees.value.key == "trees" and describe(trees.value, "decode").startswith(
        "--trees: give one robot")
    with pytest.raises(InputError) as none:
        select("nothing-like-this")
    assert str(none.value) == "pattern: no case matches 'nothing-like-this'"
    assert describe(none.value, "conformance") == \
        "--only: no case matches 'nothing-like-this' (see --list)"


def test_the_stop_of_the_suite_is_worded_by_its_reader() -> None:
    """A trace that could not be written stops the suite: a Python caller reads the
    parameter (trace_dir), the command line, its JSON and its report the option."""
    from ucom_tools.cli.conformance import _words
    from ucom_tools.conformance.runner import SuiteResult
    from ucom_tools.errors import WriteError

    result = SuiteResult(stopped=WriteError("t/CAN0: not a directory", key="trace_dir"))
    assert result.stop_text == "cannot write: trace_dir: t/CAN0: not a directory"
    assert result.describe_stop(_words) == \
        "cannot write: --trace-dir: t/CAN0: not a directory"
    assert SuiteResult(stopped=KeyboardInterrupt()).describe_stop(_words) == \
        "interrupted (SIGINT)"
