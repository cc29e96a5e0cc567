"""The run time's hot modules, compiled with mypyc where that was built, and which of the
two this process runs.

Why: ARMAR-III at 1 kHz is eleven boards' programs, their motors and four simulated buses
stepped every millisecond, and the PC's loop taking ~24,000 frames a second; in pure
Python that is more than a two-core machine has to spare (``benchmarks/runtime.py``).
The same source files compiled by mypyc (C extensions beside the ``.py`` files, built by
``make compiled`` or ``python tools/compile.py``) run the same code about twice as fast.

The pure-Python code stays the reference: every module here is ordinary Python, the
package installs and runs without a compiler, and CI tests both.  This process runs the
sources, not the compiled modules, when

- ``UCOM_PURE_PYTHON=1`` is set (how CI tests the pure path);
- nothing was compiled (no ``_native.json`` beside this file: no compiler, or a plain
  ``pip install``);
- a compiled module no longer matches its source (a checkout edited or pulled after the
  build): then once, on stderr, which file changed and how to build again.

It is all or nothing: the compiled modules call each other natively, so one of them
compiled beside another one from source would not be the same program.
:func:`activate` (run by ``ucom_tools/__init__.py`` before anything else is imported)
decides; :func:`status` says what it decided (``ucom --version`` shows it).

What the compiled build needs of the code
-----------------------------------------
The one place that says it; a comment in a compiled module points here ("see
compiled.py") where the code would otherwise look odd.  mypyc compiles ordinary typed
Python, but not all of it alike, and some of it not at all:

- Compiled classes are native: their methods cannot be replaced, on the class or an instance.
  A class whose method a test or conformance case replaces (``Link.send_raw``: frames
  lost on purpose), or that extends a built-in type other than ``object``
  (``signals.Terminated``, a ``KeyboardInterrupt``), is compiled as a plain class,
  ``@mypyc_attr(native_class=False)`` (:mod:`ucom_tools.native`); its methods are
  compiled all the same.
- A class from source may extend a compiled one only where that one allows it,
  ``@mypyc_attr(allow_interpreted_subclasses=True)``: ``RemoteValues`` and ``RemoteLoop``,
  which ``RemotePart`` (from source) extends.
- Attributes are declared fields: a class-level default of an object (a frozenset, a
  ``ProgramSpec``) is not compiled as one, the instance would have none; set it in
  ``__init__`` (``exchange``, ``programs.lauron4``).  Types narrow as the type checker
  narrows them: a field read just after it was set to None is None to the compiled code,
  even where another thread set it meanwhile; read it through a method of its own
  (``serve.connection``'s ``_take_returned``).
- Module constants on a hot path are ``Final`` (read as C values, not looked up in the
  module's dictionary); state a hot path changes lives in an object's attributes, not in
  module globals (``signals._Deferred``: module state cost some 1,400 instructions a
  block).  A compiled caller in another module does not see defaults that name the
  callee's module constants: it gives every argument (``lauron4_leg.key_of``).  A method
  with literal defaults and ``**kwargs`` has no text signature mypyc can write
  ("non-default argument follows default argument"): its defaults are named constants
  (``transport.socketcand``).
- ``raise ... from err`` leaves ``__cause__`` unset: where a caller reads the cause, it
  is set by hand (``virtual.canbus._init_error``: the CLI gives the cause's exit code).
- Some builtins and idioms go through the interpreter: ``round(x)`` looks up
  ``float.__round__`` each time (some 600 instructions: ``hardware.numeric``'s
  ``round_half_even`` instead), ``zip`` is not compiled (index loops on the programs' hot
  paths), ``(t, *args)`` builds a list first (``(t,) + args`` in ``bus.clock``).  A
  generator expression given to a call (``bytes(c >> 8 for c in table)``, ``any(...)``)
  is built as a whole list first: the same result, only not lazy (``make compiled``
  lists each one as a warning, "Treating generator comprehension as list").
- Native integers: ``i64`` annotations (``mypy_extensions``, imported under
  ``TYPE_CHECKING``: annotations of locals are never evaluated) make loop indices and
  arithmetic 64-bit C integers (``wire.canbits``, ``wire.socketcand``); lookup tables are
  ``bytes``, whose items are native integers, not tuples of objects to unbox.
- Where the fastest compiled code and the fastest interpreted code differ, a module keeps
  both, chosen by ``_NATIVE: Final = not __file__.endswith(".py")`` (``bus.clock``'s
  event heap, ``wire.socketcand``'s byte scan); the tests, run both ways, hold them to
  one result.
- A compiled loop never passes through the interpreter, so a pending signal handler
  would wait for the end of the run: the loop calls ``ops.realtime.let_signals_in`` (from
  source, not in :data:`MODULES`) once a cycle.

Beyond that the compiled modules are the pure-Python modules: the frame traces of
``tests/test_fidelity.py`` are the same bit for bit either way (``make test`` runs it
both ways).
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
import os
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

MODULES: tuple[str, ...] = (
    "ucom_tools.ops.edges",
    "ucom_tools.ops.exchange",
    "ucom_tools.ops.remote.conversations",
    "ucom_tools.ops.remote.loop",
    "ucom_tools.ops.remote.values",
    "ucom_tools.ops.remote.watch",
    "ucom_tools.protocol.dispatch",
    "ucom_tools.protocol.frames",
    "ucom_tools.protocol.link",
    "ucom_tools.protocol.mca",
    "ucom_tools.protocol.periodic",
    "ucom_tools.protocol.routing",
    "ucom_tools.protocol.sending",
    "ucom_tools.protocol.traffic",
    "ucom_tools.protocol.turns",
    "ucom_tools.signals",
    "ucom_tools.transport.socketcand",
    "ucom_tools.transport.socketcand_frames",
    "ucom_tools.transport.tcp",
    "ucom_tools.virtual.board.application",
    "ucom_tools.virtual.board.bootloader",
    "ucom_tools.virtual.board.nvmem",
    "ucom_tools.virtual.board.port",
    "ucom_tools.virtual.board.programming",
    "ucom_tools.virtual.board.receiver",
    "ucom_tools.virtual.board.runtime",
    "ucom_tools.virtual.board.ucom",
    "ucom_tools.virtual.bus.clock",
    "ucom_tools.virtual.bus.simbus",
    "ucom_tools.virtual.canbus",
    "ucom_tools.virtual.hardware.fpga",
    "ucom_tools.virtual.hardware.lauron4_leg",
    "ucom_tools.virtual.hardware.motor",
    "ucom_tools.virtual.hardware.numeric",
    "ucom_tools.virtual.hardware.plant",
    "ucom_tools.virtual.programs.armar3",
    "ucom_tools.virtual.programs.armar3_axis",
    "ucom_tools.virtual.programs.base",
    "ucom_tools.virtual.programs.idle",
    "ucom_tools.virtual.programs.lauron4",
    "ucom_tools.virtual.serve.connection",
    "ucom_tools.virtual.serve.outbox",
    "ucom_tools.wire.canbits",
    "ucom_tools.wire.mca",
    "ucom_tools.wire.socketcand",
)
"""The modules compiled (``tools/compile.py`` reads this tuple; kept sorted): those the
profiles of the served fleet and of the PC side put on top.  What they need of the code:
the module docstring."""

GROUP = "ucom_tools._native"
"""The compiled modules' shared library (``ucom_tools/_native__mypyc*.so``)."""

