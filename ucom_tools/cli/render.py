"""Tables and JSON for operation results (shared by the commands and the console).

Table cells never end in an ellipsis: on a narrow terminal a long cell folds onto the next
line; a piped output has no width limit (:mod:`ucom_tools.cli.output`), so serials,
ProgIDs and names always come out whole.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from rich.console import Console
from rich.markup import escape

from ucom_tools.cli.tables import FitTable
from ucom_tools.ops.enumerate import BusEnumeration
from ucom_tools.ops.options import ProbeResult, Row
from ucom_tools.plugons import app_name, board_name
from ucom_tools.wire import messages as m
from ucom_tools.wire.descriptor import ImageDescriptor
from ucom_tools.wire.fpga import FpgaVersion
from ucom_tools.wire.ids import Address, IdType
from ucom_tools.wire.info import BoardInfo
from ucom_tools.wire.transfer import TransferPlan

if TYPE_CHECKING:  # not imported to print the tables of the commands that do not use them
    from ucom_tools.image.model import Image
    from ucom_tools.ops.compat import CheckRow
    from ucom_tools.ops.flash_types import FlashResult


def status_leds(s: m.StatusReport) -> str:
    """The LEDs of a status report as text: 'red+green', 'off'."""
    lit = [c for bit, c in ((0, "red"), (1, "yellow"), (2, "green")) if s.leds >> bit & 1]
    return "+".join(lit) or "off"


def hex32(v: int | None) -> str:
    return f"0x{v:08X}" if v is not None else "-"


def addr_json(a: Address | None) -> dict[str, Any]:
    if a is None:
        return {"seq_id": None, "fixed_id": None}
    return {"seq_id": a.number if a.id_type is IdType.SEQUENTIAL else None,
            "fixed_id": a.number if a.id_type is IdType.FIXED else None}


def who(r: Row) -> str:
    """A row's board: its address, or the placement of an expected board that is absent."""
    return str(r.address) if r.address is not None else (r.placement or "-")


def table(title: str | None, columns: tuple[str, ...] | dict[str, int],
          **kwargs: Any) -> FitTable:
    """A table that fits the terminal (:class:`~ucom_tools.cli.tables.FitTable`):
    ``columns`` each never left out, or header -> its drop order (0: never; 1 first)."""
    t = FitTable(title, **kwargs)
    for col in columns:
        t.add_column(col, drop=columns[col] if isinstance(columns, dict) else 0)
    return t


def info_json(inf: BoardInfo) -> dict[str, Any]:
    return {
        "state": inf.state.text, "seq_id": inf.seq_id or None, "fixed_id": inf.fixed_id or None,
        "serial": hex32(inf.serial), "program": inf.name or None, "progid": hex32(inf.progid)
        if inf.flash_valid or inf.extram_valid else None, "size_words": inf.size_words,
        "programmed": inf.programmed.isoformat() if inf.programmed else None,
        "target": inf.target.name.lower(), "entry": f"P:{inf.entry:04X}",
        "autostart": inf.autostart, "prog_enable": inf.prog_enable,
        "flash_valid": inf.flash_valid, "extram_valid": inf.extram_valid,
        "bootloader": "{}.{}".format(*inf.bootloader_version),
        "plug_on_board": f"{inf.measured_board_id} ({board_name(inf.measured_board_id)})",
        "fpga": fpga_text(inf.fpga) + (" NEUTRAL" if inf.fpga_neutral else ""),
        "built_for": (descriptor_text(inf.descriptor) if inf.descriptor else
                      "corrupt descriptor" if inf.descriptor_corrupt else
                      "no descriptor" if inf.flash_valid or inf.extram_valid else None),
    }


INFO_LABELS = {
    "state": "state", "seq_id": "seq ID", "fixed_id": "fixed ID", "serial": "serial",
    "program": "program", "progid": "ProgID", "size_words": "size (words)",
    "programmed": "programmed", "target": "memory", "entry": "entry point",
    "autostart": "AutoStart", "prog_enable": "ProgEnable", "flash_valid": "flash valid",
    "extram_valid": "ExtRAM valid", "bootloader": "bootloader version",
    "plug_on_board": "plug-on board", "fpga": "FPGA", "built_for": "built for"}
"""The label of each field of :func:`info_json` in ``ucom info``'s table (``--json`` keeps
the keys)."""


def info_value(v: object) -> str:
    """A field's value as ``ucom info``'s table shows it: yes/no, '-' for none."""
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    return escape(str(v))


def descriptor_text(d: ImageDescriptor) -> str:
    return (f"{board_name(d.board_id)} app {d.app_id} FPGA v{d.fpga_major}.{d.fpga_minor}, "
            "program v{}.{}".format(*d.version))


