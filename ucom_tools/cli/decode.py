"""``ucom decode TRACE``: a CAN trace read back as the UCoM conversation it carries, with
the protocol violations found on the way (:mod:`ucom_tools.trace.decode`)."""

from __future__ import annotations

from pathlib import Path

import can
import click
from rich.markup import escape

from ucom_tools.cli.exitcodes import EXIT_FAILED
from ucom_tools.cli.options import Finite
from ucom_tools.cli.output import emit_json, stderr
from ucom_tools.errors import InputError
from ucom_tools.trace.decode import DEFAULT_MARGIN, RULES, decode_frames, load_trees, read_trace
from ucom_tools.trace.logs import check_log

_RULES = "; ".join(f"{name}: {text}" for name, text in RULES.items())

HELP = ("""Decode a CAN TRACE into the UCoM conversation it carries, per bus and board.

TRACE is any log python-can reads, by its extension: .asc, .blf, .log (candump -l),
.csv, .trc, .db, .mf4 ... (e.g. one written with --log), or an MCAP file ucom wrote
(--log FILE.mcap, remote run --record FILE.mcap: its /<bus>/frames channels).  One bus
per channel; frames without a channel (.csv, .db) are bus CAN.  Each message shows its
time (seconds from the trace's first frame), direction (PC> from the PC, <B from a
board), function and content; multi-frame answers are assembled (Info records, texts,
edge records), programming is shown as blocks, data frames and resends, and cyclic
frames (SO and CI maps, MCA Alive) as one summary per map.

Then the protocol violations, each with the frame's index in the trace and its time.
Rules: """ + _RULES + """.  Answer deadlines: ucom-protocol(7), TIMEOUTS.

Exit code 0 when the trace keeps the protocol, 1 when it shows violations, 3 when the
file cannot be read.  --json: {"frames", "buses": [{"name", "frames", "boards":
[{"board", "messages": [{"t", "index", "dir", "function", "text", "fields",
"frames", "frame"}]}]}], "violations": [{"t", "index", "bus", "board", "rule",
"message"}]}.""")


@click.command("decode", help=HELP)
@click.argument("trace", type=click.Path(path_type=Path))
@click.option("--trees", "trees", multiple=True, metavar="ROBOT_OR_TREES",
              help="The robot (a bundled topology such as armar3, or a topology file whose "
                   "boards name their attribute trees) and/or tree files replacing its trees "
                   "of the same Prefix; repeat it.  MCA values then carry their unique names "
                   "and boards are bound to their programs.")
@click.option("--timeline", is_flag=True,
              help="One list per bus in bus order, with a board column, instead of per board.")
@click.option("--bus", "bus_name", metavar="NAME", help="Show only this bus.")
@click.option("--board", metavar="BOARD",
              help="Show only this board: a seq ID, F<n>, all, 'SO map <n>', 'CI map <n>'.")
@click.option("-b", "--bitrate", type=click.IntRange(10_000, 1_000_000),
              help="Bus bitrate the answer deadlines assume (default: the topology's with "
                   "--trees, else 1000000).")
@click.option("--margin", type=Finite(0.0, 10.0), default=DEFAULT_MARGIN,
              show_default=True, metavar="SECONDS",
              help="Added to every answer deadline for the recording's time stamps (more for "
                   "a trace recorded over a network).")
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of text.")
@click.option("--to", "to", type=click.Path(path_type=Path), metavar="FILE",
              help="Instead of decoding: write the trace's frames to FILE, in the format of "
                   "its extension (.asc .blf .log .trc, .csv .db for one bus, .mcap), each "
                   "bus on its channel; e.g. an MCAP recording as .blf for CAN tools.")
@click.pass_context
def decode(ctx: click.Context, trace: Path, trees: tuple[str, ...], timeline: bool,
           bus_name: str | None, board: str | None, bitrate: int | None, margin: float,
           as_json: bool, to: Path | None) -> None:
    if to is not None:
        ext = check_log(to, key="--to")  # before the trace is read: exit 3, nothing written
    robot_trees = load_trees(trees) if trees else None
    frames = read_trace(trace)
    if not frames:
        raise InputError("no CAN frames in the file", file=str(trace))
    if to is not None:
        _convert(frames, to, ext)
        return
    conv = decode_frames(frames, robot_trees, bitrate=bitrate, margin=margin)
    if bus_name is not None and bus_name not in {b.name for b in conv.buses}:
        raise InputError(f"no bus {bus_name!r} in the trace; its buses: "
                         f"{', '.join(b.name for b in conv.buses)}", key="--bus")
    if as_json:
        data = conv.to_json()
        if bus_name is not None or board is not None:
            data["buses"] = [
                {**b, "boards": [x for x in b["boards"] if board is None or x["board"] == board]}
                for b in data["buses"] if bus_name is None or b["name"] == bus_name]
            data["violations"] = [v for v in data["violations"]
                                  if (bus_name is None or v["bus"] == bus_name)
                                  and (board is None or v["board"] == board)]
        emit_json({"trace": str(trace), **data})
    else:
        click.echo(conv.render(timeline=timeline, bus=bus_name, board=board), nl=False)
    if conv.violations:
        if not as_json:
            stderr().print(f"[yellow]ucom: {len(conv.violations)} protocol violation"
                           f"{'s' if len(conv.violations) != 1 else ''} in {escape(str(trace))}[/]",
                           highlight=False)
        ctx.exit(EXIT_FAILED)


def _convert(frames: list[can.Message], to: Path, ext: str) -> None:
    """``--to``: ``frames`` into the log ``to`` (written by the rules of ``ucom(1)``,
    FILES: complete, or not at all)."""
    from ucom_tools.fileio import Output
    from ucom_tools.trace.logs import FrameWriter, LogError, channel_names, check_buses
    from ucom_tools.trace.mcapfile import is_mcap

    names = channel_names([f.channel for f in frames])
    check_buses(ext, sorted(set(names.values())), to, "--to")
    out = Output(to, key="--to", suffix=".mcap" if is_mcap(to) else ext)
    try:
        writer = FrameWriter(out, ext)
    except InputError:
        raise
    except Exception as err:
        out.discard()
        raise InputError(f"cannot write {to}: {err}", key="--to") from None
    for f in frames:
        writer.write(f, names[f.channel])
    writer.stop()
    if writer.failure is not None:
        out.discard()
        raise LogError(f"--to: {to}: {writer.failure}; nothing was kept", path=str(to))
    out.commit()
    buses = sorted(set(names.values()))
    stderr().print(f"wrote {escape(str(to))}: {writer.frames} frames of "
                   f"{', '.join(buses)}", soft_wrap=True, highlight=False)
