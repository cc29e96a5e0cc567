"""The options of dsp_console2can as ``ucom`` subcommands, one module each.

A module is named after its command (``reset.py`` is ``ucom reset``, ``dsp_list.py``
``ucom list``, ``extram_load.py`` ``ucom extram-load``) and says which option of the
console it is; :data:`ucom_tools.cli.main.COMMANDS` finds each command there and imports
its module only when the command is used.  Each is thin click glue: it parses its
arguments, runs an operation of :mod:`ucom_tools.ops` and prints its result (a table, or
JSON with ``--json``); the exit code says how it went (:mod:`ucom_tools.cli.exitcodes`).
Help texts begin with the option table of :mod:`ucom_tools.cli.menu`, which the console
shares; what several commands share is in :mod:`.common`.  ``ucom flash`` and the code
``program`` and ``extram-load`` share with it are in :mod:`ucom_tools.cli.flash`.
"""