# ----------------------------------------------------------------------------- init
def enumeration_json(e: BusEnumeration) -> dict[str, Any]:
    return {
        "name": e.bus, "expected": e.expected, "found": e.found,
        "first_answers": e.first_answers,
        "boards": [{
            "seq_id": b.seq_id, "serial": hex32(b.serial), "fixed_id": b.fixed_id or None,
            "position": b.position, "placement": b.placement, "board": b.board,
            "duplicate_seq_id": b.duplicate,
            "state": b.info.state.text if b.info else None,
            "program": (b.info.name or None) if b.info else None,
            "progid": hex32(b.info.progid) if b.info and b.info.flash_valid else None,
        } for b in e.boards],
        "diagnosis": [{"kind": d.kind, "message": d.message, "leds": d.leds}
                      for d in e.diagnosis],
    }


def print_enumeration(c: Console, e: BusEnumeration) -> None:
    t = table(f"{e.bus}: init chain", {"seq ID": 0, "pos": 1, "placement": 0, "board": 3,
                                        "serial": 0, "fixed ID": 2, "state": 0,
                                        "program": 0, "ProgID": 4})
    for b in e.boards:
        inf = b.info
        t.add_row(
            f"[red]{b.seq_id}![/]" if b.duplicate else str(b.seq_id),
            str(b.position or "-"), escape(b.placement or "-"), b.board or "-",
            hex32(b.serial), str(b.fixed_id or "-"), inf.state.text if inf else "?",
            (escape(inf.name) or "[dim]none[/]") if inf else "?",
            hex32(inf.progid) if inf and inf.flash_valid else "-")
    c.print(t)
    exp = f" of {e.expected} expected" if e.expected is not None else ""
    colour = "green" if e.ok else "yellow"
    c.print(f"[{colour}]{e.bus}: {e.found} board(s) found{exp}[/]")
    for d in e.diagnosis:
        c.print(f"  [bold yellow]![/] {escape(d.message)}")
        if d.leds:
            c.print(f"    [dim]LEDs:[/] {escape(d.leds)}")


# ----------------------------------------------------------------------------- rows
def rows_json(rows: list[Row]) -> dict[str, Any]:
    out = []
    for r in rows:
        d: dict[str, Any] = {"bus": r.bus, **addr_json(r.address), "ok": r.ok,
                             "placement": r.placement, "detail": r.detail,
                             "state": r.state.text if r.state is not None else None}
        if r.serial is not None:
            d["serial"] = hex32(r.serial)
        if r.info is not None:
            d["info"] = info_json(r.info)
        if r.reports:
            d["messages"] = list(r.reports)
        out.append(d)
    return {"results": out}


def print_rows(c: Console, rows: list[Row], title: str) -> None:
    if not rows:
        c.print(f"[yellow]{title}: no board answered[/]")
        return
    t = table(title, ("bus", "board", "result", "state", "messages"))
    for r in rows:
        t.add_row(r.bus, escape(who(r)), "[green]ok[/]" if r.ok and r.detail == "ok" else
                  (f"[green]{escape(r.detail)}[/]" if r.ok else f"[red]{escape(r.detail)}[/]"),
                  r.state.text if r.state is not None else "-",
                  escape("\n".join(r.reports)))
    c.print(t)


def print_reset(c: Console, rows: list[Row], title: str) -> None:
    if not rows:
        c.print(f"[yellow]{title}: no board answered.[/] Boards answer a reset only once they "
                "have a number (seq ID from the init chain, or a fixed ID): run 'init'.")
        return
    t = table(f"{title}: boards that answered (alive)",
              ("bus", "board", "serial", "state after reset"))
    for r in rows:
        t.add_row(r.bus, escape(who(r)), hex32(r.serial),
                  r.state.text if r.state is not None else f"[red]{escape(r.detail)}[/]")
    c.print(t)


