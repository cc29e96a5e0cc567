"""The journal of a deploy: a directory (``journal.json`` and ``params/``) recording the
plan, each board's progress and the parameter dumps, every change written atomically,
so that a deploy killed at any point is resumed by the next (``ucom(1)``, FILES)."""

from __future__ import annotations

import contextlib
import json
import os
import re
import threading
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ucom_tools import fileio
from ucom_tools.errors import InputError

JOURNAL_FILE = "journal.json"
PARAMS_DIR = "params"
JOURNAL_VERSION = 1

# ----------------------------------------------------------------------------- journal
def default_journal(robot_name: str, environ: Mapping[str, str] | None = None) -> Path:
    """``$XDG_STATE_HOME/ucom/deploy/<robot>``, else ``~/.local/state/ucom/deploy/<robot>``
    (``<robot>`` the topology's name, made a safe file name)."""
    env = os.environ if environ is None else environ
    base = Path(env["XDG_STATE_HOME"]) if env.get("XDG_STATE_HOME") else \
        Path(env.get("HOME") or Path.home()) / ".local" / "state"
    return base / "ucom" / "deploy" / safe_name(robot_name)


def safe_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("._") or "robot"


@dataclass
class Journal:
    """An unfinished deploy: per board (``BUS:position``) its serial, image, ProgID, stage
    (planned, dumped, programming, verified, failed, restored, done) and the file of its
    saved parameters.  Every :meth:`save` replaces ``journal.json`` atomically, together
    with the parameter files it brings."""

    directory: Path
    robot: str
    boards: dict[str, dict[str, Any]] = field(default_factory=dict)
    resumed: bool = False
    """It was found on disk: a deploy before this one did not finish."""
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    @property
    def path(self) -> Path:
        return self.directory / JOURNAL_FILE

    @classmethod
    def open(cls, directory: Path, robot: str) -> Journal:
        """The journal in ``directory`` (resumed), or a new, unsaved one.  InputError
        (exit 3) for a journal that cannot be read or is not one."""
        path = directory / JOURNAL_FILE
        if not path.exists():
            return cls(directory, robot)
        data = fileio.read_input(path, limit=fileio.TEXT_LIMIT, what="a deploy journal",
                                 key="journal")
        try:
            doc = json.loads(data)
            if doc.get("version") != JOURNAL_VERSION or not isinstance(doc.get("boards"), dict):
                raise ValueError("not a deploy journal of this version")
        except (ValueError, AttributeError) as err:
            raise InputError(f"{path}: {err}; remove it to start afresh",
                             key="journal") from None
        if doc.get("robot") != robot:
            raise InputError(f"{path} is the journal of {doc.get('robot')!r}, not of "
                             f"{robot!r}; give another journal directory", key="journal")
        return cls(directory, robot, doc["boards"], resumed=True)

    def entry(self, key: str, serial: int | None) -> dict[str, Any] | None:
        """The record of board ``key``, if it is that board (same serial)."""
        e = self.boards.get(key)
        if e is None or (serial is not None and e.get("serial") not in (None, serial)):
            return None
        return e

    def update(self, key: str, **values: Any) -> None:
        with self._lock:
            self.boards.setdefault(key, {}).update(values)

    def save(self, files: Mapping[str, str] | None = None) -> None:
        """Write ``journal.json`` (and ``files``, names relative to the directory, e.g.
        ``params/CAN0-1.tree``): all or none."""
        with self._lock:
            fileio.prepare_directory(self.directory, key="journal")
            if files:
                fileio.prepare_directory(self.directory / PARAMS_DIR, key="journal")
            doc = {"version": JOURNAL_VERSION, "robot": self.robot, "boards": self.boards}
            with fileio.Batch(key="journal") as batch:
                for name, text in (files or {}).items():
                    batch.write_text(self.directory / name, text)
                batch.write_text(self.path, json.dumps(doc, indent=1, sort_keys=True) + "\n")

    def remove(self) -> None:
        """Remove what the journal wrote (its file, the parameter files) and its
        directories when they are empty."""
        params = self.directory / PARAMS_DIR
        for e in self.boards.values():
            if e.get("params"):
                with contextlib.suppress(OSError):
                    (self.directory / e["params"]).unlink()
        with contextlib.suppress(OSError):
            self.path.unlink()
        for d in (params, self.directory):
            # what a job killed while it wrote left: the temporaries of fileio's atomic
            # writes (".journal_json-XXXX.tmp", ".CAN0-1-XXXX.tree"), in the journal's
            # own directories, which nothing else writes
            with contextlib.suppress(OSError):
                for tmp in d.glob(".*-*"):
                    if tmp.is_file():
                        tmp.unlink()
            with contextlib.suppress(OSError):
                d.rmdir()
        self.boards = {}


