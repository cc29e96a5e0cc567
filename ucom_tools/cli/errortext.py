"""The command line's words for an error: the inputs the API names (``bus``, ``rate_hz``)
as the options that carry them (``--bus``, ``--rate``), and the advice that names options.

Below ``cli/`` an error names its input as the API does and says the fact and what was
expected, naming no option and no ``ucom`` command (issue 37); the command line rebuilds
the text from the error's fields here, as :func:`~ucom_tools.cli.menu.init_advice` words
:class:`~ucom_tools.ops.options.NotInitialised`.  A file's errors name the file, its line
and its field, which are printed as they are.
"""

from __future__ import annotations

from ucom_tools.errors import BusTaken, InputError, MissingInput, OutputExists, WriteError

OPTIONS: dict[str, str] = {
    "bus": "--bus", "only": "--bus", "channels": "--channel", "interface": "--interface",
    "host": "--host", "port": "--port", "topology": "--topology", "virtual": "--virtual",
    "scenario": "--scenario", "log": "--log", "rate_hz": "--rate", "periods": "--period",
    "on_fault": "--on-fault", "rejoin": "--rejoin", "boards": "--boards",
    "journal": "--journal", "output": "-o", "zenoh": "--zenoh",
    "zenoh_config": "--zenoh-config", "publish_hz": "--publish-rate", "foxglove": "--foxglove",
    "for_s": "--for", "client_loss": "--loss", "state_dir": "--state",
    "canopen": "--canopen", "master_node": "--master-node", "directory": "-o",
    "junit": "--junit", "trace_dir": "--trace-dir", "pattern": "--only",
    "dbc_file": "--output", "trees": "--trees", "record": "--record",
}
"""The option of each input the API names (a key an error below ``cli/`` gives)."""

MISSING: dict[str, str] = {
    "interface": "use --virtual NAME for the virtual fleet, or -i/--interface (e.g. "
                 "socketcan, pcan, socketcand) with -c/--channel",
    "channels": "use -c/--channel (repeat it for several buses) or --topology FILE",
    "host": "give --host HOST --port PORT, the address the socketcand server (ucom fleet "
            "serve, socketcand) listens on",
    "topology": "give --topology FILE or --virtual NAME",
}
"""How to give an input that was missing (:class:`~ucom_tools.errors.MissingInput`)."""

MISSING_IN: dict[tuple[str, str], str] = {
    ("remote", "topology"): "give --topology FILE or a robot name",
}
"""The advice of :data:`MISSING` where a command (the first word after ``ucom``) has its
own way of giving the input."""

ADVICE_IN: dict[tuple[str, str], str] = {
    ("conformance", "pattern"): "see --list",
}
"""Where to look when an input of a command was not right (any other
:class:`~ucom_tools.errors.InputError` of the key), added in parentheses."""


def option_of(key: str) -> str:
    """The option that carries the API's input ``key`` (``key`` itself when none does)."""
    return OPTIONS.get(key, key)


def describe(err: BaseException, command: str | None = None) -> str:
    """The text of ``err`` on the command line of ``command`` (``ucom COMMAND ...``)."""
    if isinstance(err, InputError) and err.key is not None and err.file is None:
        text = f"{option_of(err.key)}: {err.reason}"
        if isinstance(err, MissingInput):
            advice = MISSING_IN.get((command or "", err.key), MISSING.get(err.key))
            return f"{text}: {advice}" if advice else text
        if isinstance(err, OutputExists):
            return f"{text}; --force replaces {'it' if len(err.paths) == 1 else 'them'}"
        advice = ADVICE_IN.get((command or "", err.key))
        return f"{text} ({advice})" if advice else text
    if isinstance(err, WriteError) and err.key is not None:
        return f"{option_of(err.key)}: {err.reason}"
    if isinstance(err, BusTaken):
        return f"{err}; --force starts anyway"
    return str(err)
