"""``ucom remote plot``: the values a run recorded (``ucom remote run --record FILE``
writes ``FILE.values.csv``, or its values channels where FILE is ``.mcap``) drawn over
time: a PNG (matplotlib, Agg), a text plot in the terminal (plotext), or the series as
JSON.

The plotting libraries are the optional ``plot`` extra and imported only when drawing;
without them a drawing ends as bad input (exit 3) that says how to install them.
"""

from __future__ import annotations

import difflib
import math
import os
import shutil
import sys
from collections.abc import Sequence
from decimal import Decimal
from pathlib import Path
from typing import Any

import click
from rich.markup import escape

from ucom_tools import fileio
from ucom_tools.cli.output import emit_json, stderr
from ucom_tools.errors import InputError
from ucom_tools.trace.record import Series, Values, read_values

PLOT_EXTRA = "plotting needs the plot extra: pip install 'ucom-tools[plot]'"
"""The message when matplotlib or plotext is not installed."""

TEXT_SIZE = (100, 30)
"""Width and height of the text plot when standard output is not a terminal."""

TEXT_COLORS = ("blue+", "red+", "green+", "magenta+", "cyan+", "orange+")
TEXT_MARKERS = ("braille", "•", "x", "+", "o", "*")
"""Lines of the text plot: by colour on a terminal, by marker without colours."""

PNG_SIZE = (10.0, 5.0)
"""Inches at 100 dpi: a 1000 x 500 PNG."""

MARKED = 100
"""A series with at most this many changes has a dot at each (denser ones would blur)."""


# ----------------------------------------------------------------------------- selection
def select(values: Values, names: Sequence[str]) -> list[Series]:
    """The series NAMEs choose, in the order given (each once): ``Prefix/Unique name``,
    or the bare unique name when one prefix only has it.  InputError listing the
    closest names (unknown) or the qualified ones (ambiguous)."""
    chosen: list[Series] = []
    for name in names:
        s = values.series.get(name)
        if s is None:
            bare = [x for x in values.series.values() if x.name == name]
            if len(bare) > 1:
                raise InputError(
                    f"{name!r} is the name of {len(bare)} signals: "
                    f"{', '.join(repr(x.qualified) for x in bare)}; give one as PREFIX/NAME",
                    file=values.file, key="NAME")
            if not bare:
                raise InputError(unknown(values, name), file=values.file, key="NAME")
            s = bare[0]
        if s not in chosen:
            chosen.append(s)
    return chosen


def unknown(values: Values, name: str) -> str:
    """Why ``name`` selects nothing, with the closest qualified names."""
    if not values.series:
        return f"no signal {name!r}: the file holds no values"
    qualified = list(values.series)
    by_bare: dict[str, list[str]] = {}
    for s in values.series.values():
        by_bare.setdefault(s.name, []).append(s.qualified)
    close = [q for q in qualified
             if name.casefold() in (q.casefold(), values.series[q].name.casefold())]
    close += difflib.get_close_matches(name, qualified, n=5, cutoff=0.6)
    for bare in difflib.get_close_matches(name, list(by_bare), n=5, cutoff=0.6):
        close += by_bare[bare]
    close = list(dict.fromkeys(close))[:5]
    if close:
        return f"no signal {name!r}; closest: {', '.join(repr(c) for c in close)}"
    some = ", ".join(repr(q) for q in qualified[:5])
    more = f" (and {len(qualified) - 5} more)" if len(qualified) > 5 else ""
    return f"no signal {name!r}; the file holds {some}{more}"


# ----------------------------------------------------------------------------- data
def _number(d: Decimal) -> int | float:
    """A JSON number: an int for a value written without a fraction."""
    exponent = d.as_tuple().exponent
    return int(d) if isinstance(exponent, int) and exponent >= 0 else float(d)


def series_json(values: Values, chosen: Sequence[Series]) -> dict[str, list[list[Any]]]:
    """{qualified name: [[t, value], ...]}, t in seconds from the file's first row."""
    start = values.start or 0.0
    return {s.qualified: [[round(t - start, 6), _number(v)] for t, v in s.points]
            for s in chosen}


def steps(values: Values, s: Series) -> tuple[list[float], list[float]]:
    """The step line of ``s``: each value holds until the next change, the last one to
    the end of the recording, but for the stretches where its board was lost (a gap: no
    value, NaN); x in seconds from the first row."""
    start = values.start or 0.0
    end = (values.end or 0.0) - start
    xs: list[float] = []
    ys: list[float] = []
    gaps = [t for t, _ in s.stale]
    for t, v in s.points:
        while gaps and gaps[0] <= t:
            x = gaps.pop(0) - start
            if ys:
                xs += [x, x]
                ys += [ys[-1], math.nan]
        x = t - start
        if ys:
            xs.append(x)
            ys.append(ys[-1])
        xs.append(x)
        ys.append(float(v))
    for gap in gaps:  # lost until the end
        if ys:
            xs += [gap - start, gap - start]
            ys += [ys[-1], math.nan]
    if xs and end > xs[-1]:
        xs.append(end)
        ys.append(ys[-1])
    return xs, ys


