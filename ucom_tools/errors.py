"""The one exception tree of ucom-tools.

Every error a user can cause or meet derives from :class:`UcomError`; the CLI maps the
branches to exit codes (see ``man/ucom.1``).  Library code raises these and never prints.
"""

from __future__ import annotations


class UcomError(Exception):
    """Root of every ucom-tools error."""


class FrameError(UcomError):
    """A CAN frame that does not fit the protocol; ``field`` names what is wrong."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message


class InputError(UcomError):
    """Bad user input (a file, an argument); nothing was sent or written.

    ``key`` names the input as the API names it (a parameter such as ``bus`` or
    ``rate_hz``, or a field of a file such as ``bus[1].board[2].tree``) and ``reason``
    says the fact and what was expected, naming no command-line option: the CLI words the
    error from these fields (``ucom_tools/cli/errortext.py``), ``str()`` is
    ``FILE:LINE: key: reason`` for a Python caller."""

    def __init__(
        self, message: str, *, file: str | None = None, line: int | None = None,
        key: str | None = None, column: int | None = None,
    ) -> None:
        where = ""
        if file is not None:
            where = file
            if line is not None:
                where += f":{line}" + (f":{column}" if column is not None else "")
            where += ": "
        if key is not None:
            where += f"{key}: "
        super().__init__(where + message)
        self.file = file
        self.line = line
        self.column = column
        self.key = key
        self.reason = message


class MissingInput(InputError):
    """An input the operation needs was not given (``key`` names it); the CLI adds which
    options give it."""


class OutputExists(InputError):
    """Outputs that exist and would be replaced (``paths``); replaced only when the
    caller asks for it (a ``force`` parameter), which the CLI names."""

    def __init__(self, paths: list[str], *, key: str | None = None, detail: str = "") -> None:
        super().__init__(f"{', '.join(paths)} exist{'s' * (len(paths) == 1)}{detail}", key=key)
        self.paths = tuple(paths)


class TopologyError(InputError):
    """A topology file that cannot be used (file, line and key are named)."""


class ImageError(InputError):
    """A firmware image (S-record or Intel HEX file) that cannot be programmed."""


class WriteError(UcomError):
    """An output (a file, a device, standard output) could not be written: a full disk,
    an I/O error.  What was written before is kept whole; nothing is left half-written
    (``man/ucom.1``, FILES)."""

    def __init__(self, message: str, *, path: str | None = None,
                 key: str | None = None) -> None:
        super().__init__(f"{key}: {message}" if key is not None else message)
        self.path = path
        self.key = key
        """The output as the API names it (a parameter such as ``journal``), if named."""
        self.reason = message


class BusError(UcomError):
    """A CAN bus could not be opened or failed while in use."""


class BusTaken(BusError):
    """Another host uses the bus or the network as this one would (its cyclic exchange,
    its robot's loop); nothing was sent.  The caller may go on all the same (a ``force``
    parameter), which the CLI names."""


class UcomTimeoutError(UcomError, TimeoutError):
    """A board did not answer in time."""


class BoardError(UcomError):
    """A board answered with an Error message or refused an operation."""


class TreeError(InputError):
    """An attribute tree (``man/ucom-tree.5``) or its binding to a robot that cannot be used;
    names ``FILE:LINE:COL`` of the offending token (line 0 = the file as a whole)."""
