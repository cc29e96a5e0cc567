"""The options of dsp_console2can (dissertation B.3.1) as one table.

Read by the console (its menu, its keys, which options need init), by the subcommands
(their help text) and by the tests that hold ``man/ucom.1`` and ``man/ucom-console.1`` to
it, so the three can never disagree.  Also the small argument parsers both share.
"""

from __future__ import annotations

from dataclasses import dataclass

from ucom_tools.errors import InputError

BOARD = "BOARD is a seq ID (1-31), F<n> for a fixed ID, or 'all'; BUS:<n> picks one bus."
ONE_BOARD = "BOARD is a seq ID (1-31) or F<n> for a fixed ID; BUS:<n> picks one bus."
"""What a command's BOARD argument takes (all boards, or one)."""


@dataclass(frozen=True)
class MenuOption:
    number: int
    command: str
    """The ``ucom`` subcommand (and the console's name for it)."""
    title: str
    """The name in the dissertation's menu."""
    summary: str
    needs_init: bool = False
    """The boards must have seq IDs (a completed init, option 2): the option refuses and
    explains otherwise.  Boards with a fixed ID work without."""
    aliases: tuple[str, ...] = ()


OPTIONS: tuple[MenuOption, ...] = (
    MenuOption(1, "reset", "Reset All", "reset every board and list who answered"),
    MenuOption(2, "init", "Init", "number the boards along the init line, check the wiring"),
    MenuOption(3, "info", "GetInfo", "program name, date, ProgID, flags of a board", True,
               ("getinfo",)),
    MenuOption(4, "prog-enable", "SetProgEnable", "enable programming of a board or all",
               True, ("progenable",)),
    MenuOption(5, "program", "Program", "program a board, or all ProgEnabled boards", True),
    MenuOption(6, "extram-load", "ExtRAMLoad", "load the image into external RAM", True,
               ("extramload",)),
    MenuOption(7, "start", "Start", "start the program in flash or ExtRAM", True),
    MenuOption(8, "autostart", "SetAutoStart", "start the flash program after every reset",
               True, ("setautostart",)),
    MenuOption(9, "xreset", "XReset", "clear AutoStart and reset"),
    MenuOption(10, "set-init-in", "SetInitIn", "drive a board's init input", True,
               ("setinitin",)),
    MenuOption(11, "set-init-out", "SetInitOut", "drive a board's init output", True,
               ("setinitout",)),
    MenuOption(12, "set-seqid", "SetSeqID", "give a board another seq ID", True,
               ("setseqid",)),
    MenuOption(13, "count", "Count", "GetInfo of every board that has a number"),
    MenuOption(14, "first", "Get First", "which board is first on the init line",
               aliases=("getfirst",)),
    MenuOption(15, "last", "Get Last", "which board is last on the init line",
               aliases=("getlast",)),
    MenuOption(16, "list-update", "DSPListUpdate", "build the list of active boards",
               aliases=("dsplistupdate",)),
    MenuOption(17, "list", "Print DspList", "print the list of active boards",
               aliases=("printdsplist",)),
    MenuOption(18, "load", "Load S-Record File",
               "load the image to program (S-record or Intel HEX)"),
    MenuOption(19, "progid", "Calc ProgID", "the ProgID of the loaded image",
               aliases=("calcprogid",)),
    MenuOption(20, "progall", "ProgAll", "ProgEnable every board, then program them all"),
    MenuOption(21, "reset-one", "Reset Specific", "reset one board", True,
               ("resetspecific",)),
)

BY_NUMBER = {o.number: o for o in OPTIONS}

NEEDS_INIT_NOTE = ("The dissertation marks options 3, 4, 5, 10, 11, 12 and 21 as needing a "
                   "completed init; ucom adds 6, 7 and 8, which address boards by seq ID too.")


def option(number: int) -> MenuOption:
    return BY_NUMBER[number]


def label(number: int) -> str:
    """``option 3 (GetInfo)`` - how messages name an option."""
    o = BY_NUMBER[number]
    return f"option {o.number} ({o.title})"


FLASHING = frozenset({5, 6, 20})
"""The options that program boards (``ucom flash`` runs the init chain itself)."""


def init_advice(bus: str, number: int, *, console: bool = False) -> str:
    """What to do when option ``number`` finds no board with a seq ID on ``bus``
    (:class:`~ucom_tools.ops.options.NotInitialised`): on the command line, or in the
    console (``console``), which has no --init and runs the init chain as option 2."""
    what = label(number)
    first = "run option 2 (Init) first" if console else "run 'ucom init' first"
    if number in FLASHING:
        rest = ("" if console else ", or add --init to this command") + (
            "; 'ucom flash' runs it itself.")
    else:
        rest = " (the boards keep their seq IDs until power-off)" + (
            "" if console else ", or add --init to this command") + "."
    return (f"{bus}: no board has a seq ID yet. {what[:1].upper() + what[1:]} works only "
            f"after a successful init chain (option 2): {first}{rest}")


def help_text(number: int, detail: str = "") -> str:
    """The first lines of a subcommand's help, from the table."""
    o = BY_NUMBER[number]
    text = f"Option {o.number}, {o.title}: {o.summary}"
    if o.needs_init:
        text += " (needs init: option 2, or --init)"
    return text + "." + (f"\n\n{detail}" if detail else "")


# ----------------------------------------------------------------------------- arguments
def parse_level(text: str) -> int:
    """An init pin level: 1 = set (drive the pin low), 0 = release."""
    t = text.strip().lower()
    if t in ("set", "1", "lo", "low", "on"):
        return 1
    if t in ("release", "0", "hi", "high", "off"):
        return 0
    raise InputError(f"{text!r}: LEVEL is 'set' (drive the pin low) or 'release'", key="LEVEL")


def parse_flag(text: str | None) -> int:
    """on/off (default on)."""
    if text is None or text.lower() in ("on", "1", "yes", "set"):
        return 1
    if text.lower() in ("off", "0", "no", "clear"):
        return 0
    raise InputError(f"{text!r}: expected on or off")
