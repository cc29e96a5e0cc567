"""``ucom browse`` on a terminal: the robot's tree, live (:mod:`.browse_view` draws it and
says what the keys do; this module owns the terminal, whose bytes it turns into keys'
names (:func:`split_keys`), and the connection).

The terminal is put in cbreak mode (keys come one by one, not echoed) and the alternate
screen; both are restored on every way out: ``q``, Ctrl-C, SIGTERM and SIGHUP (raised as
:class:`~ucom_tools.signals.Terminated` by ``ucom``'s :func:`~ucom_tools.signals.
stop_signals`), an error.  The connection lives in a thread of its own
(:class:`RobotLink`): when the robot's liveliness token goes, the view says "connection lost"
and the thread connects again until the robot (the same robot name, on the same
endpoint) is back.
"""

from __future__ import annotations

import codecs
import contextlib
import os
import queue
import selectors
import sys
import termios
import threading
import time
import tty
from collections.abc import Callable
from typing import Any

from rich.console import Console
from rich.live import Live

from ucom_tools.cli.browse_view import (
    MAX_FPS,
    Action,
    Catalog,
    Keys,
    Model,
    render,
    value_of,
    window_lines,
)
from ucom_tools.errors import InputError, UcomError
from ucom_tools.net.client import RobotClient, Subscription, WritesForbidden

RETRY_S = 0.2
"""Pause between two attempts to reach a robot that is gone (each attempt waits up to
the connect timeout itself)."""

Inbox = queue.SimpleQueue[tuple[Any, ...]]


_CSI = {"A": "up", "B": "down", "C": "right", "D": "left", "H": "home", "F": "end",
        "1~": "home", "7~": "home", "4~": "end", "8~": "end", "5~": "pgup", "6~": "pgdn",
        "3~": "delete", "Z": "backtab"}
_CONTROL = {"\r": "enter", "\n": "enter", "\t": "tab", "\x7f": "backspace",
            "\x08": "backspace", "\x15": "ctrl-u"}


def split_keys(data: str) -> list[str]:
    """Keys' names from what a terminal in cbreak mode sent: characters as they are,
    ``enter``, ``tab``, ``backspace``, ``esc``, ``ctrl-u``, ``up``, ``down``, ``pgup``,
    ``pgdn``, ``home``, ``end`` (xterm's and VT100's escape sequences; others ``?``)."""
    out: list[str] = []
    i = 0
    while i < len(data):
        c = data[i]
        if c == "\x1b" and data[i + 1:i + 2] == "[":
            j = i + 2
            while j < len(data) and "\x20" <= data[j] <= "\x3f":
                j += 1  # parameters (and intermediates): 5~, 1;5A
            params, final = data[i + 2:j], data[j:j + 1]
            out.append(_CSI.get(params + "~" if final == "~" else final, "?"))
            i = j + 1
            continue
        if c == "\x1b" and data[i + 1:i + 2] == "O" and i + 2 < len(data):
            out.append(_CSI.get(data[i + 2], "?"))
            i += 3
            continue
        if c == "\x1b":
            out.append("esc")
        elif c == "\n" and i > 0 and data[i - 1] == "\r":
            pass  # CR LF: one Enter
        elif c in _CONTROL:
            out.append(_CONTROL[c])
        elif c.isprintable():
            out.append(c)
        i += 1
    return out



def interactive(*streams: Any) -> bool:
    """Whether ``streams`` (standard input and output) are all terminals."""
    try:
        return all(s.isatty() for s in streams)
    except (AttributeError, ValueError):
        return False


class RobotLink:
    """The connection to the robot, in a thread: posts ``("connected", gen, client)``,
    ``("values", gen, doc, t)``, ``("board", gen, bus, board, running)``, ``("event",
    gen, doc)`` and ``("lost", gen)`` to ``inbox``; ``gen`` counts the connections, so
    that what an old one still delivers is dropped."""

    def __init__(self, first: RobotClient, connect: Callable[[], RobotClient],
                 inbox: Inbox) -> None:
        self._client: RobotClient | None = first
        self._connect = connect
        self._inbox = inbox
        self._stop = threading.Event()
        self._wake = threading.Event()
        # not a daemon: the interpreter waits for it at exit, so the session's close is
        # over before Python finalizes (a daemon thread still inside Zenoh's close then
        # is cut off by a forced unwind through the Rust runtime: SIGABRT, "FATAL:
        # exception not rethrown", seen after SIGTERM); close() stops it within one
        # connection attempt
        self._thread = threading.Thread(target=self._run, name="ucom-browse-link")

    def start(self) -> None:
        self._thread.start()

    def close(self, timeout: float = 5.0) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout)

    def _watch(self, client: RobotClient, gen: int) -> list[Subscription]:
        post, now = self._inbox.put, time.monotonic
        subs = [client.on_values(lambda d: post(("values", gen, d, now()))),
                client.on_boards(lambda b, n, up: post(("board", gen, b, n, up))),
                client.on_events(lambda d: post(("event", gen, d))),
                client.on_status(lambda d: post(("status", gen, d))),
                client.on_gone(self._wake.set)]
        if not client.alive():  # gone before the subscription was there
            self._wake.set()
        return subs

    def _run(self) -> None:
        gen = 0
        client = self._client
        try:
            while client is not None and not self._stop.is_set():
                gen += 1
                self._wake.clear()
                self._inbox.put(("connected", gen, client))
                try:
                    subs = self._watch(client, gen)
                except Exception:  # the session broke meanwhile: as gone, connect again
                    subs = []
                    self._wake.set()
                self._wake.wait()
                self._inbox.put(("lost", gen))
                for s in subs:
                    with contextlib.suppress(Exception):
                        s.close()
                with contextlib.suppress(Exception):
                    client.close()
                client = self._client = None
                while not self._stop.is_set():
                    try:
                        client = self._client = self._connect()
                        break
                    except UcomError:
                        self._stop.wait(RETRY_S)
        finally:
            if client is not None:
                with contextlib.suppress(Exception):
                    client.close()


