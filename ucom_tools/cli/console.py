"""``ucom console``: the interactive console of dsp_console2can (options 1-21, q).

Accepts option numbers or names with arguments (``3 5``, ``info 5``, ``load FILE``),
asks for missing arguments, keeps history and completes names and files on a terminal,
shows the loaded image and the bus in the prompt.  Ctrl-C cancels the running operation
or the argument prompt, not the console.  Reads plain lines when standard input is not a
terminal, so it can be driven by a script.  The options, their names and which need init
come from the table of :mod:`ucom_tools.cli.menu`, shared with the subcommands.
"""

from __future__ import annotations

import shlex
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import click
from rich.console import Console as RichConsole
from rich.markup import escape

from ucom_tools.cli import render
from ucom_tools.cli.flashrun import run_flash
from ucom_tools.cli.menu import OPTIONS, MenuOption, init_advice, parse_flag, parse_level
from ucom_tools.cli.options import connection_options, describe
from ucom_tools.cli.output import stderr, stdout
from ucom_tools.errors import InputError, UcomError
from ucom_tools.image.formats import load_image
from ucom_tools.image.model import Image
from ucom_tools.ops import options as ops
from ucom_tools.ops.enumerate import enumerate_bus
from ucom_tools.ops.flash_types import FlashInterrupted, FlashRequest, Selection
from ucom_tools.ops.robot import ConnectSpec, Robot, open_robot
from ucom_tools.protocol.programmer import Cancelled
from ucom_tools.wire.codes import StatusOp, Target
from ucom_tools.wire.ids import ALL


@dataclass(frozen=True)
class Param:
    name: str
    prompt: str
    optional: bool = False


@dataclass(frozen=True)
class Option:
    """A menu option of :mod:`~ucom_tools.cli.menu` with its console arguments and action."""

    entry: MenuOption
    params: tuple[Param, ...]
    run: Callable[..., None]

    @property
    def number(self) -> str:
        return str(self.entry.number)

    @property
    def name(self) -> str:
        return self.entry.command

    @property
    def title(self) -> str:
        return self.entry.title

    @property
    def needs_init(self) -> bool:
        return self.entry.needs_init


BOARD = Param("board", "board (seq ID, F<n> for a fixed ID, or all)")
ONE_BOARD = Param("board", "board (seq ID or F<n>)")
LEVEL = Param("level", "level (set = drive low, release)")
FORCE = Param("force", "'force' to program a board the image does not fit", True)
TARGET = Param("target", "'flash' (default) or 'extram'", True)


