"""Every conformance case, in the protocol page's group order (the case modules register
themselves with :func:`~ucom_tools.conformance.case.case` when imported here)."""

from __future__ import annotations

from ucom_tools.conformance import cases_boot, cases_runtime  # noqa: F401 (they register)
from ucom_tools.conformance.case import GROUPS, REGISTRY, Case


def all_cases() -> list[Case]:
    """Every case, in the page's group order."""
    return sorted(REGISTRY, key=lambda c: GROUPS.index(c.group))