MANIFEST = Path(__file__).with_name("_native.json")
"""Written by the build: each compiled module's source file and its SHA-256."""

PURE_ENV = "UCOM_PURE_PYTHON"

PACKAGE_ROOT = Path(__file__).resolve().parent


@dataclass(frozen=True)
class Status:
    """What :func:`activate` decided: ``compiled`` or not, and why (for ``--version``)."""

    compiled: bool
    reason: str


_status: Status | None = None


def source_of(module: str) -> Path:
    """The source file of ``module`` (one of :data:`MODULES`)."""
    return PACKAGE_ROOT.joinpath(*module.split(".")[1:]).with_suffix(".py")


def digest(path: Path) -> str:
    import hashlib  # here, and json in _decide: a pure-Python ``ucom --help`` needs neither

    return hashlib.sha256(path.read_bytes()).hexdigest()


def changed_sources(manifest: dict[str, str], modules: Sequence[str] = MODULES,
                    ) -> list[str]:
    """The modules whose source differs from the build's (or that it did not build)."""
    changed = []
    for module in modules:
        built = manifest.get(module)
        try:
            now = digest(source_of(module))
        except OSError:
            now = None
        if built is None or built != now:
            changed.append(module)
    return changed


class _Sources:
    """Imports the compiled modules from their ``.py`` files (before the extension that
    the normal path finder would prefer); a meta path finder as ``sys.meta_path`` takes
    them (not derived from ``importlib.abc.MetaPathFinder``: its import brings
    importlib.resources, tempfile and shutil, which ``ucom --help`` does not need)."""

    def find_spec(self, fullname: str, path: Sequence[str] | None,
                  target: ModuleType | None = None) -> importlib.machinery.ModuleSpec | None:
        if fullname not in MODULES:
            return None
        return importlib.util.spec_from_file_location(fullname, source_of(fullname))


def _decide() -> Status:
    if os.environ.get(PURE_ENV, "") not in ("", "0"):
        return Status(False, f"pure Python ({PURE_ENV} is set)")
    import json

    try:
        manifest = json.loads(MANIFEST.read_text())
    except FileNotFoundError:
        return Status(False, "pure Python (not compiled: make compiled builds it)")
    except (OSError, ValueError) as err:
        return Status(False, f"pure Python ({MANIFEST.name} unreadable: {err})")
    if not isinstance(manifest, dict):
        return Status(False, f"pure Python ({MANIFEST.name} is not a table)")
    changed = changed_sources(manifest)
    if changed:
        shown = ", ".join(str(source_of(m).relative_to(PACKAGE_ROOT.parent))
                          for m in changed[:3])
        more = f" and {len(changed) - 3} more" if len(changed) > 3 else ""
        reason = f"pure Python ({shown}{more} changed since the build)"
        sys.stderr.write(f"ucom-tools: the compiled modules are older than their sources "
                         f"({shown}{more}); running the pure-Python code, which is slower. "
                         "'make compiled' builds them again.\n")
        return Status(False, reason)
    return Status(True, f"compiled with mypyc ({len(MODULES)} modules)")


def activate() -> Status:
    """Decide once per process; for pure Python put the source finder first."""
    global _status
    if _status is None:
        _status = _decide()
        if not _status.compiled and not any(isinstance(f, _Sources) for f in sys.meta_path):
            sys.meta_path.insert(0, _Sources())
    return _status


def status() -> Status:
    return activate()
