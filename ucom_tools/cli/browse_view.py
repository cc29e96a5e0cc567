"""The interactive view of ``ucom browse`` on a terminal, without the terminal: what it
shows (:class:`Model`), how (:func:`render`, a pure function of the model, the keys'
state and the time), and what the keys do (:class:`Keys`, a small state machine that
turns key names into :class:`Action` values).  :mod:`.browse_tty` runs them on a TTY.

The view is the robot as a tree: its buses, each board (where, prefix, program, state)
and the board's edges by kind (CI, SO, PAR), each with its latest value, unit and age
(how long ago the board's sample that carried it reached this host).
"""

from __future__ import annotations

import contextlib
import difflib
from dataclasses import dataclass, field
from decimal import Decimal, InvalidOperation
from typing import TYPE_CHECKING, Any

from rich.console import Group
from rich.text import Text

from ucom_tools.cli.ages import age_text

if TYPE_CHECKING:
    from ucom_tools.config.topology import BoardKey

KINDS = ("CI", "SO", "PAR")
MAX_FPS = 20.0
"""The view refreshes at the robot's publishing rate, at most this often (a terminal, or
a person, gains nothing from more)."""
HEADER_LINES, FOOTER_LINES = 1, 3
NAME_WIDTH, UNIT_WIDTH = 44, 16
HELP = "/ filter  s set  x stop  \u2191\u2193 PgUp PgDn scroll  q quit"


def value_of(text: str) -> int | float | str:
    """A value for the robot: a number where the text is one (exactly), else the text
    itself (``0x444``), which the robot reads as a local ``--set`` does."""
    try:
        return int(text, 10)
    except ValueError:
        pass
    try:
        d = Decimal(text)
    except InvalidOperation:
        return text
    f = float(d)
    return f if Decimal(repr(f)) == d else text


# ---------------------------------------------------------------------- the model
@dataclass
class Model:
    """What the view knows of the robot (filled by :mod:`.browse_tty` from the client's
    subscriptions; times are the browser's ``time.monotonic()``)."""

    endpoint: str
    structure: dict[str, Any] | None = None
    samples: dict[BoardKey, tuple[float, dict[str, Any]]] = field(default_factory=dict)
    """(bus, board) -> (when it came, the board's latest ``values`` document)."""
    running: dict[BoardKey, bool] = field(default_factory=dict)
    """-> whether its liveliness token is there."""
    stopped_by: dict[BoardKey, str] = field(default_factory=dict)
    """(bus, board) -> the Error that stopped its motors (its watchdog, say)."""
    status: dict[BoardKey, dict[str, Any]] = field(default_factory=dict)
    """(bus, board) -> its latest ``status`` document (LEDs, CAN error counters)."""
    lost_at: dict[BoardKey, float] = field(default_factory=dict)
    """(bus, board) -> when the first sample came that said it is lost (its values are
    stale until one says it is valid again)."""
    connection: str = "connecting"
    """``connected``, ``lost`` or ``connecting``."""
    since: float = 0.0
    """When :attr:`connection` last changed."""
    message: str = ""
    message_style: str = ""
    last_event: str = ""
    scroll: int = 0

    def connected(self, structure: dict[str, Any], now: float) -> None:
        """A (new) connection to the robot: its structure; what an earlier process of it
        published is forgotten."""
        self.structure = structure
        self.samples.clear()
        self.running.clear()
        self.stopped_by.clear()
        self.status.clear()
        self.lost_at.clear()
        self.connection, self.since = "connected", now

    def lost(self, now: float) -> None:
        if self.connection != "lost":
            self.connection, self.since = "lost", now
            self.running.clear()

    def sample(self, doc: dict[str, Any], now: float) -> None:
        with contextlib.suppress(KeyError, TypeError, ValueError):
            key = (str(doc["bus"]), int(doc["board"]))
            self.samples[key] = (now, doc)
            if doc.get("valid", True) is False:
                self.lost_at.setdefault(key, now)
            else:
                self.lost_at.pop(key, None)

    def board_lost(self, bus: str, board: int) -> dict[str, Any] | None:
        """What the board's latest sample says of its loss (since, seen), None: it is not
        lost."""
        got = self.samples.get((bus, board))
        if got is None or got[1].get("valid", True) is not False:
            return None
        lost = got[1].get("lost")
        return lost if isinstance(lost, dict) else {}

    def board_status(self, doc: dict[str, Any]) -> None:
        with contextlib.suppress(KeyError, TypeError, ValueError):
            self.status[(str(doc["bus"]), int(doc["board"]))] = doc

    def board(self, bus: str, board: int, running: bool) -> None:
        self.running[(bus, board)] = running
        if running:
            self.stopped_by.pop((bus, board), None)

    def event(self, doc: dict[str, Any]) -> None:
        """One of the run's events, shown in the footer; a board Error that stopped the
        motors marks the board."""
        kind = doc.get("kind")
        if kind == "board":
            where = doc.get("where") or f"{doc.get('bus')} board {doc.get('board')}"
            text = f"{where}: {doc.get('error')}" + (f" {doc['text']}" if doc.get("text")
                                                      else "")
            if doc.get("stopped_motors"):
                self.stopped_by[(str(doc.get("bus")), int(doc.get("board") or 0))] = str(
                    doc.get("error"))
                text += " (motors stopped)"
        elif kind in ("write", "stop"):
            what = f"set {doc.get('name')}={doc.get('value')}" if kind == "write" else "stop"
            text = f"{what} from {doc.get('origin')}: {doc.get('result')}"
        elif kind == "fault":
            where = doc.get("where") or f"{doc.get('bus')} board {doc.get('board')}"
            text = f"{where} {doc.get('event')}" + (f": {doc['seen']}" if doc.get("seen")
                                                    else "")
        elif kind == "state":
            text = f"the loop is {doc.get('state')}"
        else:
            return
        self.last_event = text

    def value(self, bus: str, board: int, unique: str, now: float,
              ) -> tuple[Any, float | None]:
        """The edge's latest value and its age (None, None: none yet): since its sample
        came, or where its board is lost since the board's last value (how long it was
        lost when this host heard of it, and since)."""
        got = self.samples.get((bus, board))
        if got is None:
            return None, None
        arrived, doc = got
        values = doc.get("values") or {}
        if unique not in values:
            return None, None
        lost = self.board_lost(bus, board)
        if lost is not None:
            heard = self.lost_at.get((bus, board), arrived)
            since, t = lost.get("since"), doc.get("t")
            before = max(0.0, float(since) - float(t)) if isinstance(
                since, int | float) and isinstance(t, int | float) else 0.0
            return values[unique], now - heard + before
        return values[unique], now - arrived


