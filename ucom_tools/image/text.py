"""Reading an image file of either format as text: opened as a regular file, read line
by line, each line printable ASCII of a bounded length, the whole at most
:data:`MAX_FILE_BYTES`, so that a device, a FIFO or a huge file that is no image file is
rejected at its first bad line without reading the rest.  The record readers
(:mod:`ucom_tools.image.srec`, :mod:`ucom_tools.image.ihex`) take the lines from here.
"""

from __future__ import annotations

import io
import itertools
import os
import re
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import BinaryIO, TextIO

from ucom_tools import fileio
from ucom_tools.errors import ImageError
from ucom_tools.image.model import Image

MAX_FILE_BYTES = 16 * 1024 * 1024
"""Largest file accepted (line ends included), counted while reading."""

NOT_HEX = re.compile(r"[^0-9A-Fa-f]")
_NOT_TEXT = re.compile(r"[^\t\x20-\x7e]")


def open_image(path: str | Path, what: str) -> BinaryIO:
    """Image file ``path`` opened for reading (a regular file, :func:`fileio.open_input`);
    :class:`ImageError` naming it when it cannot be.  The size cap is applied as it is
    read (:func:`read_stream`), so that a huge file that is no image is named as such."""
    source = str(path)

    def refuse(text: str) -> ImageError:
        return ImageError(text, file=source)

    return fileio.open_input(path, limit=1 << 62, what=what, error=refuse)


def read_stream(binary: BinaryIO, source: str,
                reader: Callable[[TextIO, bool], Image]) -> Image:
    """``reader(text stream, too_big)`` applied to ``binary`` (one character per byte),
    which is closed afterwards; a failing read is :class:`ImageError`."""
    try:
        st = os.fstat(binary.fileno())
        too_big = st.st_size > MAX_FILE_BYTES  # a regular file (open_image)
        with io.TextIOWrapper(binary, encoding="latin-1", newline="") as stream:  # byte = char
            return reader(stream, too_big)
    except OSError as err:
        raise ImageError(f"cannot read: {fileio.reason(err)}", file=source) from None
    finally:
        binary.close()


def numbered_lines(stream: TextIO, source: str, *, too_big: bool = False, kind: str,
                   record: str, max_record: int, max_line: int
                   ) -> Iterator[tuple[int, str]]:
    """The numbered lines of ``stream``, without line ends (LF, CR LF or CR), each checked
    to be printable ASCII and at most ``max_line`` long; the whole stream at most
    MAX_FILE_BYTES, counted while reading since devices and FIFOs report no size.

    ``too_big``: the file's size is known to exceed the limit; it is refused after its
    first line, so that a file that is no image file at all is named as such.  ``kind``
    and ``record`` name the format in messages ("Intel HEX", "Intel HEX record")."""
    total = 0
    for no in itertools.count(1):
        line = stream.readline(max_line + 3)  # a whole line with CR LF, or one more
        if not line:
            return
        total += len(line)
        if total > MAX_FILE_BYTES:
            raise ImageError(f"file is larger than {_amount(MAX_FILE_BYTES)}; not an "
                             f"{kind} image for a DSP56F803", file=source, line=no)
        body = line.rstrip("\r\n")
        bad = _NOT_TEXT.search(body)
        if bad:
            raise ImageError(f"not an {kind} file: {_describe(bad.group())}", file=source,
                             line=no, column=bad.start() + 1)
        if len(body) > max_line:
            raise ImageError(f"not an {record}: the line is longer than {max_line} "
                             f"characters (a record has at most {max_record})",
                             file=source, line=no)
        yield no, body
        if too_big:
            raise ImageError(f"file is larger than {_amount(MAX_FILE_BYTES)}; not an "
                             f"{kind} image for a DSP56F803", file=source)


def _amount(size: int) -> str:
    return f"{size // 2**20} MiB" if size % 2**20 == 0 else f"{size} bytes"


def _describe(char: str) -> str:
    code = ord(char)
    if code == 0:
        return "NUL byte (binary data)"
    if code > 0xFF:
        return f"non-ASCII character U+{code:04X}"
    if code > 0x7F:
        return f"non-ASCII byte 0x{code:02X}"
    return f"control character 0x{code:02X}"


def clip(s: str) -> str:
    return s if len(s) <= 40 else s[:37] + "..."
