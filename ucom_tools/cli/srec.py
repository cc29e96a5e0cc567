"""``ucom srec info`` and ``ucom srec progid`` (option 19, Calc ProgID)."""

from __future__ import annotations

import click

from ucom_tools.cli import render
from ucom_tools.cli.output import emit_json, stdout
from ucom_tools.image import load_image


@click.group("srec")
def srec() -> None:
    """S-record firmware images (CodeWarrior 56800 convention)."""


@srec.command("info")
@click.argument("file", type=click.Path())
@click.option("--addressing", type=click.Choice(["auto", "word", "byte"]), default="auto",
              show_default=True, help="Whether record addresses count words or bytes.")
@click.option("--json", "as_json", is_flag=True, help="Print JSON.")
def info(file: str, addressing: str, as_json: bool) -> None:
    """Header, entry, segments per memory space, size and ProgID of FILE.

    The whole file is checked first: syntax, checksums, count records, overlaps, and that
    every word lies in programmable memory."""
    img = load_image(file, addressing=addressing)
    plan = img.plan(when_epoch=0)
    if as_json:
        emit_json(render.image_json(img, plan))
    else:
        render.print_image(stdout(), img, plan)


@srec.command("progid")
@click.argument("file", type=click.Path())
@click.option("--addressing", type=click.Choice(["auto", "word", "byte"]), default="auto",
              show_default=True)
def progid(file: str, addressing: str) -> None:
    """Option 19, Calc ProgID: print the ProgID of FILE alone (0x%08X), to compare with the
    ProgID a board reports in its Info."""
    img = load_image(file, addressing=addressing)
    click.echo(f"0x{img.progid:08X}")