# ---------------------------------------------------------------------- the tree
@dataclass(frozen=True)
class Row:
    """One line of the tree: its guide (``├── ``) and what it shows."""

    guide: str
    kind: str
    """``bus``, ``board``, ``kind`` (a board's CI, SO or PAR) or ``edge``."""
    bus: dict[str, Any]
    board: dict[str, Any] | None = None
    edge: dict[str, Any] | None = None
    edge_kind: str = ""
    count: int = 0


def _matches(f: str, edge: dict[str, Any]) -> bool:
    return (f in str(edge.get("robot_name", "")).lower()
            or f in str(edge.get("qualified", "")).lower())


def tree_rows(structure: dict[str, Any] | None, filter_text: str = "") -> list[Row]:
    """The tree's lines, buses to edges; with a filter only the edges whose name holds it
    (case does not matter), and their boards (every edge of a board whose prefix or
    place holds it)."""
    if structure is None:
        return []
    f = filter_text.strip().lower()
    nodes: list[tuple[Row, list[Any]]] = []
    for bus in structure.get("buses", []):
        boards = []
        for b in bus.get("boards", []):
            whole = bool(f) and (f in str(b.get("prefix", "")).lower()
                                 or f in str(b.get("where", "")).lower())
            kinds: list[tuple[Row, list[Any]]] = []
            for kind in KINDS:
                edges = [e for e in b.get("edges", []) if e.get("kind") == kind
                         and (not f or whole or _matches(f, e))]
                if edges:
                    kinds.append((Row("", "kind", bus, b, edge_kind=kind, count=len(edges)),
                                  [(Row("", "edge", bus, b, e, kind), []) for e in edges]))
            if kinds or not f:
                boards.append((Row("", "board", bus, b), kinds))
        if boards or not f:
            nodes.append((Row("", "bus", bus), boards))
    out: list[Row] = []

    def walk(children: list[tuple[Row, list[Any]]], prefix: str) -> None:
        for i, (row, grand) in enumerate(children):
            last = i == len(children) - 1
            out.append(Row(prefix + ("\u2514\u2500\u2500 " if last else "\u251c\u2500\u2500 "),
                           row.kind, row.bus, row.board, row.edge, row.edge_kind, row.count))
            walk(grand, prefix + ("    " if last else "\u2502   "))
    walk(nodes, "")
    return out


