"""``ucom fleet serve``'s extension of the socketcand protocol: injecting a fault into the
served fleet by hand (``ucom fleet fault``; ``ucom-protocol(7)``, SOCKETCAND).

A control connection greets as any other (``< hi >``) and, before any ``< open >``, asks::

    client  < ucom_fault TARGET KIND [SECONDS] >
    server  < ok TEXT >                 (what was done, in a sentence)
       or   < error ucom_fault: TEXT >  (a target the fleet lacks, a kind that does not
                                         fit it, a malformed element: nothing was done)
       or   < error ucom_fault failed: TEXT >   (the fleet could not apply it)

TARGET is ``BUS/BOARD`` (a board: ``CAN0/3``), ``BUS`` (a bus: ``CAN0``) or ``robot``;
KIND one of ``power-off``, ``reset``, ``bus-off``, ``cable``, ``estop``; SECONDS how long
until it ends (a decimal number; without it, the kind's default: ``reset`` 0, the
others have none and are refused).  The client may ask again on the same connection, or
close it.  A server that does not know the element (socketcand itself, an older ucom)
answers ``< error unsupported command ... >`` or nothing: not a fleet that takes faults.
python-can's socketcand client never sends it, so it is unaffected.

The elements as pure code, one copy for both ends: :func:`fault_element` and
:func:`parse_fault` (the request), :func:`ok_element` and :func:`answer` (the answers).
"""

from __future__ import annotations

import math
import re
from typing import Final

from ucom_tools.wire.socketcand import ElementError, element_words, quote

COMMAND: Final = "ucom_fault"
"""The element's command word."""
REFUSED: Final = f"{COMMAND}:"
"""How the server's refusal (nothing was done: bad input) begins."""
FAILED: Final = f"{COMMAND} failed:"
"""How the server's failure (the fleet could not apply it) begins."""
_SECONDS: Final = re.compile(r"\d+(?:\.\d+)?|\.\d+", re.ASCII)
_WORD: Final = re.compile(r"[!-~]+", re.ASCII)


def fault_element(target: str, kind: str, seconds: float | None = None) -> bytes:
    """``< ucom_fault TARGET KIND [SECONDS] >``; ValueError for words that cannot travel
    (blanks, ``<``, ``>``, non-ASCII) or seconds that are not a finite number >= 0."""
    for word in (target, kind):
        if not _WORD.fullmatch(word) or "<" in word or ">" in word:
            raise ValueError(f"{word!r} cannot be sent in an element")
    parts = [COMMAND, target, kind]
    if seconds is not None:
        if not math.isfinite(seconds) or seconds < 0:
            raise ValueError(f"seconds must be a finite number >= 0, not {seconds!r}")
        parts.append(f"{seconds:.6f}".rstrip("0").rstrip("."))
    return ("< " + " ".join(parts) + " >").encode("ascii")


def parse_fault(args: list[str]) -> tuple[str, str, float | None]:
    """TARGET, KIND and SECONDS (None: not given) of the words after ``ucom_fault``;
    :class:`ElementError` with the server's answer when malformed."""
    if len(args) not in (2, 3):
        raise ElementError(f"{REFUSED} usage: {COMMAND} TARGET KIND [SECONDS]")
    target, kind = args[0], args[1]
    seconds: float | None = None
    if len(args) == 3:
        if not _SECONDS.fullmatch(args[2]):
            raise ElementError(f"{REFUSED} SECONDS {quote(args[2])} is not a decimal number")
        seconds = float(args[2])
    return target, kind, seconds


def ok_element(text: str) -> str:
    """``< ok TEXT >`` with ``TEXT`` safe in an element (printable ASCII, no brackets)."""
    return f"< ok {_clean(text)} >"


def refusal(text: str, *, failed: bool = False) -> str:
    """The text of ``< error ... >`` for a refused (or, ``failed``, a failed) request."""
    return f"{FAILED if failed else REFUSED} {_clean(text)}"


def _clean(text: str) -> str:
    return "".join(c if " " <= c <= "~" and c not in "<>" else "?" for c in text)


def answer(element: bytes) -> tuple[str, str]:
    """The server's answer element as (``ok``, TEXT), (``refused``, TEXT), (``failed``,
    TEXT) or (``other``, the whole element): an answer of a server that does not take
    faults."""
    try:
        words = element_words(element)
    except ElementError:
        return "other", element.decode("ascii", "replace")
    text = " ".join(words[1:])
    if words[0] == "ok":
        return "ok", text
    if words[0] == "error" and text.startswith(FAILED):
        return "failed", text[len(FAILED):].strip()
    if words[0] == "error" and text.startswith(REFUSED):
        return "refused", text[len(REFUSED):].strip()
    return "other", " ".join(words)
