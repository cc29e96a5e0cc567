"""The live view of ``ucom remote run`` on a terminal: every board's sensor values under
their robot-wide names, refreshed ten times a second, the loop's figures and each bus's
load, and a command line to set CI and PAR values while the boards run (with completion
of the names).

The PC's loop runs in a thread of its own (:meth:`RemotePart.cycle`); this view only
reads the latest values.  The boxes are plain text with ANSI styles, prompt_toolkit runs the
screen and the input line.
"""

from __future__ import annotations

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

from ucom_tools.errors import UcomError
from ucom_tools.ops.edges import EdgeRef
from ucom_tools.ops.remote import RECENT_SAMPLES, RemotePart
from ucom_tools.wire import mca

REFRESH_S = 0.1
NAME_WIDTH = 32
"""Longer names are cut (with an ellipsis) in the boxes."""
VALUE_WIDTH = 8
"""The least width of a value column (so that boxes do not jump as values change)."""
_BOLD, _DIM, _RESET = "\x1b[1m", "\x1b[2m", "\x1b[0m"
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


def _box(title: str, rows: list[tuple[str, str, str]]) -> tuple[int, list[str]]:
    """A rounded box titled ``title`` with a row per (name, value, unit): its width in
    columns and its lines (ANSI styles do not count in the width)."""
    names = [n if len(n) <= NAME_WIDTH else n[:NAME_WIDTH - 1] + "\u2026" for n, _, _ in rows]
    name_w = max((len(n) for n in names), default=0)
    value_w = max([VALUE_WIDTH, *(len(v) for _, v, _ in rows)])
    unit_w = max((len(u) for _, _, u in rows), default=0)
    inner = max(name_w + 1 + value_w + 1 + unit_w, len(title) + 2)
    if len(title) + 2 > inner:  # pragma: no cover - max() above
        title = title[:inner - 2]
    lines = ["\u256d\u2500 " + title + " " + "\u2500" * (inner - len(title) - 1) + "\u256e"]
    pad = inner - (name_w + 1 + value_w + 1 + unit_w)
    for name, (_, value, unit) in zip(names, rows, strict=True):
        lines.append(f"\u2502 {name:<{name_w}} {value:>{value_w}} {_DIM}{unit:<{unit_w}}"
                     f"{_RESET}{' ' * pad} \u2502")
    lines.append("\u2570" + "\u2500" * (inner + 2) + "\u256f")
    return inner + 4, lines


def _arrange(boxes: list[tuple[int, list[str]]], width: int) -> list[str]:
    """Boxes side by side as many as fit in ``width``, then the next row of them."""
    out: list[str] = []
    row: list[tuple[int, list[str]]] = []
    used = 0
    for box in [*boxes, (0, [])]:
        if row and (not box[1] or used + 1 + box[0] > width):
            height = max(len(lines) for _, lines in row)
            for k in range(height):
                out.append(" ".join(lines[k] if k < len(lines) else " " * w
                                    for w, lines in row).rstrip())
            row, used = [], 0
        if box[1]:
            row.append(box)
            used += box[0] + (1 if used else 0)
    return out


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
        self._events_seen = len(part.events)
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
        """The view as text with ANSI styles: the loop's figures, then a box per board.
        Written out by hand, not with rich's tables: at ten renders a second rich took
        most of a core for ARMAR-III's 220 values, and held the GIL the loop needs."""
        self._ticks += 1
        if len(self.part.events) > self._events_seen:  # what the boards reported
            self._events_seen = len(self.part.events)
            e = self.part.events[-1]
            self.message = f"! {e.where} at {e.time:.3f} s: {e.text}"
        if self._ticks % 10 == 0:
            now = self.part.traffic()
            self._loads = self.part.load_between(self._traffic, now)
            self._traffic = now
        s = self.part.stats
        head = (f"{_BOLD}{s.cycles}{_RESET} cycles  {_BOLD}{s.rate(self.part._clock()):.0f}"
                f"{_RESET} Hz  missed {_BOLD}{s.missed}{_RESET}  lateness (last "
                f"{RECENT_SAMPLES} cycles) p50 {s.percentile(50, RECENT_SAMPLES) * 1e3:.3f} ms"
                f"  p99 {s.percentile(99, RECENT_SAMPLES) * 1e3:.3f} ms"
                + ("  (virtual time)" if self.part.virtual else "")
                + "   bus load " + "  ".join(f"{n} {v:.1%}" for n, v in self._loads.items()))
        boxes = []
        for refs in self.boards.values():
            rows = []
            for ref in refs:
                raw = self.part.raw(ref)
                rows.append((ref.unique, _text(None if raw is None else ref.value(raw)),
                             ref.spec.unit))
            boxes.append(_box(f"{refs[0].prefix} - {refs[0].where}", rows))
        return "\n".join([head, *_arrange(boxes, width)]) + "\n"

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
