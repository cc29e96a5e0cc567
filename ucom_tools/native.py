"""What the modules compiled with mypyc (:mod:`ucom_tools.compiled`) tell the compiler,
at no cost where nothing is compiled.

:func:`mypyc_attr` is ``mypy_extensions.mypyc_attr`` where that is installed (it comes
with mypy, which a build needs anyway), else a decorator that changes nothing: the
pure-Python run time needs neither mypy nor mypy_extensions.  Used for

- ``native_class=False``: a class whose methods tests or conformance cases replace on
  an instance (``Link.send_raw``), or that extends a built-in type other than
  ``object`` (:class:`~ucom_tools.signals.Terminated`, a ``KeyboardInterrupt``); its
  methods are compiled all the same;
- ``allow_interpreted_subclasses=True``: a compiled class that a class from source
  extends (``RemotePart`` of ``RemoteLoop``).
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
