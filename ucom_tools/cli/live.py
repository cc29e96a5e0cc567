"""The live view of ``ucom remote run`` on a terminal: every board's sensor values under
their robot-wide names, refreshed ten times a second, the loop's figures and each bus's
load, and a command line to set CI and PAR values while the boards run (with completion
of the names).

The view reads nothing of the loop's but the snapshots it hands over
(:class:`~ucom_tools.ops.remote.publish.LoopSnapshot`: values, figures, events, the lost
boards) and the part's structure (:class:`~ucom_tools.ops.remote.image.PartImage`);
its writes are applied on the loop's thread and answered.  ``ucom remote run`` shows it
from the consumers' process (:mod:`ucom_tools.cli.consumers`), the loop in another;
:meth:`LiveView.local` shows it beside the loop in one process (the loop on a thread of
the view's).  A lost board's box says so and for how long, its values dimmed with their
age.  The boxes are plain text with ANSI styles, prompt_toolkit runs the screen and the
input line.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable
from decimal import Decimal
from typing import TYPE_CHECKING, Any

from prompt_toolkit.application import Application
from prompt_toolkit.buffer import Buffer
from prompt_toolkit.completion import CompleteEvent, Completer, Completion
from prompt_toolkit.document import Document
from prompt_toolkit.formatted_text import StyleAndTextTuples
from prompt_toolkit.input import Input
from prompt_toolkit.key_binding import KeyBindings, KeyPressEvent
from prompt_toolkit.layout import Dimension, HSplit, Layout, Window
from prompt_toolkit.layout.controls import BufferControl, FormattedTextControl
from prompt_toolkit.output import Output

from ucom_tools.cli.ages import age_text
from ucom_tools.ops.edges import EdgeRef
from ucom_tools.ops.remote import RemotePart
from ucom_tools.ops.remote.feed import LocalRun
from ucom_tools.ops.remote.image import PartImage
from ucom_tools.ops.remote.loop import RECENT_SAMPLES
from ucom_tools.ops.remote.publish import LoopSnapshot
from ucom_tools.wire import mca

if TYPE_CHECKING:
    from ucom_tools.config.topology import BoardKey

REFRESH_S = 0.1
NAME_WIDTH = 32
"""Longer names are cut (with an ellipsis) in the boxes."""
VALUE_WIDTH = 8
"""The least width of a value column (so that boxes do not jump as values change)."""
WRITE_S = 5.0
"""How long the view waits for the loop's answer to a write."""
LOAD_EVERY_S = 1.0
"""The buses' load is measured over this long (of the bus clock)."""
_BOLD, _DIM, _RESET = "\x1b[1m", "\x1b[2m", "\x1b[0m"
_RED = "\x1b[1;31m"
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


Line = list[tuple[str, str]]
"""A line of the view as prompt_toolkit's formatted text: (style, text) fragments."""
BOLD, DIM, RED = "bold", "dim", "bold fg:ansired"
_ESCAPES = {"": "", BOLD: _BOLD, DIM: _DIM, RED: _RED}


def ansi(lines: list[Line]) -> str:
    """The lines as text with ANSI styles."""
    return "\n".join("".join(text if not style else _ESCAPES[style] + text + _RESET
                               for style, text in line) for line in lines)


def _box(title: str, rows: list[tuple[str, str, str]], *, stale: str = "",
         ) -> tuple[int, list[Line]]:
    """A rounded box titled ``title`` with a row per (name, value, unit): its width in
    columns and its lines.  ``stale``: the board is lost; the title says so (e.g. 'LOST
    1.2 s', red) and the values are dimmed."""
    names = [n if len(n) <= NAME_WIDTH else n[:NAME_WIDTH - 1] + "\u2026" for n, _, _ in rows]
    name_w = max((len(n) for n in names), default=0)
    value_w = max([VALUE_WIDTH, *(len(v) for _, v, _ in rows)])
    unit_w = max((len(u) for _, _, u in rows), default=0)
    lost = f"  {stale}" if stale else ""
    inner = max(name_w + 1 + value_w + 1 + unit_w, len(title) + len(lost) + 2)
    lines: list[Line] = [[("", "\u256d\u2500 " + title), (RED, lost),
                          ("", " " + "\u2500" * (inner - len(title) - len(lost) - 1)
                           + "\u256e")]]
    pad = inner - (name_w + 1 + value_w + 1 + unit_w)
    value_style = DIM if stale else ""
    for name, (_, value, unit) in zip(names, rows, strict=True):
        lines.append([("", f"\u2502 {name:<{name_w}} "), (value_style, f"{value:>{value_w}}"),
                      ("", " "), (DIM, f"{unit:<{unit_w}}"), ("", f"{' ' * pad} \u2502")])
    lines.append([("", "\u2570" + "\u2500" * (inner + 2) + "\u256f")])
    return inner + 4, lines


