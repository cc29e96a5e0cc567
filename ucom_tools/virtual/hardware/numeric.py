"""Numeric helpers the board models (programs and plants) share in their inner loops: a
16-bit register's value as a signed number (:func:`signed16`), a value bounded to a range
(:func:`clamp`), and :func:`round_half_even`, the same value as the builtin ``round`` for
every float.

Why not ``round``: compiled, it goes through the interpreter (some 600 instructions, see
:mod:`ucom_tools.compiled`), and ARMAR-III's axes round about 120 times a virtual
millisecond; :func:`round_half_even` is a few comparisons.  ``tests/test_numeric.py`` holds
it to ``round`` (ties, signs, the last float below a half, the edges of exact integers,
random values of every magnitude).
"""

from __future__ import annotations


def round_half_even(x: float) -> int:
    """``round(x)``: the nearest integer, a tie to the even one; ValueError for NaN,
    OverflowError for an infinity, as ``round``.

    ``int(x)`` truncates toward zero exactly, and ``x - int(x)`` is exact too (for
    ``|x| >= 1`` both lie within a factor of two, Sterbenz's lemma; below 1 the
    integer part is 0), so comparing that fraction with one half decides as ``round``
    does."""
    i = int(x)
    frac = x - i
    if frac > 0.5:
        return i + 1
    if frac < -0.5:
        return i - 1
    if frac == 0.5:
        return i + 1 if i & 1 else i
    if frac == -0.5:
        return i - 1 if i & 1 else i
    return i


def signed16(value: int) -> int:
    """The low 16 bits of ``value`` as a signed (two's complement) number."""
    value &= 0xFFFF
    return value - 0x10000 if value & 0x8000 else value


def clamp(value: float, low: float, high: float) -> float:
    """``value`` bounded to ``low .. high`` (a NaN as it is)."""
    return low if value < low else high if value > high else value
