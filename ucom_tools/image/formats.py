"""Which reader takes an image file (S-record or Intel HEX), and conversion between them.

The rule (``ucom(1)``, IMAGES): a file named ``*.hex``, ``*.ihex`` or ``*.ihx`` (in any
case) is Intel HEX; any other file is Intel HEX when its first non-blank character is
``:``, and S-records otherwise.  Both are checked completely before any use.
:func:`load_image` is the one way to read an image file.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import BinaryIO

from ucom_tools import fileio
from ucom_tools.errors import ImageError
from ucom_tools.image import ihex, srec, text
from ucom_tools.image.model import Image

FORMATS = ("srec", "ihex")
_BLANK = b" \t\r\n"
_PEEK = 64 * 1024


def format_of_name(name: str | os.PathLike[str]) -> str | None:
    """Intel HEX ("ihex") for a name the extension decides, else None (by content)."""
    return "ihex" if os.fspath(name).lower().endswith(ihex.SUFFIXES) else None


def load_image(path: str | Path, *, addressing: str = "auto") -> Image:
    """Read and check an image file of either format (the rule of the module docstring);
    :class:`ImageError` naming file and line.  ``addressing`` is for S-record files
    ("auto", "word", "byte"); Intel HEX addresses always count bytes."""
    source = str(path)
    srec.check_addressing(addressing, source)
    if format_of_name(source) == "ihex":
        binary = text.open_image(path, "an Intel HEX file")
        fmt = "ihex"
    else:
        binary = text.open_image(path, "an S-record file")
        try:
            fmt = _by_content(binary, source)
        except BaseException:
            binary.close()
            raise
    if fmt == "ihex":
        if addressing == "word":
            binary.close()
            raise ImageError("Intel HEX addresses count bytes; word addressing is for "
                             "S-record files", file=source)
        return ihex.load_stream(binary, source)
    return srec.load_stream(binary, source, addressing=addressing)


def _by_content(binary: BinaryIO, source: str) -> str:
    """The format by content: "ihex" when the first non-blank byte is ":", else "srec"; the stream
    is put back at its start."""
    seen = 0
    try:
        while seen <= text.MAX_FILE_BYTES:
            chunk = binary.read(_PEEK)
            if not chunk:
                break
            seen += len(chunk)
            body = chunk.lstrip(_BLANK)
            if body:
                binary.seek(0)
                return "ihex" if body[:1] == b":" else "srec"
        binary.seek(0)
    except OSError as err:
        raise ImageError(f"cannot read: {fileio.reason(err)}", file=source) from None
    return "srec"


def output_format(name: str, image: Image, to: str | None = None) -> str:
    """The format ``ucom image convert`` writes to ``name``: ``to`` when given, else
    Intel HEX for a .hex/.ihex/.ihx name, else the format ``image`` is not in."""
    if to is not None:
        return to
    if format_of_name(name) == "ihex":
        return "ihex"
    return "srec" if image.format == "ihex" else "ihex"


def dumps(image: Image, fmt: str) -> str:
    """``image`` as the text of format ``fmt`` ("srec" or "ihex")."""
    return ihex.dumps(image) if fmt == "ihex" else srec.dumps(image)
