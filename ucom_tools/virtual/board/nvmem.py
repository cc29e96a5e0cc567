"""Non-volatile memory of a virtual UCoM: program flash, data flash and the bootloader
record (AutoStart flag, program validity, ProgID, name, date), persistable to a directory
so that a fleet keeps its boards' flash across restarts like power cycles.
"""

from __future__ import annotations

import json
from array import array
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Final

from ucom_tools import fileio
from ucom_tools.errors import InputError, UcomError
from ucom_tools.memory import P_FLASH_END, PAGE_WORDS, X_FLASH_END, X_FLASH_START
from ucom_tools.wire.codes import Space
from ucom_tools.wire.transfer import TransferPlan, encode_date

BOOT_VECTORS: Final = (0xE984, 0x8000, 0xE984, 0x8000)
"""P:0000-0003 as the bootloader keeps them: JMP 0x8000 (reset) and JMP 0x8000 (COP)."""
P_WORDS: Final = P_FLASH_END + 1
X_WORDS: Final = X_FLASH_END - X_FLASH_START + 1


@dataclass
class BootRecord:
    """The bootloader's record in the last data-flash page (X:1F00-1FFF)."""

    autostart: bool = False
    flash_valid: bool = False
    progid: int = 0
    size_words: int = 0
    date: int = 0  # seconds since 2000-01-01 UTC; 0 = never programmed
    name: str = ""
    entry: int = 0


class Memory:
    """Word-addressed P: or X: memory with flash semantics (program can only clear bits)."""

    def __init__(self, base: int, words: int) -> None:
        self.base = base
        self.words = array("H", [0xFFFF]) * words

    def erase_page(self, page: int) -> None:
        start = page * PAGE_WORDS - self.base
        self.words[start:start + PAGE_WORDS] = array("H", [0xFFFF]) * PAGE_WORDS

    def program(self, address: int, values: array) -> bool:
        """Program words; False if a word did not take (it was not erased)."""
        start = address - self.base
        old = self.words[start:start + len(values)]
        ok = True
        if old.count(0xFFFF) != len(old):
            merged = array("H", (o & v for o, v in zip(old, values, strict=True)))
            ok = merged == values
            values = merged
        self.words[start:start + len(values)] = values
        return ok

    def write(self, address: int, values: array) -> None:
        """Store words as RAM does (no flash semantics)."""
        start = address - self.base
        self.words[start:start + len(values)] = values

    def read(self, address: int, count: int) -> array:
        start = address - self.base
        return self.words[start:start + count]


@dataclass
class ExtRamProgram:
    """A program loaded into external RAM (volatile: gone after reset or power loss)."""

    memory: dict[Space, Memory]
    progid: int
    size_words: int
    name: str
    entry: int
    date: int


def external_ram() -> dict[Space, Memory]:
    """Empty external RAM for an ExtRAM program, mapped like flash (P: and X:)."""
    return {Space.P: Memory(0, P_WORDS), Space.X: Memory(X_FLASH_START, X_WORDS)}


class NonVolatile:
    """Flash and bootloader record of one board."""

    def __init__(self) -> None:
        self.p = Memory(0, P_WORDS)
        self.x = Memory(X_FLASH_START, X_WORDS)
        self.p.words[0:4] = array("H", BOOT_VECTORS)
        self.record = BootRecord()
        self.save_failure: str | None = None
        """Why the last save failed (the files on disk then hold the state before it)."""

    def space(self, space: Space) -> Memory:
        return self.p if space is Space.P else self.x

    def erase_page(self, space: Space, page: int) -> None:
        self.space(space).erase_page(page)
        if space is Space.P and page == 0:
            self.p.words[0:4] = array("H", BOOT_VECTORS)

    def install(self, plan: TransferPlan) -> None:
        """Store a whole image at once, as a completed, verified transfer would."""
        for space, page in sorted({(b.space, b.page) for b in plan.blocks}):
            self.erase_page(space, page)
        for b in plan.blocks:
            self.space(b.space).program(b.address, array("H", b.words))
        rec = self.record
        rec.flash_valid = True
        rec.progid, rec.size_words, rec.date = plan.progid, plan.size_words, encode_date(plan.when)
        rec.name, rec.entry = plan.name, plan.entry

    # ------------------------------------------------------------------ persistence
    def save(self, path: Path) -> None:
        """Write ``path.flash`` and ``path.json``, both or neither (``ucom(1)``, FILES):
        when the disk is full the previous pair stays as it was and :attr:`save_failure`
        says why (the board goes on with what it has in memory, as a board whose flash
        write failed would report it; the CLI names it at the end)."""
        self._save(path, flash=True)

    def save_record(self, path: Path) -> None:
        """Write ``path.json`` alone (the bootloader record changed, the flash did not)."""
        self._save(path, flash=False)

    def _save(self, path: Path, *, flash: bool) -> None:
        try:
            with fileio.Batch(key="state_dir") as batch:
                if flash:
                    batch.write_bytes(path.with_suffix(".flash"),
                                      self.p.words.tobytes() + self.x.words.tobytes())
                batch.write_text(path.with_suffix(".json"),
                                 json.dumps(asdict(self.record), indent=1))
        except UcomError as err:  # InputError (the directory went away) or WriteError
            self.save_failure = str(err)
        else:
            self.save_failure = None

    def load(self, path: Path) -> bool:
        """Read what :meth:`save` wrote; False if nothing was stored yet.

        A file that cannot be read or is not what :meth:`save` writes raises
        :class:`~ucom_tools.errors.InputError` naming it (a power cycle never quietly
        loses or invents a board's program)."""
        flash = path.with_suffix(".flash")
        rec = path.with_suffix(".json")
        found = False
        if flash.exists():
            raw = _read(flash)
            size = 2 * (P_WORDS + X_WORDS)
            if len(raw) != size:
                raise InputError(f"not a board's flash image: {len(raw)} bytes, expected {size}; "
                                 "delete it to start with erased flash", file=str(flash))
            self.p.words = array("H")
            self.p.words.frombytes(raw[:2 * P_WORDS])
            self.x.words = array("H")
            self.x.words.frombytes(raw[2 * P_WORDS:])
            found = True
        if rec.exists():
            self.record = _record(rec)
            found = True
        return found


def _read(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as err:
        raise InputError(f"cannot read: {err.strerror or err}", file=str(path)) from None


def _record(path: Path) -> BootRecord:
    """The bootloader record saved in ``path``, every field checked."""
    try:
        data = json.loads(_read(path).decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        line = getattr(err, "lineno", None)
        raise InputError(f"not a bootloader record (corrupt JSON: {err}); delete it to start "
                         "with an empty board", file=str(path), line=line) from None
    if not isinstance(data, dict):
        raise InputError("not a bootloader record (expected a JSON object)", file=str(path))
    fields = asdict(BootRecord())
    values = {}
    for key, default in fields.items():
        if key not in data:
            continue
        value = data[key]
        if type(value) is not type(default):
            raise InputError(f"expected {type(default).__name__}, got {value!r}",
                             file=str(path), key=key)
        values[key] = value
    return BootRecord(**values)
