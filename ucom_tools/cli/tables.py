"""Tables that fit the terminal without breaking a word.

:class:`FitTable` is built like a rich ``Table`` (``add_column``, ``add_row``) and laid out
when it is printed, for the width it gets:

- a column whose every cell is empty (or ``-``) is left out;
- when the columns do not fit side by side with each word whole (a hex number, a state,
  a placement's words), the secondary columns are left out, the least important first,
  and a caption names them (``--json`` has every field);
- the columns left get the widths they need and wrap at spaces: no word, serial or ProgID
  is cut in two.  Only when even the primary columns' longest words do not fit does rich
  fold the cells (a path longer than the terminal).

A piped output has no width limit (:mod:`ucom_tools.cli.output`): there a table only
loses its empty columns.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rich.console import Console, ConsoleOptions, RenderableType, RenderResult
from rich.measure import Measurement
from rich.padding import Padding
from rich.table import Table
from rich.text import Text

EMPTY = ("", "-")
"""Cell texts that say nothing: a column of only these is left out."""


@dataclass(frozen=True)
class _Column:
    header: str
    drop: int
    """0: never left out; 1, 2, ...: left out in this order when the table is too wide."""
    keep: bool
    """Shown even when every cell is empty."""
    options: dict[str, Any]


class FitTable:
    """A rich table laid out for the width it is printed at (module docstring)."""

    def __init__(self, title: str | None = None, **table_options: Any) -> None:
        self.title = title
        self.table_options = {"title_justify": "left", **table_options}
        self.columns: list[_Column] = []
        self.rows: list[tuple[RenderableType, ...]] = []
        self.row_options: list[dict[str, Any]] = []

    def add_column(self, header: str, *, drop: int = 0, keep: bool = False,
                   **options: Any) -> None:
        """A column; ``drop`` > 0 makes it secondary (see :class:`_Column`), ``keep``
        shows it even when empty; ``options`` are rich's (``justify``, ``no_wrap``...)."""
        self.columns.append(_Column(header, drop, keep, options))

    def add_row(self, *cells: RenderableType, **options: Any) -> None:
        """A row; ``options`` are rich's (``end_section``, ``style``)."""
        self.rows.append(tuple(cells))
        self.row_options.append(options)

    # ------------------------------------------------------------------ layout
    def __rich_console__(self, console: Console, options: ConsoleOptions) -> RenderResult:
        yield self.fitted(console, options.max_width)

    def fitted(self, console: Console, width: int) -> Table:
        """The rich table for ``width`` columns (the module docstring says how)."""
        shown = [i for i, c in enumerate(self.columns)
                 if c.keep or not self.rows or not all(_empty(r[i]) for r in self.rows)]
        sizes = {i: self._measure(console, i) for i in shown}
        by_drop = sorted((c.drop, -i) for i, c in enumerate(self.columns) if c.drop)
        while self._chrome(len(shown)) + sum(sizes[i][0] for i in shown) > width and by_drop:
            _, neg = by_drop.pop(0)  # drop 1 goes first
            if -neg in shown:
                shown.remove(-neg)
        dropped = [c.header for i, c in enumerate(self.columns)
                   if i not in shown and i in sizes]
        widths = _share(width - self._chrome(len(shown)), [sizes[i] for i in shown])
        options = {"caption_justify": "left", **self.table_options}
        if dropped:
            note = (f"[dim]left out at {width} columns: {', '.join(dropped)} (--json has "
                    "every field)[/]")
            options["caption"] = "\n".join(filter(None, (options.get("caption"), note)))
        table = Table(title=self.title, **options)
        for i, w in zip(shown, widths, strict=True):
            col = self.columns[i]
            table.add_column(col.header, **{"overflow": "fold", **col.options,
                                            **({"width": w} if w is not None else {})})
        for row, row_options in zip(self.rows, self.row_options, strict=True):
            table.add_row(*(row[i] for i in shown), **row_options)
        return table

    def _chrome(self, columns: int) -> int:
        """What the table takes besides its cells' text: padding and lines."""
        opts = self.table_options
        _, right, _, left = Padding.unpack(opts.get("padding", (0, 1)))
        pads = (left + right) * columns
        if not opts.get("pad_edge", True):
            pads -= left + right
        lines = 0
        if opts.get("box", True) is not None:
            lines = columns - 1 + (2 if opts.get("show_edge", True) else 0)
        return pads + lines

    def _measure(self, console: Console, i: int) -> tuple[int, int]:
        """(longest word, longest line) of column ``i``, its header included."""
        no_wrap = bool(self.columns[i].options.get("no_wrap"))
        least, most = 1, 1
        options = console.options.update_width(10**5)
        for cell in (self.columns[i].header, *(r[i] for r in self.rows)):
            found = Measurement.get(console, options, _renderable(console, cell))
            least = max(least, found.maximum if no_wrap else found.minimum)
            most = max(most, found.maximum)
        return least, most


def _renderable(console: Console, cell: RenderableType) -> RenderableType:
    return console.render_str(cell) if isinstance(cell, str) else cell


def _empty(cell: RenderableType) -> bool:
    if isinstance(cell, str):
        return Text.from_markup(cell).plain.strip() in EMPTY
    if isinstance(cell, Text):
        return cell.plain.strip() in EMPTY
    return False


def _share(room: int, sizes: list[tuple[int, int]]) -> list[int | None]:
    """Cell widths for ``room`` columns: None each where every column fits its longest
    line (rich lays it out), else each its longest word and the rest shared out by what
    each still lacks; None each where not even the words fit (rich folds)."""
    least = sum(s[0] for s in sizes)
    most = sum(s[1] for s in sizes)
    if most <= room or least > room:
        return [None] * len(sizes)
    spare = room - least
    lacking = most - least
    widths = [lo + (hi - lo) * spare // lacking for lo, hi in sizes]
    left = room - sum(widths)
    for i in _by_need(sizes, widths):
        if left <= 0:
            break
        widths[i] += 1
        left -= 1
    return list(widths)


def _by_need(sizes: list[tuple[int, int]], widths: list[int]) -> Iterator[int]:
    """The columns that still lack width, the one lacking most first."""
    return iter(sorted((i for i, (_, hi) in enumerate(sizes) if widths[i] < hi),
                       key=lambda i: widths[i] - sizes[i][1]))


def shown_path(path: str | Path) -> str:
    """A file's path as a table shows it: the bundled trees' short name
    (``armar3/neck.tree``) or relative to the current directory when it is in it,
    whichever is shorter, else as given."""
    from ucom_tools.config.topology import SOURCE_ROOT  # where the bundled files are

    if not str(path):
        return ""
    p = Path(path)
    found = [str(path)]
    for base in (Path.cwd(), SOURCE_ROOT / "attribute_trees"):
        try:
            found.append(str(p.resolve().relative_to(base.resolve())))
        except (ValueError, OSError):
            continue
    return min(found, key=len)