class Session:
    """One console session: the open buses, the loaded image, the init state."""

    def __init__(self, robot: Robot, image: Image | None, *, console: RichConsole | None = None,
                 ask: Callable[[str], str] | None = None) -> None:
        self.robot = robot
        self.image = image
        self.bus: str | None = None
        self.out = console or stdout()
        self.ask = ask or (lambda prompt: input(prompt))
        self.initialised: set[str] = set()
        self.dsp_list: list[ops.Row] = []
        self.options = self._options()
        self.by_key: dict[str, Option] = {}
        for o in self.options:
            for key in (o.number, o.name, *o.entry.aliases):
                self.by_key[key] = o

    # ------------------------------------------------------------------ menu & prompt
    def _options(self) -> list[Option]:
        on = Param("on", "on/off", True)
        table: dict[int, tuple[tuple[Param, ...], Callable[..., None]]] = {
            1: ((), self.do_reset),
            2: ((), self.do_init),
            3: ((BOARD,), self.do_info),
            4: ((BOARD, on), self.do_prog_enable),
            5: ((BOARD, FORCE), self.do_program),
            6: ((ONE_BOARD, FORCE), self.do_extram),
            7: ((BOARD, TARGET), self.do_start),
            8: ((BOARD, on), self.do_autostart),
            9: ((Param("board", "board or all", True),), self.do_xreset),
            10: ((ONE_BOARD, LEVEL), self.do_init_in),
            11: ((ONE_BOARD, LEVEL), self.do_init_out),
            12: ((ONE_BOARD, Param("new", "new seq ID")), self.do_seqid),
            13: ((), self.do_count),
            14: ((), self.do_first),
            15: ((), self.do_last),
            16: ((), self.do_list_update),
            17: ((), self.do_list_print),
            18: ((Param("file", "image file (S-record or Intel HEX)"),), self.do_load),
            19: ((), self.do_progid),
            20: ((FORCE,), self.do_progall),
            21: ((ONE_BOARD,), self.do_reset_one),
        }
        return [Option(entry, *table[entry.number]) for entry in OPTIONS]

    def menu(self) -> None:
        lines = []
        for o in self.options:
            mark = "*" if o.needs_init else " "
            lines.append(f"{o.number:>3}{mark} {o.title:<20} [dim]{o.name}[/]")
        half = (len(lines) + 1) // 2
        self.out.print("[bold]dsp_console2can[/] - UCoM console      "
                       f"[dim]{describe(self.robot.spec)}[/]")
        for i in range(half):
            right = lines[i + half] if i + half < len(lines) else ""
            self.out.print(f"{lines[i]:<60}{right}")
        self.out.print("  q  Quit       [dim]* needs a completed init (2)   'bus NAME|all' "
                       "selects a bus   'menu' shows this[/]")

    def prompt(self) -> str:
        buses = self.bus or (",".join(self.robot.buses) if len(self.robot.buses) <= 2
                             else f"{len(self.robot.buses)} buses")
        img = (f" | {self.image.name} 0x{self.image.progid:08X}" if self.image
               else " | no image")
        return f"ucom [{buses}{img}]> "

    # ------------------------------------------------------------------ dispatch
    def execute(self, line: str) -> bool:
        """Run one input line; False when the console should quit."""
        try:
            words = shlex.split(line)
        except ValueError as e:
            self.out.print(f"[red]{escape(str(e))}[/]")
            return True
        if not words:
            return True
        key = words[0].lower()
        if key in ("q", "quit", "exit"):
            return False
        if key in ("menu", "help", "?", "h"):
            self.menu()
            return True
        if key == "bus":
            self.select_bus(words[1] if len(words) > 1 else "")
            return True
        option = self.by_key.get(key)
        if option is None:
            self.out.print(f"[red]unknown option {escape(repr(words[0]))}[/]: type a number "
                           "1-21, a name (e.g. info 3), 'menu' or q")
            return True
        args = words[1:]
        try:
            values = self._arguments(option, args)
        except EOFError:
            return True
        if values is None:
            return True
        try:
            option.run(*values)
        except FlashInterrupted as e:  # per board what the programming left
            render.print_flash(self.out, e.result)
            self.out.print(f"[yellow]{escape(render.interrupted_line(e.result, 'cancelled'))}[/]",
                           soft_wrap=True)
        except KeyboardInterrupt:
            self.out.print("[yellow]cancelled[/]")
        except Cancelled as e:
            self.out.print(f"[yellow]{escape(str(e))}[/]")
        except ops.NotInitialised as e:
            text = init_advice(e.bus, option.entry.number, console=True)
            self.out.print(f"[yellow]{escape(text)}[/]")
        except UcomError as e:
            self.out.print(f"[red]{escape(str(e))}[/]")
        return True

    def _arguments(self, option: Option, args: list[str]) -> list[str] | None:
        if len(args) > len(option.params):
            self.out.print(f"[red]{option.name} takes at most {len(option.params)} "
                           f"argument(s): " + " ".join(p.name for p in option.params) + "[/]")
            return None
        values = list(args)
        for p in option.params[len(args):]:
            if p.optional:
                break
            try:
                answer = self.ask(f"  {p.prompt}: ").strip()
            except KeyboardInterrupt:
                answer = ""  # Ctrl-C at a prompt cancels the prompt, not the console
            if not answer:
                self.out.print("[dim]cancelled[/]")
                return None
            values.append(answer)
        return values

    def select_bus(self, name: str) -> None:
        if not name or name == "all":
            self.bus = None
        elif name in self.robot.buses:
            self.bus = name
        else:
            self.out.print(f"[red]no bus {escape(repr(name))}; buses: "
                           f"{', '.join(self.robot.buses)}[/]")
            return
        self.out.print(f"bus: {self.bus or 'all (' + ', '.join(self.robot.buses) + ')'}")

    # ------------------------------------------------------------------ options
    def do_reset(self) -> None:
        render.print_reset(self.out, ops.reset(self.robot, bus=self.bus), "Reset All")

    def do_init(self) -> None:
        for h in self.robot.select(self.bus):
            e = enumerate_bus(h)
            render.print_enumeration(self.out, e)
            if e.found:
                self.initialised.add(h.name)

    def do_info(self, board: str) -> None:
        rows = ops.info(self.robot, ops.parse_ref(board), bus=self.bus)
        render.print_infos(self.out, rows, "GetInfo")

    def do_prog_enable(self, board: str, on: str | None = None) -> None:
        ref = ops.parse_ref(board)
        rows = ops.set_status(self.robot, ref, StatusOp.PROG_ENABLE, parse_flag(on),
                              bus=self.bus)
        render.print_rows(self.out, rows, "SetProgEnable")

    def _need_image(self) -> Image | None:
        if self.image is None:
            self.out.print("no S-record file loaded (option 18; Intel HEX is read too)")
            path = self.ask("  image file (S-record or Intel HEX): ").strip()
            if not path:
                return None
            self.do_load(path)
        return self.image

    def _program(self, selection: Selection, target: Target, bus: str | None,
                 force: str | None) -> None:
        if force is not None and force.lower() != "force":
            raise InputError(f"{force!r}: the only word allowed here is 'force'")
        image = self._need_image()
        if image is None:
            return
        request = FlashRequest(image, selection=selection, bus=bus, target=target, init=False,
                               force=force is not None)
        result = run_flash(self.robot, request, force_hint=None)
        if selection.kind == "enabled" and not result.boards:
            self.out.print("[yellow]no board is ProgEnabled:[/] 'all' programs the boards "
                           "that option 4 enabled; use '4 all' first, or option 20 "
                           "(ProgAll), which enables and programs every board")
            return
        render.print_flash(self.out, result)
        if any(b.outcome == "refused" for b in result.boards):
            self.out.print("[dim]add 'force' to program them anyway, e.g. '5 all force'[/]")

    def do_program(self, board: str, force: str | None = None) -> None:
        ref = ops.parse_ref(board)
        sel = Selection("enabled") if ref.is_all else Selection("list", (ref.address.number,))
        self._program(sel, Target.FLASH, ref.bus or self.bus, force)

    def do_extram(self, board: str, force: str | None = None) -> None:
        ref = ops.parse_ref(board)
        sel = Selection("enabled") if ref.is_all else Selection("list", (ref.address.number,))
        self._program(sel, Target.EXTRAM, ref.bus or self.bus, force)

    def do_progall(self, force: str | None = None) -> None:
        self._program(Selection("all"), Target.FLASH, self.bus, force)

    def do_start(self, board: str, target: str | None = None) -> None:
        where = (target or "flash").lower()
        if where not in ("flash", "extram"):
            raise InputError(f"{target!r}: start from 'flash' or 'extram'")
        rows = ops.start(self.robot, ops.parse_ref(board),
                         Target.EXTRAM if where == "extram" else Target.FLASH, bus=self.bus)
        render.print_rows(self.out, rows, "Start" + (" (ExtRAM)" if where == "extram" else ""))

    def do_autostart(self, board: str, on: str | None = None) -> None:
        rows = ops.set_status(self.robot, ops.parse_ref(board), StatusOp.AUTOSTART,
                              parse_flag(on), bus=self.bus)
        render.print_rows(self.out, rows, "SetAutoStart")

    def do_xreset(self, board: str = "all") -> None:
        rows = ops.reset(self.robot, ops.parse_ref(board), bus=self.bus, clear_autostart=True)
        render.print_reset(self.out, rows, "XReset")

    def _pin(self, board: str, level: str, op: StatusOp, option: int) -> None:
        ref = ops.parse_ref(board, allow_all=False)
        rows = ops.set_status(self.robot, ref, op, parse_level(level), bus=self.bus)
        render.print_rows(self.out, rows, "SetInitIn" if option == 10 else "SetInitOut")
        if rows and all(r.ok for r in rows):
            for bus, s in ops.board_status(self.robot, ref, bus=self.bus):
                self.out.print(f"{bus} board {ref.address}: LEDs {render.status_leds(s)}")

    def do_init_in(self, board: str, level: str) -> None:
        self._pin(board, level, StatusOp.INIT_IN, 10)

    def do_init_out(self, board: str, level: str) -> None:
        self._pin(board, level, StatusOp.INIT_OUT, 11)

    def do_seqid(self, board: str, new: str) -> None:
        try:
            value = int(new)
        except ValueError:
            raise InputError(f"{new!r} is not a seq ID 1-31") from None
        if not 1 <= value <= 31:
            raise InputError(f"{value} is not a seq ID 1-31")
        rows = ops.set_seqid(self.robot, ops.parse_ref(board, allow_all=False), value,
                             bus=self.bus)
        render.print_rows(self.out, rows, "SetSeqID")

    def do_count(self) -> None:
        rows = ops.info(self.robot, ops.BoardRef(None, ALL), bus=self.bus)
        if rows:
            render.print_infos(self.out, rows, "Count")
        else:
            self.out.print("[yellow]Count: no board answered[/] (boards answer once they have "
                           "a number: run option 2, init)")

    def do_first(self) -> None:
        render.print_probe(self.out, ops.probe(self.robot, bus=self.bus))

    def do_last(self) -> None:
        render.print_probe(self.out, ops.probe(self.robot, last=True, bus=self.bus))

    def do_list_update(self) -> None:
        self.dsp_list = ops.dsp_list(self.robot, bus=self.bus)
        self.out.print(f"DSP list updated: {len(self.dsp_list)} active board(s)")

    def do_list_print(self) -> None:
        if not self.dsp_list:
            self.out.print("DSP list is empty (option 16 builds it)")
            return
        render.print_infos(self.out, self.dsp_list, "DSP list")

    def do_load(self, file: str) -> None:
        self.image = load_image(Path(file).expanduser())
        self.out.print(f"loaded {escape(self.image.path)}: {self.image.size()} words, "
                       f"ProgID 0x{self.image.progid:08X}")

    def do_progid(self) -> None:
        image = self._need_image()
        if image is not None:
            self.out.print(f"ProgID of {escape(image.name)}: [bold]0x{image.progid:08X}[/]")

    def do_reset_one(self, board: str) -> None:
        ref = ops.parse_ref(board, allow_all=False)
        rows = ops.reset(self.robot, ref, bus=self.bus)
        render.print_reset(self.out, rows, f"Reset board {ref}")