def print_infos(c: Console, rows: list[Row], title: str) -> None:
    infos = [r for r in rows if r.info is not None]
    if len(infos) == 1 and len(rows) == 1:
        r = rows[0]
        assert r.info is not None
        t = FitTable(f"{title}: {r.bus} board {r.address}", show_header=False)
        t.add_column("field", style="bold", keep=True)
        t.add_column("value", keep=True)
        for k, v in info_json(r.info).items():
            t.add_row(INFO_LABELS.get(k, k), info_value(v))
        c.print(t)
        return
    t = table(title, {"bus": 0, "seq ID": 0, "fixed": 4, "serial": 0, "state": 0,
                      "program": 0, "ProgID": 5, "size": 2, "programmed": 1, "plug-on": 3,
                      "FPGA": 6, "flags": 0})
    for r in rows:
        inf = r.info
        if inf is None:
            t.add_row(r.bus, escape(who(r)), "", "", f"[red]{escape(r.detail)}[/]", "", "", "",
                      "", "", "", "")
            continue
        flags = " ".join(f for f, on in (("AutoStart", inf.autostart),
                                         ("ProgEnable", inf.prog_enable),
                                         ("ExtRAM", inf.extram_valid)) if on)
        valid = inf.flash_valid or inf.extram_valid
        t.add_row(r.bus, str(inf.seq_id or "-"), str(inf.fixed_id or "-"), hex32(inf.serial),
                  inf.state.text, escape(inf.name) if valid else "[dim]none[/]",
                  hex32(inf.progid) if valid else "-",
                  f"{inf.size_words} w" if valid else "-",
                  inf.programmed.strftime("%Y-%m-%d %H:%M") if inf.programmed else "-",
                  board_name(inf.measured_board_id),
                  fpga_text(inf.fpga) + (" [red]NEUTRAL[/]" if inf.fpga_neutral else ""), flags)
    c.print(t)


# ----------------------------------------------------------------------------- probes
def probe_json(results: list[ProbeResult]) -> dict[str, Any]:
    return {"buses": [{
        "name": p.bus, "broken": p.broken,
        "answers": [{"seq_id": a.seq_id or None, "fixed_id": a.fixed_id or None,
                     "serial": hex32(a.serial)} for a in p.answers],
        "info": info_json(p.info) if p.info else None} for p in results]}


def print_probe(c: Console, results: list[ProbeResult]) -> None:
    for p in results:
        which = "last" if p.last else "first"
        if not p.answers:
            c.print(f"[yellow]{p.bus}: no board answered as {which} board[/]")
            continue
        for a in p.answers:
            c.print(f"{p.bus}: {which} board: seq ID {a.seq_id or '-'}, serial "
                    f"{hex32(a.serial)}" + (f", fixed ID {a.fixed_id}" if a.fixed_id else ""))
        if p.info is not None:
            c.print(f"  program {escape(p.info.name) or 'none'}, state {p.info.state.text}")
        if p.broken:
            c.print(f"[bold yellow]  ! {len(p.answers)} boards answer as {which}: the init "
                    "line is broken.[/] A board right after a break lights yellow only at "
                    "power-on.")


# ----------------------------------------------------------------------------- images
def image_json(img: Image, plan: TransferPlan) -> dict[str, Any]:
    from ucom_tools.wire.codes import Space
    return {
        "file": img.path, "format": img.format_name, "header": img.header,
        "entry": f"P:{img.entry:04X}",
        "addressing": img.addressing, "records": img.records,
        "progid": hex32(plan.progid), "size_words": img.size(),
        "words": {"P": img.size(Space.P), "X": img.size(Space.X)},
        "blocks": len(plan.blocks),
        "segments": [{"space": s.space.name, "start": f"{s.start:04X}", "end": f"{s.end:04X}",
                      "words": s.length} for s in img.segments()],
        "vector_words": {f"P:{a:04X}": f"{v:04X}" for a, v in sorted(img.vector_words.items())},
        "descriptor": descriptor_json(img.descriptor),
        "flags": [] if img.descriptor else [
            "no image descriptor at P:7DE0: programmable, but compatibility with board and "
            "FPGA cannot be checked"],
    }


def descriptor_json(d: ImageDescriptor | None) -> dict[str, Any] | None:
    if d is None:
        return None
    out: dict[str, Any] = {
        "board_id": d.board_id, "board": board_name(d.board_id), "app_id": d.app_id,
        "application": app_name(d.board_id, d.app_id),
        "fpga_version": f"{d.fpga_major}.{d.fpga_minor}",
        "program_version": "{}.{}".format(*d.version)}
    if d.name:
        out["name"] = d.name
    return out


