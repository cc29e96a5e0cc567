"""How long ago, in the few characters a live view's line has (``ucom browse`` and the
live view of ``ucom remote run``): one function, no imports, cheap for either."""

from __future__ import annotations


def age_text(seconds: float) -> str:
    """``12 ms``, ``3.4 s``, ``2 min``, ``5 h``."""
    seconds = max(0.0, seconds)
    if seconds < 1.0:
        return f"{seconds * 1000:.0f} ms"
    if seconds < 60.0:
        return f"{seconds:.1f} s"
    if seconds < 3600.0:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.0f} h"