def _state(model: Model, bus: str, board: int) -> Text:
    key = (bus, board)
    lost = model.board_lost(bus, board)
    if lost is not None and model.connection == "connected":
        seen = lost.get("seen")
        return Text("LOST" + (f": {seen}" if seen else ""), style="bold red")
    if key in model.stopped_by:
        return Text(f"stopped: {model.stopped_by[key]}", style="bold red")
    running = model.running.get(key)
    if model.connection != "connected":
        return Text("unknown", style="dim")
    if running:
        return Text("running", style="green")
    if running is None:
        return Text("starting", style="dim")
    return Text("stopped", style="yellow")


LED_STYLES = {"red": "bold red", "yellow": "bold yellow", "green": "bold green"}


def _leds(model: Model, bus: str, board: int) -> Text:
    """The board's LEDs as its last Status report said (● on, ◐ blinking, ○ off)."""
    doc = model.status.get((bus, board))
    t = Text()
    if doc is None or not isinstance(doc.get("leds"), dict):
        return t
    t.append("  ")
    for colour, style in LED_STYLES.items():
        shown = doc["leds"].get(colour)
        t.append({"on": "●", "blink": "◐"}.get(str(shown), "○"),
                 style=style if shown in ("on", "blink") else "dim")
    errors = (doc.get("tec") or 0, doc.get("rec") or 0)
    if any(errors):
        t.append(f" CAN errors tx {errors[0]} rx {errors[1]}", style="red")
    return t


def _line(model: Model, row: Row, now: float, name_width: int, unit_width: int) -> Text:
    t = Text(row.guide, style="dim", no_wrap=True, overflow="ellipsis")
    bus = row.bus
    if row.kind == "bus":
        rate = bus.get("bitrate")
        t.append(str(bus.get("name")), style="bold")
        if rate:
            t.append(f"  {rate / 1000:g} kbit/s", style="dim")
        return t
    b = row.board or {}
    if row.kind == "board":
        t.append(str(b.get("where")), style="bold")
        t.append(f" [{b.get('prefix')}]", style="cyan")
        if b.get("program"):
            t.append(f" {b.get('program')}", style="dim")
        t.append("  ")
        t.append_text(_state(model, str(bus.get("name")), int(b.get("board", 0))))
        t.append_text(_leds(model, str(bus.get("name")), int(b.get("board", 0))))
        got = model.samples.get((str(bus.get("name")), int(b.get("board", 0))))
        if got is not None and got[1].get("t") is not None:
            t.append(f"  t {got[1]['t']:.3f} s", style="dim")
        return t
    if row.kind == "kind":
        t.append(f"{row.edge_kind} ({row.count})", style="magenta")
        return t
    e = row.edge or {}
    value, age = model.value(str(bus.get("name")), int(b.get("board", 0)), str(e.get("name")),
                             now)
    name = str(e.get("robot_name") or e.get("name"))
    t.append(name.ljust(name_width), style="bold" if e.get("writable") else "")
    shown = "-" if value is None else str(value)
    lost = model.board_lost(str(bus.get("name")), int(b.get("board", 0))) is not None
    t.append(" " + shown.rjust(12), style="dim" if lost or value is None else "bold cyan")
    unit = str(e.get("unit") or "")
    t.append(" " + unit.ljust(unit_width))
    if age is not None:
        stale = lost or model.connection != "connected"
        t.append(age_text(age).rjust(8), style="red" if stale else "dim")
    return t


def _header(model: Model) -> Text:
    s = model.structure
    if s is None:
        return Text(f"connecting to {model.endpoint} ...", style="bold", no_wrap=True)
    t = Text(no_wrap=True, overflow="ellipsis")
    t.append(str(s.get("name", s.get("robot"))), style="bold")
    t.append(f" ({s.get('robot')}) on {s.get('host')}, pid {s.get('pid')}: ")
    t.append(f"{s.get('rate_hz', 0):g} Hz loop, values at {s.get('publish_hz', 0):g} Hz, ")
    t.append("writes allowed" if s.get("allow_writes") else "writes not allowed",
             style="green" if s.get("allow_writes") else "yellow")
    return t


def _connection(model: Model, now: float) -> Text:
    s = model.structure or {}
    if model.connection == "connected":
        return Text(f"connected to {s.get('robot')} on {model.endpoint}", style="green")
    if model.connection == "lost":
        return Text(f"connection lost {age_text(now - model.since)} ago: reconnecting to "
                    f"{model.endpoint}", style="bold red")
    return Text(f"connecting to {model.endpoint}", style="yellow")


