"""``ucom conformance``: the protocol conformance suite against the boards of a bus, for
CI (JUnit report, a trace per case) and by hand (a table, decoded frames of failures)."""

from __future__ import annotations

import textwrap
from pathlib import Path
from typing import Any

import click
from rich.markup import escape

from ucom_tools import fileio
from ucom_tools.cli.errortext import describe
from ucom_tools.cli.exitcodes import EXIT_BUS, EXIT_FAILED
from ucom_tools.cli.options import connection_json, connection_options, json_option, robot
from ucom_tools.cli.output import emit_json, stderr, stdout
from ucom_tools.cli.tables import FitTable
from ucom_tools.conformance import junit
from ucom_tools.conformance.bench import RUNTIME_IMAGE
from ucom_tools.conformance.restore import RECONNECT_S
from ucom_tools.conformance.runner import (
    Outcome,
    SuiteResult,
    describe_stop,
    run_suite,
    select,
)
from ucom_tools.errors import InputError, UcomError, WriteError
from ucom_tools.ops.robot import ConnectSpec

LIST_WIDTH = 80
"""``--list`` wraps its sentences at this width at most (also when piped)."""
STYLE = {"passed": "green", "failed": "red", "skipped": "yellow", "error": "red"}


def _list(pattern: str | None, as_json: bool) -> None:
    cases = select(pattern)
    if as_json:
        emit_json({"cases": [{"id": c.id, "group": c.group, "title": c.title,
                              "section": c.section, "writes": c.writes} for c in cases]})
        return
    out = stdout()
    width = min(out.width, LIST_WIDTH)
    out.print(f"[bold]{len(cases)} cases[/]")
    for c in cases:
        out.print(f"[bold]{escape(c.id)}[/] [dim]({escape(c.group)})[/]", soft_wrap=True)
        for text in (c.title, f"ucom-protocol(7): {c.section}; writes {c.writes or 'nothing'}"):
            for line in textwrap.wrap(text, width, initial_indent="    ",
                                      subsequent_indent="    ", break_on_hyphens=False,
                                      break_long_words=False):
                out.print(escape(line), soft_wrap=True)


def _words(err: BaseException) -> str:
    """An error as this command line words it (its options, not the API's keys)."""
    return describe(err, "conformance")


def _json(result: SuiteResult, spec: ConnectSpec) -> dict[str, Any]:
    return {"connection": connection_json(spec), "ok": result.ok,
            "counts": result.counts(), "bus_failure": result.bus_failure,
            "stopped": result.describe_stop(_words),
            "left_as_found": not result.not_restored, "not_restored": result.not_restored,
            "cases": [{"id": o.case.id, "group": o.case.group, "bus": o.bus,
                       "section": o.case.section, "status": o.status,
                       "message": o.message or None, "seconds": round(o.seconds, 3),
                       "trace": o.trace, "frames": o.frames or None}
                      for o in result.outcomes]}


def _print(result: SuiteResult) -> None:
    t = FitTable("conformance")
    for col in ("bus", "case", "result", "detail"):
        t.add_column(col)
    for o in result.outcomes:
        t.add_row(o.bus, o.case.id, f"[{STYLE[o.status]}]{o.status}[/]",
                  escape(o.message) or "")
    stdout().print(t)
    for o in result.failed:
        stdout().print(f"\n[bold red]{escape(o.case.id)}[/] on {o.bus} "
                       f"({escape(o.case.section)}): {escape(o.message)}")
        if o.frames:
            stdout().print(escape(o.frames), highlight=False)
    c = result.counts()
    stop_text = result.describe_stop(_words)
    stdout().print(f"\n{c['passed']} passed, {c['failed']} failed, {c['skipped']} skipped"
                   + (f", {c['error']} errors" if c["error"] else "")
                   + (f"; [yellow]stopped:[/] {escape(stop_text)}" if stop_text else "")
                   + ("" if not result.not_restored else
                      f"; [red]not left as found:[/] {escape('; '.join(result.not_restored))}"))


@click.command("conformance")
@click.option("--junit", "junit_file", type=click.Path(path_type=Path),
              metavar="FILE", help="Write a JUnit XML report (one testcase per case and bus).")
@click.option("--trace-dir", type=click.Path(file_okay=False, path_type=Path), metavar="DIR",
              help="Write each case's frames to DIR/BUS/CASE.log (python-can format).")
@click.option("--only", "pattern", metavar="PATTERN",
              help="Only the cases whose id or group matches (glob, e.g. 'init.*', "
                   "'run time').")
@click.option("--list", "list_only", is_flag=True,
              help="List the cases (and what each writes to the boards); run nothing.")
@click.option("--runtime-image", type=click.Path(path_type=Path),
              default=RUNTIME_IMAGE, show_default=True, metavar="FILE",
              help="The run-time program the run-time cases load into external RAM.")
