"""The live view of ``ucom remote run`` on a terminal: every board's sensor values under
their robot-wide names, refreshed ten times a second, the loop's figures and each bus's
load, and a command line to set CI and PAR values while the boards run (with completion
of the names).

The PC's loop runs in a thread of its own (:meth:`RemotePart.cycle`); this view only
reads the latest values.  Rich renders the panels, prompt_toolkit runs the screen and the
input line.
"""

from __future__ import annotations

import io
import threading
from collections.abc import Iterable
from decimal import Decimal

from prompt_toolkit.application import Application
from prompt_toolkit.buffer import Buffer
from prompt_toolkit.completion import CompleteEvent, Completer, Completion
from prompt_toolkit.document import Document
from prompt_toolkit.formatted_text import ANSI, StyleAndTextTuples
from prompt_toolkit.input import Input
from prompt_toolkit.key_binding import KeyBindings, KeyPressEvent
from prompt_toolkit.layout import HSplit, Layout, Window
from prompt_toolkit.layout.controls import BufferControl, FormattedTextControl
from prompt_toolkit.output import Output
from rich.columns import Columns
from rich.console import Console, Group
from rich.markup import escape
from rich.panel import Panel
from rich.table import Table

from ucom_tools.errors import UcomError
from ucom_tools.ops.edges import EdgeRef
from ucom_tools.ops.remote import RemotePart
from ucom_tools.wire import mca

REFRESH_S = 0.1
HELP = ("NAME VALUE (or set NAME VALUE, NAME=VALUE) sets a CI or PAR by its robot-wide "
        "name; Tab completes; PgUp/PgDn scroll; q, Ctrl-C or Ctrl-D stop the boards and quit")


def _text(v: object) -> str:
    if v is None:
        return "-"
    return format(v, "f") if isinstance(v, Decimal) else str(v)


def parse_command(line: str) -> tuple[str, str] | None:
    """(name, value) of '[set] NAME VALUE' or 'NAME=VALUE'; None for an empty line."""
    text = line.strip()
    if not text:
        return None
    if text.lower().startswith("set "):
        text = text[4:].strip()
    if "=" in text:
        name, _, value = text.partition("=")
    else:
        name, _, value = text.rpartition(" ")
    if not name.strip() or not value.strip():
        raise ValueError("expected: [set] NAME VALUE, or NAME=VALUE")
    return name.strip(), value.strip()


class NameCompleter(Completer):
    """Completes robot-wide names (after an optional 'set '; case-insensitive, by prefix
    or by the start of a word)."""

    def __init__(self, names: list[str]) -> None:
        self.names = names

    def get_completions(self, document: Document, complete_event: CompleteEvent,
                        ) -> Iterable[Completion]:
        text = document.text_before_cursor
        body = text[4:] if text.lower().startswith("set ") else text
        typed = body.lower()
        for name in self.names:
            low = name.lower()
            if low.startswith(typed) or (typed and f" {typed}" in f" {low}"):
                yield Completion(name + " ", start_position=-len(body), display=name)