def _prompt(model: Model, keys: Keys) -> tuple[Text, Text]:
    """The footer's first two lines: the prompt (or the latest message) and a hint (or
    the latest event)."""
    cursor = Text("\u2588", style="blink")
    if keys.mode == "filter":
        first = Text("filter: ", style="bold") + Text(keys.text) + cursor
    elif keys.mode == "name":
        first = Text("set (name, Tab completes): ", style="bold") + Text(keys.text) + cursor
    elif keys.mode == "value":
        first = (Text(f"set {keys.name} ", style="bold") + Text(f"({keys.about})", style="dim")
                 + Text(" = ", style="bold") + Text(keys.text) + cursor)
    elif keys.mode == "stop":
        first = Text("stop every board (motors off) and the robot's loop? y/N ",
                     style="bold red") + cursor
    else:
        first = Text(model.message, style=model.message_style)
    second = (Text(keys.hint, style="yellow") if keys.hint
              else Text(model.last_event, style="dim") if model.last_event
              else Text(f"filter: {keys.filter}", style="dim") if keys.filter else Text(""))
    for t in (first, second):
        t.no_wrap, t.overflow = True, "ellipsis"
    return first, second


def render(model: Model, keys: Keys, now: float, height: int) -> Group:
    """The screen, ``height`` lines: a header (the robot), as much of the tree as fits
    from ``model.scroll`` on (clamped there), and the footer (prompt or message, a hint or
    the latest event, the connection and the keys)."""
    rows = tree_rows(model.structure, keys.filter)
    body = max(1, height - HEADER_LINES - FOOTER_LINES)
    model.scroll = max(0, min(model.scroll, len(rows) - body))
    window = rows[model.scroll:model.scroll + body]
    edges = [r.edge for r in window if r.edge is not None]
    width = min(NAME_WIDTH, max([len(str(e.get("robot_name", ""))) for e in edges] or [0]))
    units = min(UNIT_WIDTH, max([len(str(e.get("unit") or "")) for e in edges] or [0]))
    lines: list[Text] = [_header(model)]
    lines += [_line(model, r, now, width, units) for r in window]
    if not rows:
        lines.append(Text(f"no edge is called like {keys.filter!r}" if keys.filter
                          and model.structure else "", style="dim"))
    lines += [Text("")] * (HEADER_LINES + body - len(lines))
    first, second = _prompt(model, keys)
    status = _connection(model, now)
    shown = f"  {model.scroll + 1}-{model.scroll + len(window)} of {len(rows)}" if rows else ""
    status.append(shown, style="dim")
    status.append("   " + HELP, style="dim")
    status.no_wrap, status.overflow = True, "ellipsis"
    return Group(*lines, first, second, status)


# ---------------------------------------------------------------------- the keys
@dataclass(frozen=True)
class Action:
    """What a key asks of the application: ``quit``, ``set`` (name, value), ``stop``,
    ``scroll`` (n lines), ``page`` (n pages), ``top``, ``bottom``."""

    kind: str
    name: str = ""
    value: str = ""
    n: int = 0


class Catalog:
    """The robot's CI and PAR edges by their robot-wide names, for the set prompt: Tab
    completion and a name's check (the robot checks the write again)."""

    def __init__(self, structure: dict[str, Any] | None) -> None:
        self.writable: dict[str, dict[str, Any]] = {}
        self._by: dict[str, tuple[str, dict[str, Any]]] = {}
        for bus in (structure or {}).get("buses", []):
            for b in bus.get("boards", []):
                for e in b.get("edges", []):
                    name = str(e.get("robot_name") or e.get("qualified"))
                    if e.get("kind") in ("CI", "PAR"):
                        self.writable[name] = e
                    for n in {name, str(e.get("qualified", name))}:
                        self._by[n.lower()] = (name, e)

    @property
    def names(self) -> list[str]:
        return list(self.writable)

    def complete(self, text: str) -> tuple[str, list[str]]:
        """``text`` completed as far as it goes (the names that start with it, else those
        that hold it; case does not matter) and the names it could still be."""
        t = text.lower()
        cands = [n for n in self.writable if n.lower().startswith(t)]
        if cands:
            common = _common_prefix([c.lower() for c in cands])
            return (cands[0][:len(common)] if len(common) > len(text) else text), cands
        cands = [n for n in self.writable if t in n.lower()]
        return (cands[0] if len(cands) == 1 else text), cands

    def lookup(self, text: str) -> tuple[str, str]:
        """(the name, what it is: kind and range) of the CI or PAR called ``text``;
        ValueError with the closest names otherwise."""
        name = text.strip()
        got = self._by.get(name.lower())
        if got is not None and got[0] in self.writable:
            e = got[1]
            return got[0], f"{e.get('kind')}, {e.get('range') or 'no range'}"
        if got is not None:
            raise ValueError(f"{got[0]} is an {got[1].get('kind')}: read only")
        close = difflib.get_close_matches(name, self.names, n=3, cutoff=0.5) or [
            n for n in self.names if name.lower() in n.lower()][:3]
        raise ValueError(f"no CI or PAR is called {name!r}"
                         + (f"; closest: {', '.join(close)}" if close else ""))


