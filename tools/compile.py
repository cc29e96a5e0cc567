#!/usr/bin/env python3
"""Compile the run time's hot modules (:data:`ucom_tools.compiled.MODULES`) with mypyc, in
place: a C extension beside each ``.py`` file, their shared library
``ucom_tools/_native__mypyc*.so``, and ``ucom_tools/_native.json`` (each source's
SHA-256, so that a process runs the extensions only while they match their sources).

``make compiled`` runs it (``make demo``, ``make test`` and ``make bench`` do so first).
Without a C compiler or mypyc it says so and leaves the package pure Python (exit 0:
ucom-tools runs either way), unless ``--strict`` (exit 1).  ``--clean`` removes what a
build left, so that the sources run again.
"""

from __future__ import annotations

import argparse
import ast
import hashlib
import json
import os
import shutil
import sys
import tempfile
import types
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "ucom_tools"
LISTING = PACKAGE / "compiled.py"
MANIFEST = PACKAGE / "_native.json"
BUILD = ROOT / "build" / "mypyc"
DONE = BUILD / "done"
"""Touched after every attempt, compiled or not (``make``'s target: a machine without a
compiler does not try again at every ``make test``, only when a source changes)."""


def listed() -> tuple[tuple[str, ...], str]:
    """MODULES and GROUP of ucom_tools/compiled.py, read without importing the package
    (importing it would load the very extensions this replaces)."""
    found: dict[str, object] = {}
    for node in ast.parse(LISTING.read_text()).body:
        target = node.target if isinstance(node, ast.AnnAssign) else (
            node.targets[0] if isinstance(node, ast.Assign) else None)
        if isinstance(target, ast.Name) and target.id in ("MODULES", "GROUP"):
            assert node.value is not None
            found[target.id] = ast.literal_eval(node.value)
    modules, group = found["MODULES"], found["GROUP"]
    assert isinstance(modules, tuple) and isinstance(group, str)
    return modules, group


def source(module: str) -> Path:
    return ROOT.joinpath(*module.split(".")).with_suffix(".py")


def built_files() -> list[Path]:
    """The extensions a build leaves in the package (any Python version's)."""
    return sorted(p for p in PACKAGE.rglob("*.so"))


def clean() -> None:
    for path in built_files():
        path.unlink()
    MANIFEST.unlink(missing_ok=True)
    shutil.rmtree(BUILD, ignore_errors=True)


def compiler() -> str | None:
    """The C compiler Python's build would call, if it is there."""
    import sysconfig
    cc = (os.environ.get("CC") or sysconfig.get_config_var("CC") or "cc").split()[0]
    return shutil.which(cc)


def _compile_side_by_side(compiler: Any, sources: list[str], output_dir: str | None = None,
                          macros: Any = None, include_dirs: Any = None, debug: bool = False,
                          extra_preargs: Any = None, extra_postargs: Any = None,
                          depends: Any = None) -> list[str]:
    """``CCompiler.compile`` with the source files compiled side by side, one per core,
    the largest first.  distutils compiles an extension's sources one after the other
    (``build_ext --parallel`` runs whole extensions side by side), so the one group
    library, most of the C code, would keep one core busy and the other idle."""
    macros, objects, extra_postargs, pp_opts, todo = compiler._setup_compile(
        output_dir, macros, include_dirs, sources, depends, extra_postargs)
    cc_args = compiler._get_cc_args(pp_opts, debug, extra_preargs)
    jobs = sorted(((obj, *todo[obj]) for obj in objects if obj in todo),
                  key=lambda job: -os.path.getsize(job[1]))
    with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        for done in [pool.submit(compiler._compile, obj, src, ext, cc_args, extra_postargs,
                                 pp_opts) for obj, src, ext in jobs]:
            done.result()  # the first failure, once every compiler has ended
    return objects


def _build_ext() -> type:
    """setuptools' build_ext, compiling each extension's sources side by side where the
    compiler is distutils' usual one (a compiler with its own ``compile``, MSVC's, is left
    as it is)."""
    from setuptools.command.build_ext import build_ext

    class SideBySide(build_ext):  # type: ignore[misc]
        def build_extensions(self) -> None:
            # (by name: setuptools' distutils may be loaded under two module names)
            if type(self.compiler).compile.__qualname__ == "CCompiler.compile":
                self.compiler.compile = types.MethodType(_compile_side_by_side,
                                                         self.compiler)
            super().build_extensions()

    return SideBySide


def build(modules: tuple[str, ...], group: str) -> None:
    import warnings

    if compiler() is None:
        raise RuntimeError("no C compiler")
    from mypyc.build import mypycify  # only here: the package itself never needs mypyc
    from setuptools import setup

    warnings.simplefilter("ignore")  # setuptools' notes on pyproject.toml, not ours

    clean()  # never a mixture of an old build and a new one
    os.chdir(ROOT)  # mypycify takes paths relative to the project (and its mypy config)
    BUILD.mkdir(parents=True, exist_ok=True)
    # mypyc's type check keeps a cache of its own: in .mypy_cache (mypy's SQLite shards)
    # it met `make lint`'s mypy, which runs beside the build, and mypy failed with an
    # INTERNAL ERROR (a clean clone's CI, 2026-12-08)
    os.environ["MYPY_CACHE_DIR"] = str(BUILD / "mypy-cache")
    # one C file per module (multi_file), compiled side by side on every core
    # (_compile_side_by_side), into one shared library: the modules still call each other
    # natively (as one C file did, at the same speed: benchmarks/runtime_fleet.py,
    # callgrind); the build takes a third of the time one C file took
    extensions = mypycify([str(source(m).relative_to(ROOT)) for m in modules],
                          opt_level="3", group_name=group, multi_file=True,
                          target_dir=str(BUILD / "c"))
    # the group's headers go where its dotted name says (c/ucom_tools/), the C files that
    # include them to c/ (mypy 2.4)
    headers = str(BUILD.joinpath("c", *group.split(".")[:-1]))
    for extension in extensions:
        extension.include_dirs.append(headers)
    setup(name="ucom-tools-native", ext_modules=extensions,
          cmdclass={"build_ext": _build_ext()}, script_args=[
        "--quiet", "build_ext", "--inplace", "--build-temp", str(BUILD / "temp"),
        "--parallel", str(os.cpu_count() or 1)])
    # the manifest last, atomically: a build that failed left none, so nothing runs it
    table = {m: hashlib.sha256(source(m).read_bytes()).hexdigest() for m in modules}
    with tempfile.NamedTemporaryFile("w", dir=PACKAGE, delete=False, suffix=".tmp") as f:
        json.dump(table, f, indent=1, sort_keys=True)
    os.replace(f.name, MANIFEST)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clean", action="store_true", help="remove the compiled modules")
    ap.add_argument("--strict", action="store_true",
                    help="fail (exit 1) when the modules cannot be compiled")
    args = ap.parse_args()
    if args.clean:
        clean()
        print("compile: removed the compiled modules; the sources run")
        return 0
    modules, group = listed()
    try:
        build(modules, group)
    except (Exception, SystemExit) as err:  # no compiler, no mypyc, a type error ...
        clean()
        what = err if str(err) else type(err).__name__
        print(f"compile: the modules were not compiled ({what}); ucom-tools runs as pure "
              "Python, slower", file=sys.stderr)
        if args.strict:
            return 1
    else:
        print(f"compile: {len(modules)} modules compiled with mypyc")
    BUILD.mkdir(parents=True, exist_ok=True)
    DONE.touch()
    return 0


if __name__ == "__main__":
    sys.exit(main())