@click.option("--reconnect", "reconnect_s", type=click.FloatRange(0, 3600),
              default=RECONNECT_S, show_default=True, metavar="SECONDS",
              help="How long a lost connection is given to come back, so that the boards "
                   "can be restored.")
@connection_options
@json_option
@click.pass_context
def conformance(ctx: click.Context, junit_file: Path | None, trace_dir: Path | None,
                pattern: str | None, list_only: bool, runtime_image: Path,
                reconnect_s: float, spec: ConnectSpec, bus_name: str | None,
                as_json: bool) -> None:
    """Check that the boards speak the protocol (ucom-protocol(7)), content and timing.

    Runs every case on every bus (or --bus): identifiers, reset, init chain, Info,
    program enable, programming (into external RAM), AutoStart and XReset, FPGA
    registers, the run time (MCA Ready, descriptions, parameters, Dump CI, SO period
    accuracy, watchdog reaction, Report 3) and bad input.  Each case cites the page's
    section.  The boards are reset between cases and left as found, also after Ctrl-C,
    SIGTERM, SIGHUP, a trace that cannot be written or a lost bus that comes back; a board
    that could not be restored is named.  Exit 0 when every case passed or was skipped,
    1 when one failed or a board was not left as found, 4 when the bus failed, 5 when a
    trace or the report could not be written, 130/143/129 when interrupted."""
    if list_only:
        _list(pattern, as_json)
        return
    cases = select(pattern)
    if not runtime_image.is_file():
        raise InputError(f"{runtime_image}: no such file", key="--runtime-image")
    # the report's target is checked (and its temporary file made) before anything is sent
    report = fileio.Output(junit_file, key="junit", allow_stdout=True) \
        if junit_file is not None else None

    def progress(o: Outcome) -> None:
        if not as_json and o.status != "passed":
            stderr().print(f"[{STYLE[o.status]}]{o.status}[/] {o.bus} {escape(o.case.id)}: "
                           f"{escape(o.message)}", soft_wrap=True)

    def notice(text: str) -> None:
        stderr().print(f"[yellow]{escape(text)}[/]", soft_wrap=True)

    try:
        if trace_dir is not None:
            fileio.prepare_directory(trace_dir, key="trace_dir")
        with robot(spec) as r:
            result = run_suite(r, cases, trace_dir=trace_dir, runtime_image=runtime_image,
                               progress=progress, buses=[h.name for h in r.select(bus_name)],
                               notice=notice, reconnect_s=reconnect_s)
    except BaseException:
        if report is not None:
            report.discard()
        raise
    _finish(ctx, result, spec, report, as_json)


def _finish(ctx: click.Context, result: SuiteResult, spec: ConnectSpec,
            report: fileio.Output | None, as_json: bool) -> None:
    """Report, then the exit code: 1 when a board was not left as found (whatever else
    happened), else the interrupt's (130, 143, 129), else 4 for a bus failure, 1 for a
    failed case, else the write error's (a trace or the report; its line in any case)."""
    report_error: UcomError | None = None
    if report is not None:
        try:
            junit.write(result, report, _words)
        except UcomError as err:
            report_error = err
    if as_json:
        emit_json(_json(result, spec))
    else:
        _print(result)
    stop = result.stopped
    interrupt = stop if isinstance(stop, KeyboardInterrupt) else None
    errors = [e for e in (stop, report_error) if e is not None and e is not interrupt]
    if result.not_restored:
        if interrupt is not None:
            stderr().print(f"[yellow]{escape(describe_stop(interrupt))}[/]")
        _error_lines(errors)
        for line in result.not_restored:
            stderr().print(f"[bold red]ucom: not left as found:[/] {escape(line)}",
                           highlight=False, soft_wrap=True)
        ctx.exit(EXIT_FAILED)
    if interrupt is not None:
        _error_lines(errors)
        raise interrupt  # the error boundary (cli.main) gives it its line and exit code
    if result.bus_failure is not None or result.failed:
        _error_lines(errors)
        if result.bus_failure is not None:
            stderr().print(f"[bold red]ucom: bus error:[/] {escape(result.bus_failure)}")
            ctx.exit(EXIT_BUS)
        ctx.exit(EXIT_FAILED)
    if errors:
        _error_lines(errors[1:])
        raise errors[0]  # the error boundary: one line, the exit code of its kind


def _error_lines(errors: list[BaseException]) -> None:
    """The line the error boundary would print for each of ``errors``."""
    for err in errors:
        label = "bad input" if isinstance(err, InputError) else \
            "cannot write" if isinstance(err, WriteError) else "error"
        stderr().print(f"[bold red]ucom: {label}:[/] {escape(describe(err, 'conformance'))}",
                       highlight=False, soft_wrap=True)