def _common_prefix(texts: list[str]) -> str:
    first, last = min(texts), max(texts)
    n = 0
    while n < min(len(first), len(last)) and first[n] == last[n]:
        n += 1
    return first[:n]


def _printable(key: str) -> bool:
    return len(key) == 1 and key.isprintable()


class Keys:
    """The keys' state machine.  ``mode``: ``view`` (the tree: scroll, or start one of the
    prompts), ``filter`` (the filter applies as it is typed), ``name`` and ``value`` (the
    set prompt), ``stop`` (the stop's confirmation).  :meth:`feed` takes one key name
    (:func:`~ucom_tools.cli.browse_tty.split_keys`) and answers the actions for the application."""

    def __init__(self, catalog: Catalog | None = None) -> None:
        self.catalog = catalog or Catalog(None)
        self.mode = "view"
        self.text = ""
        self.name = ""
        self.about = ""
        self.hint = ""
        self.filter = ""

    def _edit(self, key: str) -> bool:
        if key == "backspace":
            self.text = self.text[:-1]
        elif key == "ctrl-u":
            self.text = ""
        elif _printable(key):
            self.text += key
        else:
            return False
        return True

    def _view(self, key: str) -> list[Action]:
        self.hint = ""
        moves = {"up": Action("scroll", n=-1), "k": Action("scroll", n=-1),
                 "down": Action("scroll", n=1), "j": Action("scroll", n=1),
                 "pgup": Action("page", n=-1), "pgdn": Action("page", n=1),
                 " ": Action("page", n=1), "home": Action("top"), "g": Action("top"),
                 "end": Action("bottom"), "G": Action("bottom")}
        if key == "q":
            return [Action("quit")]
        if key in moves:
            return [moves[key]]
        if key == "/":
            self.mode, self.text = "filter", self.filter
        elif key == "s":
            self.mode, self.text = "name", ""
        elif key == "x":
            self.mode = "stop"
        elif key == "esc" and self.filter:
            self.filter = ""
            return [Action("top")]
        return []

    def feed(self, key: str) -> list[Action]:
        if self.mode == "view":
            return self._view(key)
        if key == "esc":
            was = self.mode
            if was == "filter":
                self.filter = ""
            self.mode, self.text, self.hint = "view", "", ""
            return [Action("top")] if was == "filter" else []
        if self.mode == "stop":
            self.mode = "view"
            return [Action("stop")] if key in ("y", "Y") else []
        if self.mode == "filter":
            if key == "enter":
                self.mode, self.text = "view", ""
                return []
            if self._edit(key):
                self.filter = self.text
                return [Action("top")]
            return []
        if self.mode == "name":
            return self._name(key)
        return self._value(key)

    def _name(self, key: str) -> list[Action]:
        self.hint = ""
        if key == "tab":
            name, _, value = self.text.partition("=")
            if not value:
                done, cands = self.catalog.complete(name.strip())
                self.text = done
                if not cands:
                    self.hint = f"no CI or PAR is called like {name.strip()!r}"
                elif len(cands) > 1:
                    shown = ", ".join(cands[:8]) + (", ..." if len(cands) > 8 else "")
                    self.hint = f"{len(cands)} names: {shown}"
            return []
        if key == "enter":
            name, sep, value = self.text.partition("=")
            try:
                self.name, self.about = self.catalog.lookup(name)
            except ValueError as err:
                self.hint = str(err)
                return []
            if sep and value.strip():
                self.mode, self.text = "view", ""
                return [Action("set", self.name, value.strip())]
            self.mode, self.text = "value", ""
            return []
        self._edit(key)
        return []

    def _value(self, key: str) -> list[Action]:
        self.hint = ""
        if key == "enter":
            if not self.text.strip():
                self.hint = "a value, please (Esc: no set)"
                return []
            value, self.mode, self.text = self.text.strip(), "view", ""
            return [Action("set", self.name, value)]
        self._edit(key)
        return []


def window_lines(height: int) -> int:
    """How many lines of the tree fit on a screen of ``height`` lines."""
    return max(1, height - HEADER_LINES - FOOTER_LINES)