class LiveView:
    def __init__(self, part: RemotePart, *, pt_input: Input | None = None,
                 pt_output: Output | None = None) -> None:
        self.part = part
        self.pt_input = pt_input
        self.pt_output = pt_output
        self.message = HELP
        self.scroll = 0
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._loads: dict[str, float] = {}
        self._traffic = part.traffic()
        self._ticks = 0
        self.boards: dict[tuple[str, int], list[EdgeRef]] = {}
        for ref in part.names:
            if ref.kind is mca.Kind.SO:
                self.boards.setdefault((ref.bus, ref.board), []).append(ref)

    # ------------------------------------------------------------------ the loop thread
    def loop(self, app: Application[None]) -> None:
        try:
            while not self._stop.is_set():
                self.part.cycle()
        except BaseException as err:  # a bus failure ends the run; shown by the caller
            self.error = err
            app.exit()

    # ------------------------------------------------------------------ rendering
    def render(self, width: int) -> str:
        self._ticks += 1
        if self._ticks % 10 == 0:
            now = self.part.traffic()
            self._loads = self.part.load_between(self._traffic, now)
            self._traffic = now
        s = self.part.stats
        head = (f"[bold]{s.cycles}[/] cycles  [bold]{s.rate(self.part._clock()):.0f}[/] Hz"
                f"  missed [bold]{s.missed}[/]  lateness p50 {s.percentile(50) * 1e3:.3f} ms"
                f"  p99 {s.percentile(99) * 1e3:.3f} ms"
                + ("  (virtual time)" if self.part.virtual else "")
                + "   bus load " + "  ".join(f"{n} {v:.1%}" for n, v in self._loads.items()))
        panels = []
        for refs in self.boards.values():
            t = Table(show_header=False, box=None, pad_edge=False)
            t.add_column("name", overflow="ellipsis", no_wrap=True, max_width=32)
            t.add_column("value", justify="right", no_wrap=True)
            t.add_column("unit", style="dim", no_wrap=True)
            for ref in refs:
                raw = self.part.raw(ref)
                t.add_row(escape(ref.unique), _text(None if raw is None else ref.value(raw)),
                          escape(ref.spec.unit))
            panels.append(Panel(t, title=escape(f"{refs[0].prefix} - {refs[0].where}"),
                                title_align="left", expand=False))
        buf = io.StringIO()
        console = Console(file=buf, force_terminal=True, width=width, color_system="standard")
        console.print(Group(head, Columns(panels)))
        return buf.getvalue()

    def run(self) -> None:
        out = Buffer(completer=NameCompleter(self.part.names.names()),
                     complete_while_typing=True, multiline=False,
                     accept_handler=self._accept)
        keys = KeyBindings()

        @keys.add("c-c")
        @keys.add("c-d")
        def _quit(event: KeyPressEvent) -> None:
            event.app.exit()

        @keys.add("pageup")
        def _up(event: KeyPressEvent) -> None:
            self.scroll = max(0, self.scroll - 10)

        @keys.add("pagedown")
        def _down(event: KeyPressEvent) -> None:
            self.scroll += 10

        def body() -> StyleAndTextTuples:
            size = app.output.get_size()
            lines = self.render(size.columns).splitlines()
            room = max(1, size.rows - 3)
            self.scroll = min(self.scroll, max(0, len(lines) - room))
            return ANSI("\n".join(lines[self.scroll:self.scroll + room])).__pt_formatted_text__()

        app: Application[None] = Application(
            layout=Layout(HSplit([
                Window(FormattedTextControl(body), wrap_lines=False),
                Window(FormattedTextControl(lambda: [("class:message", self.message)]),
                       height=1),
                Window(BufferControl(out, input_processors=[]), height=1,
                       get_line_prefix=lambda n, w: [("bold", "> ")]),
            ]), focused_element=out),
            key_bindings=keys, full_screen=True, refresh_interval=REFRESH_S,
            mouse_support=False, input=self.pt_input, output=self.pt_output)
        thread = threading.Thread(target=self.loop, args=(app,), name="ucom-loop",
                                  daemon=True)
        thread.start()
        try:
            app.run()
        finally:
            self._stop.set()
            thread.join(timeout=5)
        if self.error is not None:
            raise self.error

    def _accept(self, buffer: Buffer) -> bool:
        line = buffer.text
        if line.strip().lower() in ("q", "quit", "exit"):
            from prompt_toolkit.application.current import get_app
            get_app().exit()
            return False
        try:
            parsed = parse_command(line)
            if parsed is not None:
                ref = self.part.set(parsed[0], parsed[1])
                raw = self.part.raw(ref)
                self.message = (f"{ref.qualified} = "
                                f"{_text(None if raw is None else ref.value(raw))}"
                                f" {ref.spec.unit}")
        except (UcomError, ValueError) as err:
            self.message = f"! {err}"
        return False


def live_view(part: RemotePart) -> None:
    """Show the live view until the user quits (the caller then stops the boards)."""
    LiveView(part).run()
