"""The catalogue of mutant boards' defects: documented deviations from
``man/ucom-protocol.7`` that a virtual UCoM can be given, to prove a conformance suite
(a suite is only as good as the defects it catches).

Each :class:`Defect` has a one-line title, the section of the page it violates and the
symptom a host observes on the bus.  A board gets a defect from its topology
(``defect = "NAME"``, checked here by the topology parser) or from its fleet
(``ucom fleet serve --defect NAME``); the virtual boards carry the defects out
(:mod:`ucom_tools.virtual.board.mutants`: their figures and the hooks' helpers).

The words: a mutant board's *defect* is a protocol deviation it has for life; an injected
*fault* (:mod:`ucom_tools.config.scenario`) is what happens to a robot at run time (a
power loss, a cut cable); a *user error* is a mistake in what a user gives ucom.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from ucom_tools.errors import InputError


@dataclass(frozen=True)
class Defect:
    """One documented defect of a mutant board."""

    name: str
    title: str
    """One line: what the board does wrong."""
    section: str
    """The section of ``man/ucom-protocol.7`` the defect violates."""
    symptom: str
    """What a host observes on the bus."""

    def as_dict(self) -> dict[str, str]:
        return asdict(self)


# ---------------------------------------------------------------------- the names
SEQ_FROM_ZERO = "seq-from-zero"
INIT_TWICE = "init-twice"
INFO_SWAPPED = "info-swapped"
WRONG_PROGID = "wrong-progid"
ACCEPT_BAD_PROGID = "accept-bad-progid"
IGNORE_ALIVE = "ignore-alive"
SO_SLOW = "so-slow"
LATE_ANSWER = "late-answer"
PROMISCUOUS = "promiscuous"
IGNORE_INITOUT = "ignore-initout"
DESCR_TRUNCATED = "descr-truncated"
NO_RANGE_CHECK = "no-range-check"
CI_WHILE_LATCHED = "ci-while-latched"
AUTOSTART_LOST = "autostart-lost"
XRESET_KEEPS_AUTOSTART = "xreset-keeps-autostart"
UNKNOWN_FUNCTION_SILENT = "unknown-function-silent"
DUMP_OFF_BY_ONE = "dump-off-by-one"
READY_COUNTS_WRONG = "ready-counts-wrong"
DIGEST_UNKNOWN = "digest-unknown"
DIGEST_WRONG = "digest-wrong"

CATALOGUE: tuple[Defect, ...] = (
    Defect(SEQ_FROM_ZERO, "the init chain numbering starts at 0",
           "INIT CHAIN (step 2: the first board takes seq ID 1)",
           "the first board's Init Ack (ASSIGNED) says seq ID 0 and comes from board number 0 "
           "(0x0C0); no board answers as seq ID 1; asked NEXT n, a board takes n - 1"),
    Defect(INIT_TWICE, "every Init request the board claims is answered with two Init Acks",
           "INIT CHAIN (steps 2 and 3: the board that takes the number answers)",
           "two identical Init Acks (ASSIGNED, same seq ID and serial) for one BEGIN or NEXT"),
    Defect(INFO_SWAPPED, "the Info record carries the serial number and the ProgID swapped",
           "MESSAGES, 5 Info (frame 1 ProgID, frame 3 serial)",
           "Info frame 1 carries the board's serial number, frame 3 the ProgID of its program"),
    Defect(WRONG_PROGID, "after a transfer the board reports a ProgID one more than the "
           "image's", "PROGRAMMING (step 5) and PROGID",
           "Program Finished VERIFIED with ProgID image + 1, and Info frame 1 says image + 1: "
           "the host counts the board as not programmed"),
    Defect(ACCEPT_BAD_PROGID, "a transfer whose ProgID check fails is accepted",
           "PROGRAMMING (step 5; a board never starts a program that did not verify)",
           "after Program Finished PROGID_MISMATCH, Info says the flash program is valid and "
           "Start answers Ready(STARTED) instead of Error NO_PROGRAM"),
    Defect(IGNORE_ALIVE, "the run-time watchdog never fires",
           "RUN TIME, Watchdog",
           "without MCA Alive the board stays RUNNING: no Error WATCHDOG, no latch, its SO "
           "maps keep coming and its motors keep driving"),
    Defect(SO_SLOW, "SO maps are sent every 1.1 x their period (10 % slow)",
           "RUN TIME, Messages (14 MCA Sensor Output: every period cycles)",
           "an SO map of period p cycles comes every 1.1 p cycles on average, on the cycle "
           "grid (period 10: every 11 cycles; period 5: 6 and 5 cycles in turn)"),
    Defect(LATE_ANSWER, "Info requests and SetStatus are answered 3 x later than their "
           "deadline", "TIMEOUTS (a request is answered within 0.05 s)",
           "the 10 Info frames, Ready(STATUS) and the Errors answering SetStatus come 0.15 s "
           "after the request; the host asks again (what they ask for is done at once)"),
    Defect(PROMISCUOUS, "the board acts on SetStatus frames addressed to another board's seq "
           "ID as if they were its own", "IDENTIFIERS, Addressing",
           "a SetStatus to seq ID n changes this board too, and it answers with Ready(STATUS) "
           "from its own number"),
    Defect(IGNORE_INITOUT, "SetStatus INIT_OUT has no effect",
           "MESSAGES, 7 SetStatus (4 INIT_OUT)",
           "SetStatus INIT_OUT is answered with Ready(STATUS), but Report STATUS shows the "
           "init output unchanged (and the next board's init input with it)"),
    Defect(DESCR_TRUNCATED, "MCA DumpIO Descr sends edge names cut to 16 characters",
           "RUN TIME, Values (the record: a name has at most 40 characters)",
           "longer names arrive cut: armar3 PAR 3 is described as 'Set Joint Moving'"),
    Defect(NO_RANGE_CHECK, "PAR and CI values outside their edge's range are taken",
           "RUN TIME, Bad input (Error OUT_OF_RANGE, nothing of the frame is taken)",
           "MCA Parameter / Controller Input with a value outside its range is acknowledged "
           "with MCA Ready and reads back; a CI map slot out of range is taken without Error"),
    Defect(CI_WHILE_LATCHED, "while latched by the watchdog, CI frames are taken",
           "RUN TIME, Watchdog and Bad input (CI refused with Error LATCHED)",
           "after the watchdog latch, MCA Controller Input is acknowledged with MCA Ready "
           "(LATCHED) and its value reads back; no Error LATCHED (the motors stay off)"),
    Defect(AUTOSTART_LOST, "the AutoStart flag is not kept across a reset or a power "
           "cycle",
           "BOOTLOADER (non-volatile: the AutoStart flag)",
           "after a Reset or a power cycle the board stays in its bootloader and Info's "
           "AutoStart flag is clear"),
    Defect(XRESET_KEEPS_AUTOSTART, "XReset does not clear AutoStart",
           "MESSAGES, 1 XReset",
           "after XReset, Ready(BOOT) says RUNNING_FLASH (the program started again) and "
           "Info keeps the AutoStart flag"),
    Defect(UNKNOWN_FUNCTION_SILENT, "a frame of an unassigned function (28-31) addressed to "
           "the board gets no Error", "BOOTLOADER, Frames a board does not take",
           "no Error UNKNOWN_FUNCTION for a frame of function 28-31 addressed to the board"),
    Defect(DUMP_OFF_BY_ONE, "MCA Dump CI answers carry the values of the next index",
           "RUN TIME, Messages (24 MCA Dump CI, 27 MCA DSP CI)",
           "MCA DSP CI for index i carries the value of i + 1 (0 past the last edge): armar3 "
           "PAR 0-1 read back 16000, 0 instead of 1000, 16000"),
    Defect(READY_COUNTS_WRONG, "MCA Ready reports one SO edge more than the program has",
           "RUN TIME, Messages (20 MCA Ready: [5] number of SO edges)",
           "every MCA Ready says one SO edge more (armar3: 21 instead of 20); describing "
           "that edge gets Error UNKNOWN_EDGE"),
    Defect(DIGEST_UNKNOWN, "the program does not know the description's digest (an older "
           "program)", "RUN TIME, Messages (22 MCA DumpIO Descr Request, DLC 1: the digest)",
           "MCA DumpIO Descr Request with DLC 1 gets Error BAD_LENGTH instead of the digest; "
           "a rejoining board's records are read again, four edges at a time"),
    Defect(DIGEST_WRONG, "the description's digest is not the CRC-32 of the records the "
           "board describes", "RUN TIME, Messages (23 MCA DumpIO Descr: the digest)",
           "the digest answer carries the CRC-32 of the records with its lowest bit "
           "inverted: a host that compares it with the records it read finds them different"),
)

BY_NAME: dict[str, Defect] = {f.name: f for f in CATALOGUE}
NAMES: tuple[str, ...] = tuple(BY_NAME)


def defects() -> tuple[Defect, ...]:
    """The catalogue, in its order (for ``ucom fleet defects``: :func:`listing` as text,
    :meth:`Defect.as_dict` for ``--json``)."""
    return CATALOGUE


def listing() -> str:
    """The catalogue as text, a defect per paragraph: name and title, section, symptom."""
    return "\n\n".join(f"{f.name}: {f.title}\n  violates: {f.section}\n  symptom: {f.symptom}"
                       for f in CATALOGUE)


def unknown(name: str) -> str:
    """The message for a name not in the catalogue."""
    return f"unknown defect {name!r}; known: " + ", ".join(NAMES)


def check(name: str | None, *, key: str = "defect") -> str | None:
    """``name`` if it is a defect of the catalogue (or None); InputError naming ``key``
    and listing the known names otherwise."""
    if name is not None and name not in BY_NAME:
        raise InputError(unknown(name), key=key)
    return name


