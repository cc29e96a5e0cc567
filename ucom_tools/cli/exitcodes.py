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
EXIT_WRITE = 5
"""An output could not be written (a full disk, an I/O error, a full standard output) after
the job began; the job's result was reported, the files it wrote before are whole, nothing
is left half-written, and a file being replaced keeps its old content."""
EXIT_INTERRUPTED = 130
"""Interrupted (Ctrl-C); a transfer under way was aborted, the boards were stopped or
restored.  SIGHUP and SIGTERM end a job the same way, with 129 and 143."""

ALL = {EXIT_OK: "success", EXIT_FAILED: "some boards failed", EXIT_USAGE: "usage error",
       EXIT_BAD_INPUT: "bad input", EXIT_BUS: "bus or connection failure",
       EXIT_WRITE: "output not written", EXIT_INTERRUPTED: "interrupted",
       129: "ended by SIGHUP", 143: "ended by SIGTERM"}