class App:
    """The view on a terminal: :meth:`run` until ``q``."""

    def __init__(self, client: RobotClient, connect: Callable[[], RobotClient],
                 timeout: float, console: Console | None = None) -> None:
        self.inbox: Inbox = queue.SimpleQueue()
        self.link = RobotLink(client, connect, self.inbox)
        self.model = Model(client.where)
        self.keys = Keys()
        self.timeout = timeout
        self.gen = 0
        self.client: RobotClient | None = None
        self.console = console or Console(highlight=False, emoji=False)
        self.interval = 1.0 / MAX_FPS

    # ------------------------------------------------------------------ what comes in
    def _take(self, item: tuple[Any, ...]) -> bool:
        """Apply one posted item; whether the screen must be drawn now."""
        kind, gen = item[0], item[1]
        now = time.monotonic()
        if kind == "connected":
            self.gen, self.client = gen, item[2]
            s = item[2].structure
            self.model.connected(s, now)
            self.keys.catalog = Catalog(s)
            self.interval = 1.0 / max(1.0, min(float(s.get("publish_hz") or MAX_FPS),
                                               MAX_FPS))
            return True
        if gen != self.gen:
            return False  # from a connection that is gone
        if kind == "values":
            self.model.sample(item[2], item[3])
            return False
        if kind == "board":
            self.model.board(item[2], item[3], item[4])
        elif kind == "status":
            self.model.board_status(item[2])
        elif kind == "event":
            self.model.event(item[2])
        elif kind == "lost":
            self.model.lost(now)
            self.client = None
        elif kind == "answer":
            self.model.message, self.model.message_style = item[2], item[3]
        return True

    # ------------------------------------------------------------------ what goes out
    def _ask(self, what: str, action: Action) -> None:
        client = self.client
        if client is None:
            self.model.message = "not connected: nothing sent"
            self.model.message_style = "red"
            return
        gen, post = self.gen, self.inbox.put
        if what == "set":
            self.model.message = f"setting {action.name} = {action.value} ..."
        else:
            self.model.message = "stopping the boards ..."
        self.model.message_style = ""

        def ask() -> None:
            try:
                if what == "set":
                    a = client.write(action.name, value_of(action.value),
                                     timeout=self.timeout)
                    unit = f" {a['unit']}" if a.get("unit") else ""
                    text, style = f"{a.get('name')} = {a.get('value')}{unit}: done", "green"
                else:
                    client.stop(timeout=self.timeout)
                    text, style = "stopping every board: the robot's loop ends", "yellow"
            except WritesForbidden as err:
                text, style = f"not allowed: {err}", "bold red"
            except InputError as err:
                text, style = f"refused: {err}", "bold red"
            except Exception as err:  # the session closed meanwhile, no answer, ...
                text, style = f"failed: {err}", "bold red"
            post(("answer", gen, text, style))
        threading.Thread(target=ask, name=f"ucom-browse-{what}", daemon=True).start()

    def _act(self, action: Action, height: int) -> bool:
        """Do what a key asked; False to quit."""
        page = window_lines(height)
        if action.kind == "quit":
            return False
        if action.kind == "scroll":
            self.model.scroll = max(0, self.model.scroll + action.n)
        elif action.kind == "page":
            self.model.scroll = max(0, self.model.scroll + action.n * (page - 1))
        elif action.kind == "top":
            self.model.scroll = 0
        elif action.kind == "bottom":
            self.model.scroll = 1 << 30  # clamped by render
        elif action.kind in ("set", "stop"):
            self._ask(action.kind, action)
        return True

    # ------------------------------------------------------------------ the loop
    def run(self) -> None:
        fd = sys.stdin.fileno()
        saved = termios.tcgetattr(fd)
        decoder = codecs.getincrementaldecoder("utf-8")(errors="replace")
        self.link.start()
        try:
            tty.setcbreak(fd)
            with selectors.DefaultSelector() as sel, Live(
                    console=self.console, screen=True, auto_refresh=False,
                    redirect_stdout=False, redirect_stderr=False) as live:
                sel.register(fd, selectors.EVENT_READ)
                self._loop(fd, sel, live, decoder)
        finally:
            termios.tcsetattr(fd, termios.TCSADRAIN, saved)
            self.link.close()

    def _loop(self, fd: int, sel: selectors.BaseSelector, live: Live,
              decoder: codecs.IncrementalDecoder) -> None:
        next_at = 0.0
        while True:
            height = self.console.size.height
            draw = False
            for _ in sel.select(max(0.0, next_at - time.monotonic())):
                data = os.read(fd, 1024)
                if not data:
                    return  # the terminal is gone
                for key in split_keys(decoder.decode(data)):
                    for action in self.keys.feed(key):
                        if not self._act(action, height):
                            return
                draw = True
            while True:
                try:
                    draw = self._take(self.inbox.get_nowait()) or draw
                except queue.Empty:
                    break
            now = time.monotonic()
            if draw or now >= next_at:
                live.update(render(self.model, self.keys, now, height), refresh=True)
                next_at = now + self.interval


def run(client: RobotClient, connect: Callable[[], RobotClient], timeout: float) -> None:
    """The view of ``client``'s robot until ``q``; ``connect()`` reaches it again after it
    was gone."""
    App(client, connect, timeout).run()