def print_image(c: Console, img: Image, plan: TransferPlan) -> None:
    d = image_json(img, plan)
    c.print(f"[bold]{escape(img.path)}[/]")
    c.print(f"  format     {d['format']} ({d['records']} records, {img.addressing} "
            "addresses)")
    if img.format == "srec":
        c.print(f"  header     {escape(repr(d['header']))}")
    c.print(f"  entry      {d['entry']}")
    c.print(f"  size       {d['size_words']} words ({d['words']['P']} P:, {d['words']['X']} X:)"
            f" = {d['size_words'] * 2} bytes in {d['blocks']} blocks")
    c.print(f"  ProgID     [bold]{d['progid']}[/]")
    t = table(None, ("space", "words", "from", "to"), box=None, padding=(0, 2))
    for s in d["segments"]:
        t.add_row(s["space"], str(s["words"]), f"{s['space']}:{s['start']}",
                  f"{s['space']}:{s['end']}")
    c.print(t)
    if img.vector_words:
        c.print("  [dim]reset-vector words P:0000-0003 in the file are not programmed: the "
                "bootloader keeps its own vectors[/]")
    desc = d["descriptor"]
    if desc:
        c.print(f"  built for  Board-ID {desc['board_id']} ({desc['board']}), App-ID "
                f"{desc['app_id']} ({desc['application']}), FPGA {desc['fpga_version']}")
        c.print(f"  program    {escape(repr(desc.get('name', '')))} version "
                f"{desc['program_version']}")
    else:
        c.print("  [yellow]no image descriptor (P:7DE0): programmable, but compatibility with "
                "board and FPGA cannot be checked[/]")


# ----------------------------------------------------------------------------- flash
def left_json(info: BoardInfo | None) -> dict[str, Any] | None:
    """A board's state as an interrupted job left it (its Info), for ``left``."""
    if info is None:
        return None
    return {"state": info.state.text, "prog_enable": info.prog_enable,
            "flash_valid": info.flash_valid, "autostart": info.autostart,
            "progid": hex32(info.progid) if info.flash_valid else None}


def flash_json(r: FlashResult) -> dict[str, Any]:
    return {
        "image": r.image, "progid": hex32(r.progid), "size_words": r.size_words,
        "target": r.target.name.lower(), "all_verified": r.all_verified,
        "boards": [{
            "bus": b.bus, "seq_id": b.seq_id or None, "serial": hex32(b.serial),
            "placement": b.placement,
            "outcome": b.outcome, "verified_progid": hex32(b.progid) if b.verified else None,
            "detail": b.detail, "resent_frames": b.resent_frames, "autostart": b.autostart,
            "started": b.started, "messages": list(b.messages),
            "warnings": list(b.warnings), "left": left_json(b.left)} for b in r.boards],
        "buses": [{"name": bus.bus, "frames": bus.frames, "rounds": bus.rounds,
                   "resent_frames": bus.resent_frames,
                   "note": bus.note or None, "interrupted": bus.interrupted or None,
                   "diagnosis": [d.message for d in bus.enumeration.diagnosis]
                   if bus.enumeration else []} for bus in r.buses],
    }


def print_flash(c: Console, r: FlashResult) -> None:
    t = table(f"{escape(r.image)} (ProgID {hex32(r.progid)}, {r.size_words} words) "
              f"-> {r.target.name.lower()}",
              {"bus": 0, "seq ID": 0, "placement": 5, "serial": 2, "result": 0, "ProgID": 3,
               "resent": 1, "AutoStart": 4, "started": 0})
    for b in r.boards:
        t.add_row(b.bus, str(b.seq_id or "-"), escape(b.placement or "-"), hex32(b.serial),
                  "[green]verified[/]" if b.verified else
                  f"[{'yellow' if b.outcome == 'kept' else 'red'}]{b.outcome}[/]",
                  hex32(b.progid) if b.verified or (b.outcome == "kept" and b.progid)
                  else "-", str(b.resent_frames or ""),
                  "yes" if b.autostart else "", {None: "", True: "[green]yes[/]",
                                                 False: "[red]no[/]"}[b.started])
    c.print(t)
    for b in r.boards:
        for w in b.warnings:
            c.print(f"  [yellow]{b.bus} board {b.seq_id}: {escape(w)}[/]")
        for msg in b.messages:
            c.print(f"  [dim]{b.bus} board {b.seq_id}:[/] {escape(msg)}")
    for bus in r.buses:
        if bus.enumeration is not None:
            for d in bus.enumeration.diagnosis:
                c.print(f"  [bold yellow]! {bus.bus}:[/] {escape(d.message)}")
    for b in r.boards:
        if not b.verified or r.interrupted:
            who = f"board {b.seq_id}" if b.seq_id else escape(b.placement or "a board")
            colour = "yellow" if b.outcome == "kept" or b.verified else "red"
            c.print(f"  [{colour}]{b.bus} {who}:[/] {escape(b.detail)}", soft_wrap=True)
    ok = sum(1 for b in r.boards if b.verified)
    colour = "green" if r.all_verified else "red"
    c.print(f"[{colour}]{ok} of {len(r.boards)} board(s) verified[/]")
    not_started = [b for b in r.boards if b.verified and b.started is False]
    if not_started:
        c.print(f"[red]{len(not_started)} verified board(s) did not start: "
                + ", ".join(f"{b.bus}:{b.seq_id}" for b in not_started) + "[/]")


