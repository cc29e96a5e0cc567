"""Exit codes of ``ucom``: one meaning each, for every command (``man/ucom.1``, EXIT STATUS)."""

from __future__ import annotations

EXIT_OK = 0
"""Everything asked for was done (for flash and program: every selected board verified)."""
EXIT_FAILED = 1
"""The operation failed on some boards, which are named; a wiring fault was found; an
expected board did not answer; the boards have no seq ID yet."""
EXIT_USAGE = 2
"""The command line is wrong (unknown option, missing argument, options that exclude each
other)."""
EXIT_BAD_INPUT = 3
"""A file, argument or environment value is wrong; nothing was sent or written."""
EXIT_BUS = 4
"""A bus or connection could not be opened or failed while in use (also: a server could
not listen)."""
EXIT_INTERRUPTED = 130
"""Interrupted (Ctrl-C); a transfer under way was aborted."""

ALL = {EXIT_OK: "success", EXIT_FAILED: "some boards failed", EXIT_USAGE: "usage error",
       EXIT_BAD_INPUT: "bad input", EXIT_BUS: "bus or connection failure",
       EXIT_INTERRUPTED: "interrupted"}
