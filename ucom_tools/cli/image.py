"""``ucom image info|progid|convert``: firmware images of either format (S-record, Intel
HEX); ``ucom srec info|progid`` are the same commands under their old name."""

from __future__ import annotations

import os

import click
from rich.markup import escape

from ucom_tools import fileio
from ucom_tools.cli import render
from ucom_tools.cli.output import emit_json, stderr, stdout
from ucom_tools.errors import InputError, UcomError
from ucom_tools.image import formats, ihex
from ucom_tools.image.formats import load_image
from ucom_tools.image.model import FORMAT_NAMES, Image
from ucom_tools.image.srec import parse_srec

ADDRESSING = click.Choice(["auto", "word", "byte"])
FORMAT_CHOICE = click.Choice(list(formats.FORMATS))


@click.group("image")
def image() -> None:
    """Firmware images: S-record (CodeWarrior 56800 convention) and Intel HEX.

    A file named .hex, .ihex or .ihx is Intel HEX; any other is Intel HEX when its first
    non-blank character is ':', else S-records."""


@image.command("info")
@click.argument("file", type=click.Path())
@click.option("--addressing", type=ADDRESSING, default="auto", show_default=True,
              help="Whether S-record addresses count words or bytes (Intel HEX: bytes).")
@click.option("--json", "as_json", is_flag=True, help="Print JSON.")
def info(file: str, addressing: str, as_json: bool) -> None:
    """Format, header, entry, segments per memory space, size and ProgID of FILE.

    The whole file is checked first: syntax, checksums, record types and lengths, the
    end record, overlaps, and that every word lies in programmable memory."""
    img = load_image(file, addressing=addressing)
    plan = img.plan(when_epoch=0)
    if as_json:
        emit_json(render.image_json(img, plan))
    else:
        render.print_image(stdout(), img, plan)


@image.command("progid")
@click.argument("file", type=click.Path())
@click.option("--addressing", type=ADDRESSING, default="auto", show_default=True,
              help="Whether S-record addresses count words or bytes (Intel HEX: bytes).")
def progid(file: str, addressing: str) -> None:
    """Option 19, Calc ProgID: print the ProgID of FILE alone (0x%08X), to compare with the
    ProgID a board reports in its Info."""
    img = load_image(file, addressing=addressing)
    click.echo(f"0x{img.progid:08X}")


@image.command("convert")
@click.argument("source", metavar="IN", type=click.Path())
@click.argument("target", metavar="OUT")
@click.option("--to", "to", type=FORMAT_CHOICE,
              help="The format to write [default: Intel HEX for an OUT named .hex, .ihex "
                   "or .ihx, else the format IN is not in].")
@click.option("--addressing", type=ADDRESSING, default="auto", show_default=True,
              help="Whether IN's S-record addresses count words or bytes.")
@click.option("--force", is_flag=True, help="Replace an existing OUT.")
def convert(source: str, target: str, to: str | None, addressing: str, force: bool) -> None:
    """Convert IN between S-record and Intel HEX, losslessly: the same words (the
    reset-vector words too) and entry, so the same ProgID.

    Intel HEX is written at byte addresses (P:a at 2a, X:a at 0x00400000 + 2a, low byte
    first, a start linear address record of 2 x the entry), as the intelhex package and
    other toolchains read it; S-records in the CodeWarrior 56800 convention (S0
    header, S3 records at word addresses, X: at 0x00200000, S7 entry), as ucom and
    CodeWarrior read them.  OUT is written atomically; an existing OUT only with
    --force (else exit code 3); '-' writes to standard output."""
    img = load_image(source, addressing=addressing)
    fmt = formats.output_format(target, img, to)
    if fmt != "ihex" and formats.format_of_name(target) == "ihex":
        raise InputError(f"{target}: a file named .hex, .ihex or .ihx is read as Intel HEX; "
                         "S-records need another name (e.g. .S)", key="OUT")
    if target != fileio.STDOUT and os.path.isfile(target) and not force:
        raise InputError(f"{target} exists; --force replaces it", key="OUT")
    text = formats.dumps(img, fmt)
    _check_round_trip(img, text, fmt, target)
    fileio.write_text(target, text, key="OUT", allow_stdout=True)
    where = "standard output" if target == fileio.STDOUT else target
    stderr().print(f"wrote {escape(where)}: {FORMAT_NAMES[fmt]}, {img.size()} words, "
                   f"entry P:{img.entry:04X}, ProgID 0x{img.progid:08X}", highlight=False,
                   soft_wrap=True)


def _check_round_trip(img: Image, text: str, fmt: str, target: str) -> None:
    """What is about to be written reads back as ``img`` (else nothing is written)."""
    back = ihex.parse_ihex(text, target) if fmt == "ihex" else parse_srec(text, target)
    if (back.words, back.vector_words, back.entry) != (img.words, img.vector_words,
                                                       img.entry):
        raise UcomError(f"{target}: the converted image does not read back as "
                        f"{img.path}; nothing was written")