# ----------------------------------------------------------------------------- loop
def _interactive(session: Session) -> None:
    from prompt_toolkit import PromptSession
    from prompt_toolkit.completion import NestedCompleter, PathCompleter, WordCompleter
    from prompt_toolkit.history import FileHistory, InMemoryHistory

    history: FileHistory | InMemoryHistory
    try:
        path = Path.home() / ".local" / "state" / "ucom" / "console_history"
        path.parent.mkdir(parents=True, exist_ok=True)
        history = FileHistory(str(path))
    except OSError:
        history = InMemoryHistory()
    words: dict[str, object] = {k: None for k in session.by_key}
    for k in ("menu", "q", "quit"):
        words[k] = None
    words["load"] = PathCompleter(expanduser=True)
    words["18"] = PathCompleter(expanduser=True)
    words["bus"] = WordCompleter([*session.robot.buses, "all"])
    completer = NestedCompleter.from_nested_dict(words)
    prompter: PromptSession[str] = PromptSession(history=history, completer=completer)
    session.ask = lambda p: prompter.prompt(p, completer=None)
    while True:
        try:
            line = prompter.prompt(session.prompt())
        except KeyboardInterrupt:
            continue
        except EOFError:
            break
        if not session.execute(line):
            break


def _scripted(session: Session) -> None:
    lines = iter(sys.stdin.readline, "")

    def ask(prompt: str) -> str:
        answer = next(lines, None)
        if answer is None:
            raise EOFError
        session.out.print(prompt + answer.rstrip("\n"), markup=False, highlight=False)
        return answer

    session.ask = ask
    for line in lines:
        session.out.print(session.prompt() + line.rstrip("\n"), markup=False, highlight=False)
        if not session.execute(line):
            break


@click.command("console")
@click.option("--image", "image_path", type=click.Path(),
              help="Image to load at start, S-record or Intel HEX (like dsp_console2can's "
                   "command line).")
@connection_options
def console(image_path: str | None, spec: ConnectSpec, bus_name: str | None) -> None:
    """The interactive console of dsp_console2can: options 1-21 and q.

    Type an option's number or name with its arguments ('3 5', 'info 5',
    'load firmware_images/armar3.fl.S'); missing arguments are asked for.  Options marked
    * need a completed init (option 2).  Ctrl-C cancels the running operation; q or
    Ctrl-D quits.  Try: ucom console --virtual armar3"""
    image = load_image(image_path) if image_path else None
    robot = open_robot(spec)
    try:
        session = Session(robot, image)
        if bus_name:
            session.select_bus(bus_name)
        session.menu()
        if sys.stdin.isatty() and sys.stdout.isatty():
            _interactive(session)
        else:
            _scripted(session)
    finally:
        robot.close()
    stderr().print("[dim]bye[/]")