def _arrange(boxes: list[tuple[int, list[Line]]], width: int) -> list[Line]:
    """Boxes side by side as many as fit in ``width``, then the next row of them."""
    out: list[Line] = []
    row: list[tuple[int, list[Line]]] = []
    used = 0
    for box in [*boxes, (0, [])]:
        if row and (not box[1] or used + 1 + box[0] > width):
            height = max(len(lines) for _, lines in row)
            for k in range(height):
                line: Line = []
                for i, (w, lines) in enumerate(row):
                    if i:
                        line.append(("", " "))
                    line += lines[k] if k < len(lines) else [("", " " * w)]
                out.append(line)
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
    """The view of a run: ``image`` is the part's structure, ``source`` hands over the
    loop's snapshots (``latest``) and applies the view's writes on the loop's thread
    (``write``): the consumers' process's :class:`~ucom_tools.ops.remote.mirror.Mirror`
    (``ucom remote run``), or in the loop's own process a
    :class:`~ucom_tools.ops.remote.feed.LocalRun` with ``cycle``, the loop, run on a
    thread of the view's own (:meth:`local`).  ``ended``: set when the run ended
    elsewhere (the view then ends too)."""

    def __init__(self, image: PartImage, source: Any, *,
                 ended: threading.Event | None = None,
                 cycle: Callable[[], object] | None = None,
                 pt_input: Input | None = None, pt_output: Output | None = None) -> None:
        self.image = image
        self.source = source
        self.ended = ended
        self.cycle = cycle
        self.pt_input = pt_input
        self.pt_output = pt_output
        self.message = HELP
        self.scroll = 0
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._loads: dict[str, float] = {}
        self._load_from: LoopSnapshot | None = None
        self._events_seen = 0
        self._faults_seen = 0
        self._app: Application[None] | None = None
        self.boards: dict[BoardKey, list[EdgeRef]] = {}
        for ref in image.refs:
            if ref.kind is mca.Kind.SO:
                self.boards.setdefault((ref.bus, ref.board), []).append(ref)

    @classmethod
    def local(cls, part: RemotePart, **kwargs: Any) -> LiveView:
        """The view of a started ``part`` in this process, its loop on a thread of the
        view's (:meth:`run` starts it before anything else)."""
        return cls(PartImage.of(part), LocalRun(part, 1.0 / REFRESH_S), cycle=part.cycle,
                   **kwargs)

    # ------------------------------------------------------------------ the loop thread
    def loop(self) -> None:
        """The loop's thread (:meth:`local`): cycles until the view ends (or the loop
        fails: then the view ends, and :meth:`run` raises what stopped the loop)."""
        assert self.cycle is not None
        try:
            while not self._stop.is_set():
                self.cycle()
        except BaseException as err:  # a bus failure ends the run; shown by the caller
            self.error = err
            self._exit()

    def _exit(self) -> None:
        """End the screen (from any thread)."""
        app = self._app
        loop = None if app is None else app.loop
        if app is not None and app.is_running and loop is not None:
            loop.call_soon_threadsafe(app.exit)  # (the screen's own thread exits it)

    # ------------------------------------------------------------------ rendering
    def render(self, width: int) -> str:
        """The view as text with ANSI styles (:meth:`lines`)."""
        return ansi(self.lines(width)) + "\n"

    def lines(self, width: int) -> list[Line]:
        """The view, a line at a time: the loop's figures, then a box per board, all from
        the latest snapshot the loop handed over.  Written out by hand as fragments of
        prompt_toolkit's formatted text, a fragment per style: at ten renders a second
        rich's tables took most of a core for ARMAR-III's 220 values, and text with ANSI
        styles cost prompt_toolkit three times as much as the fragments."""
        snap = self.source.latest
        if snap is None:
            return [[("", "starting ...")]]
        self._note_events(snap)
        if self._load_from is None:
            self._load_from = snap
        elif snap.clock - self._load_from.clock >= LOAD_EVERY_S:
            self._loads = snap.load_since(self._load_from)
            self._load_from = snap
        f = snap.figures
        head: Line = [
            (BOLD, str(f.cycles)), ("", " cycles  "), (BOLD, f"{f.rate(snap.clock):.0f}"),
            ("", " Hz  missed "), (BOLD, str(f.missed)),
            ("", f"  lateness (last {RECENT_SAMPLES} cycles) p50 "
                 f"{f.percentile(50) * 1e3:.3f} ms  p99 {f.percentile(99) * 1e3:.3f} ms"
                 + ("  (virtual time)" if self.image.virtual else "")
                 + "   bus load " + "  ".join(f"{n} {v:.1%}"
                                              for n, v in self._loads.items()))]
        if snap.lost:
            head.append((RED, f"  {len(snap.lost)} board(s) lost"))
        values = self.image.decode(snap.values, (mca.Kind.SO,))
        boxes = []
        for (bus, board), refs in self.boards.items():
            lost = snap.lost.get((bus, board))
            rows = []
            for ref in refs:
                got = values.get(ref)
                text = "-" if got is None else _text(got[1])
                if lost is not None and got is not None:
                    text += f" ({age_text(snap.stamp - got[0])})"
                rows.append((ref.unique, text, ref.spec.unit))
            stale = "" if lost is None else "LOST " + age_text(
                snap.clock - f.started_clock - lost.since)
            boxes.append(_box(f"{refs[0].prefix} - {refs[0].where}", rows, stale=stale))
        return [head, *_arrange(boxes, width)]

    def _note_events(self, snap: LoopSnapshot) -> None:
        """The latest of what the boards reported (Errors) and of the boards lost or
        rejoined, as the message line."""
        events = snap.newer(snap.events, snap.events_total, self._events_seen)
        self._events_seen = snap.events_total
        if events:
            e = events[-1]
            self.message = f"! {e.where} at {e.time:.3f} s: {e.text}"
        faults = snap.newer(snap.faults, snap.faults_total, self._faults_seen)
        self._faults_seen = snap.faults_total
        if faults:
            self.message = "! " + faults[-1].describe()

    def application(self) -> Application[None]:
        out = Buffer(completer=NameCompleter(self.image.names.names()),
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
            lines = self.lines(size.columns)
            room = max(1, size.rows - 3)
            self.scroll = min(self.scroll, max(0, len(lines) - room))
            out: StyleAndTextTuples = []
            for k, line in enumerate(lines[self.scroll:self.scroll + room]):
                if k:
                    out.append(("", "\n"))
                out += line
            return out

        app: Application[None] = Application(
            layout=Layout(HSplit([
                # the rows left (a preferred height given: prompt_toolkit then does not
                # lay the whole view out once more to measure it)
                Window(FormattedTextControl(body), wrap_lines=False,
                       height=Dimension(weight=1, preferred=1)),
                Window(FormattedTextControl(lambda: [("class:message", self.message)]),
                       height=1),
                Window(BufferControl(out, input_processors=[]), height=1,
                       get_line_prefix=lambda n, w: [("bold", "> ")]),
            ]), focused_element=out),
            key_bindings=keys, full_screen=True, refresh_interval=REFRESH_S,
            mouse_support=False, input=self.pt_input, output=self.pt_output)
        return app

    async def _watch_end(self) -> None:
        """The screen ends when the run ended elsewhere."""
        import asyncio

        while self.ended is not None and not self.ended.is_set():
            await asyncio.sleep(REFRESH_S)
        if self._app is not None:
            self._app.exit()

    def run(self) -> None:
        """The loop's thread (:meth:`local`), then the screen until the user quits."""
        thread = None
        if self.cycle is not None:
            thread = threading.Thread(target=self.loop, name="ucom-loop", daemon=True)
            thread.start()  # first: the boards' watchdogs count from the start's last cycle
        try:
            app = self._app = self.application()

            def pre_run() -> None:
                if self.error is not None:  # the loop failed before the screen came up
                    app.exit()
                elif self.ended is not None:
                    app.create_background_task(self._watch_end())
            app.run(pre_run=pre_run)
        finally:
            self._stop.set()
            if thread is not None:
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
        except ValueError as err:
            self.message = f"! {err}"
            return False
        if parsed is None:
            return False
        future = self.source.write(parsed[0], parsed[1], "the live view", network=False)
        try:
            applied = future.result(timeout=WRITE_S)
        except TimeoutError:
            self.message = f"! no answer from the loop within {WRITE_S:g} s"
            return False
        self.message = (f"{applied.name} = {_text(applied.value)} {applied.unit}".rstrip()
                        if applied.ok else f"! {applied.message}")
        return False
