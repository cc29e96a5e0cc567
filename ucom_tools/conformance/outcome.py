"""How a conformance case ends other than passing: it failed (what was expected, what
came) or it does not apply to these boards (why)."""

from __future__ import annotations


class CaseFailed(Exception):
    """The boards did not do what the page says: what was expected, what came."""

    def __init__(self, what: str, expected: object, got: object) -> None:
        super().__init__(f"{what}: expected {expected}, got {got}")
        self.what = what
        self.expected = expected
        self.got = got


class Skipped(Exception):
    """The case does not apply (a board lacks a capability); the reason."""
