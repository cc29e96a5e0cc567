"""What the compiled modules (:mod:`ucom_tools.compiled`) tell the compiler, at no cost
where nothing is compiled.

:func:`mypyc_attr` is ``mypy_extensions.mypyc_attr`` where that is installed (it comes
with mypy, which a build needs anyway), else a decorator that changes nothing: the
pure-Python run time needs neither mypy nor mypy_extensions.  Used for
``native_class=False`` and ``allow_interpreted_subclasses=True``; when and why: the
docstring of :mod:`ucom_tools.compiled`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")

try:
    from mypy_extensions import mypyc_attr
except ImportError:  # pragma: no cover - only without mypy (a plain install)
    def mypyc_attr(*attrs: str, **kwattrs: object) -> Callable[[T], T]:
        def keep(x: T) -> T:
            return x
        return keep

__all__ = ["mypyc_attr"]