# ----------------------------------------------------------------------------- drawing
def draw_png(values: Values, chosen: Sequence[Series], out: str) -> None:
    """Draw ``chosen`` into the PNG ``out``, written by the rules of ``ucom(1)``, FILES
    (a regular file atomically, keeping its permissions; a device or FIFO written
    through)."""
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        raise InputError(PLOT_EXTRA) from None
    target = Path(out)
    if target.suffix.lower() != ".png":
        raise InputError(f"{out}: the plot is a PNG; name it *.png", key="-o")
    if not target.parent.is_dir():
        raise InputError(f"{out}: directory {target.parent} does not exist", key="-o")
    if target.is_dir():
        raise InputError(f"{out} is a directory", key="-o")
    fig = Figure(figsize=PNG_SIZE, dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    start = values.start or 0.0
    for s in chosen:
        xs, ys = steps(values, s)
        ax.plot(xs, ys, drawstyle="steps-post", label=s.qualified)
        if len(s.points) <= MARKED:
            ax.plot([t - start for t, _ in s.points], [float(v) for _, v in s.points],
                    linestyle="none", marker=".", color=ax.lines[-1].get_color())
    ax.set_xlabel("time [s] from the first row")
    ax.set_ylabel("value" if len({s.kind for s in chosen}) != 1 else f"value ({chosen[0].kind})")
    ax.set_title(os.path.basename(values.file))
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best")
    with fileio.output_stream(target, "wb", key="-o") as f:
        fig.savefig(f, format="png")


def _tty() -> bool:
    try:
        return sys.stdout.isatty()
    except (AttributeError, ValueError):
        return False


def text_size() -> tuple[int, int]:
    """The terminal's size when standard output is one, else :data:`TEXT_SIZE`."""
    if not _tty():
        return TEXT_SIZE
    size = shutil.get_terminal_size(TEXT_SIZE)
    return max(size.columns, 40), max(size.lines - 1, 10)


def draw_text(values: Values, chosen: Sequence[Series], *, color: bool) -> str:
    """The text plot of ``chosen`` (plotext), sized by :func:`text_size`."""
    try:
        import plotext
    except ImportError:
        raise InputError(PLOT_EXTRA) from None
    width, height = text_size()
    plotext.clear_figure()
    try:
        plotext.theme("clear")
        plotext.limitsize(False, False)  # the size chosen here, not plotext's guess
        plotext.plotsize(width, height)
        for i, s in enumerate(chosen):
            xs, ys = steps(values, s)
            if color:
                plotext.plot(xs, ys, label=s.qualified, marker="braille",
                             color=TEXT_COLORS[i % len(TEXT_COLORS)])
            else:  # the marker tells the lines apart
                plotext.plot(xs, ys, label=s.qualified,
                             marker=TEXT_MARKERS[i % len(TEXT_MARKERS)])
        plotext.title(os.path.basename(values.file))
        plotext.xlabel("time [s] from the first row")
        text: str = plotext.build()
    finally:
        plotext.clear_figure()
    return text if color else plotext.uncolorize(text)


# ----------------------------------------------------------------------------- command
@click.command("plot")
@click.argument("values_csv", metavar="VALUES_CSV")
@click.argument("names", nargs=-1, required=True, metavar="NAME...")
@click.option("-o", "--output", "out", metavar="OUT.png",
              help="Draw into this PNG (matplotlib; written atomically) instead of the "
                   "terminal.")
@click.option("--json", "as_json", is_flag=True,
              help='Print the series as JSON: {"Prefix/Name": [[t, value], ...]}, t in '
                   "seconds from the first row.")
def plot(values_csv: str, names: tuple[str, ...], out: str | None, as_json: bool) -> None:
    """Plot recorded values over time: VALUES_CSV is the FILE.values.csv that
    `remote run --record FILE` writes (or FILE itself where it is an MCAP recording,
    FILE.mcap), NAME a signal as Prefix/Unique name (e.g.
    "Eyes/Right Eye Joint Sensor") or its bare unique name when one prefix only has it.

    A step plot (a value holds until it changes), x in seconds from the first row: in
    the terminal (plotext; 100x30 when not a terminal), or with -o into a PNG
    (matplotlib).  Needs the plot extra: pip install 'ucom-tools[plot]'.
    """
    if str(values_csv).lower().endswith(".mcap"):
        from ucom_tools.trace.mcap_values import read_mcap_values

        values = read_mcap_values(values_csv)
    else:
        values = read_values(values_csv)
    chosen = select(values, names)
    if out is not None:
        draw_png(values, chosen, out)
        points = sum(len(s.points) for s in chosen)
        stderr().print(f"wrote {escape(out)}: {len(chosen)} signal"
                       f"{'s' if len(chosen) != 1 else ''}, {points} changes, "
                       f"{_span(values):.3f} s", soft_wrap=True)
    if as_json:
        emit_json(series_json(values, chosen))
    elif out is None:
        color = _tty() and "NO_COLOR" not in os.environ
        click.echo(draw_text(values, chosen, color=color))


def _span(values: Values) -> float:
    if values.start is None or values.end is None:
        return 0.0
    return values.end - values.start


__all__ = ["PLOT_EXTRA", "draw_png", "draw_text", "plot", "select", "series_json", "steps"]