LEFT_WORDS = {"kept": "kept their program as found (not erased, not ProgEnabled)",
              "erased": "in their bootloader with ProgEnable cleared and no transfer open, "
                        "their program erased",
              "verified": "new program verified",
              "unreachable": "did not answer (state unknown)",
              "not undone": "still ProgEnabled or in the transfer"}
"""How :func:`interrupted_line` counts the boards of each outcome."""


def interrupted_line(r: FlashResult, how: str, what: str = "flash") -> str:
    """One line for an interrupted flash: where each bus was, how many boards were left
    with what (every board is named in the table and its detail lines)."""
    from ucom_tools.ops.flash_types import at_phase

    phases: dict[str, list[str]] = {}
    for bus in r.buses:
        phases.setdefault(bus.interrupted or "finished", []).append(bus.bus)
    where = "; ".join(f"{', '.join(names)} {at_phase(phase)}" for phase, names in phases.items())
    counts: dict[str, list[str]] = {}
    for b in r.boards:
        counts.setdefault(b.outcome, []).append(
            f"{b.bus}:{b.seq_id}" if b.seq_id else f"{b.bus}:{b.placement}")
    parts = []
    for outcome, names in counts.items():
        words = LEFT_WORDS.get(outcome, outcome)
        named = f" ({', '.join(names)})" if outcome in ("unreachable", "not undone") else ""
        parts.append(f"{len(names)} {words}{named}")
    return f"{what} {how} ({where}): " + ("; ".join(parts) or "no board was touched")


# ----------------------------------------------------------------------------- check
def fpga_text(f: FpgaVersion | None) -> str:
    if f is None:
        return "?"
    return f"{board_name(f.board_id)} app {f.app_id} v{f.version}"


def check_json(rows: list[CheckRow]) -> dict[str, Any]:
    return {"boards": [{
        "bus": r.bus, "seq_id": r.seq_id or None, "placement": r.placement,
        "serial": hex32(r.serial),
        "plug_on_board": {"board_id": r.plug_board_id, "board": board_name(r.plug_board_id)},
        "fpga": None if r.fpga is None else {
            "board_id": r.fpga.board_id, "board": board_name(r.fpga.board_id),
            "app_id": r.fpga.app_id, "version": r.fpga.version, "ikl": r.fpga.ikl,
            "ikh": r.fpga.ikh, "neutral": r.neutral},
        "program": None if r.program is None else {
            "name": r.program, "progid": hex32(r.progid),
            "descriptor": descriptor_json(r.descriptor)},
        "verdict": r.verdict,
        "reasons": [{"severity": f.severity, "field": f.field, "expected": f.expected,
                     "found": f.found, "message": f.message} for f in r.findings],
    } for r in rows], "clean": not any(r.failed for r in rows)}


def print_check(c: Console, rows: list[CheckRow]) -> None:
    t = table("compatibility: plug-on board - FPGA - DSP program",
              {"bus": 0, "seq": 0, "placement": 1, "plug-on": 0, "FPGA": 0, "DSP program": 0,
               "built for": 0, "verdict": 0})
    colours = {"ok": "green", "warning": "yellow", "mismatch": "red", "no program": "dim",
               "unknown": "red", "missing": "red"}
    for r in rows:
        d = r.descriptor
        built = (f"{board_name(d.board_id)} app {d.app_id} v{d.fpga_major}.{d.fpga_minor}"
                 if d else ("-" if r.program is None else "[yellow]no descriptor[/]"))
        fpga = ("-" if r.verdict == "missing" else fpga_text(r.fpga)) + (
            " [red]NEUTRAL[/]" if r.neutral else "")
        t.add_row(r.bus, str(r.seq_id or "-"), escape(r.placement or "-"),
                  board_name(r.plug_board_id) if r.verdict != "missing" else "-", fpga,
                  escape(r.program) if r.program else "[dim]none[/]", built,
                  f"[{colours.get(r.verdict, 'white')}]{r.verdict}[/]")
    c.print(t)
    for r in rows:
        for f in r.findings:
            colour = "red" if f.severity == "error" else "yellow"
            where = f"board {r.seq_id}" if r.seq_id else escape(r.placement or "?")
            c.print(f"  [{colour}]{r.bus} {where}:[/] {escape(f.message)}")
    bad = sum(1 for r in rows if r.failed)
    c.print("[green]clean: every board fits its FPGA and program[/]" if not bad and rows
            else f"[red]{bad} board(s) do not fit or are missing[/]" if bad
            else "[yellow]no board found[/]")
