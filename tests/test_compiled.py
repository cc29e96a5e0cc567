"""The compiled run time (:mod:`ucom_tools.compiled`): the extensions run only while they
match their sources, all of them or none, and the pure-Python path on request."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from ucom_tools import compiled

ROOT = Path(__file__).resolve().parent.parent
DEADLINE = 60.0

WHERE = ("import importlib, json, ucom_tools.compiled as c; "
         "print(json.dumps({'files': [importlib.import_module(m).__file__ for m in c.MODULES],"
         " 'status': [c.status().compiled, c.status().reason]}))")
"""Imports every compiled module in a fresh process and says where each came from."""


@pytest.fixture(autouse=True)
def _decided_here(monkeypatch: pytest.MonkeyPatch) -> None:
    """``_decide`` as in a process without UCOM_PURE_PYTHON (the suite may run with it)."""
    monkeypatch.delenv(compiled.PURE_ENV, raising=False)


def where(**env: str) -> dict[str, object]:
    environment = {k: v for k, v in os.environ.items() if k != compiled.PURE_ENV}
    environment.update(env)
    r = subprocess.run([sys.executable, "-c", WHERE], capture_output=True, text=True,
                       timeout=DEADLINE, cwd=ROOT, env=environment)
    assert r.returncode == 0, r.stderr
    out: dict[str, object] = json.loads(r.stdout)
    return out


def manifest(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, table: object) -> None:
    path = tmp_path / "_native.json"
    path.write_text(json.dumps(table))
    monkeypatch.setattr(compiled, "MANIFEST", path)


def digests() -> dict[str, str]:
    return {m: hashlib.sha256(compiled.source_of(m).read_bytes()).hexdigest()
            for m in compiled.MODULES}


def test_every_listed_module_has_its_source() -> None:
    for module in compiled.MODULES:
        assert compiled.source_of(module).is_file(), module


def test_pure_python_on_request() -> None:
    got = where(**{compiled.PURE_ENV: "1"})
    files = got["files"]
    assert isinstance(files, list) and len(files) == len(compiled.MODULES)
    assert all(str(f).endswith(".py") for f in files), files
    assert got["status"] == [False, f"pure Python ({compiled.PURE_ENV} is set)"]


def test_the_compiled_modules_run_when_built() -> None:
    if not compiled.MANIFEST.exists():
        pytest.skip("not compiled here ('make compiled' builds the extensions; a machine "
                    "without a C compiler runs pure Python)")
    got = where()
    files = got["files"]
    assert isinstance(files, list)
    assert all(str(f).endswith(".so") for f in files), files
    assert got["status"] == [True, f"compiled with mypyc ({len(compiled.MODULES)} modules)"]


def test_a_build_that_matches_its_sources_is_run(tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    manifest(tmp_path, monkeypatch, digests())
    assert compiled._decide().compiled


def test_a_changed_source_is_named_and_the_sources_run(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    table = digests()
    table["ucom_tools.virtual.bus.simbus"] = "0" * 64  # as if built from another simbus.py
    manifest(tmp_path, monkeypatch, table)
    status = compiled._decide()
    assert not status.compiled
    assert status.reason == "pure Python (ucom_tools/virtual/bus/simbus.py changed since the build)"
    err = capsys.readouterr().err
    assert "ucom_tools/virtual/bus/simbus.py" in err and "make compiled" in err


def test_a_module_the_build_did_not_compile_means_the_sources_run(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    table = digests()
    del table["ucom_tools.virtual.bus.clock"]  # an older build, before clock.py was listed
    manifest(tmp_path, monkeypatch, table)
    assert not compiled._decide().compiled
    assert "ucom_tools/virtual/bus/clock.py" in capsys.readouterr().err


@pytest.mark.parametrize(("text", "reason"), [
    ("{not json", "_native.json unreadable"), ("[1, 2]", "_native.json is not a table")])
def test_a_broken_manifest_means_the_sources_run(tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch,
                                                 text: str, reason: str) -> None:
    path = tmp_path / "_native.json"
    path.write_text(text)
    monkeypatch.setattr(compiled, "MANIFEST", path)
    status = compiled._decide()
    assert not status.compiled and reason in status.reason


def test_no_build_means_the_sources_run(tmp_path: Path,
                                        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(compiled, "MANIFEST", tmp_path / "none.json")
    status = compiled._decide()
    assert status == compiled.Status(
        False, "pure Python (not compiled: make compiled builds it)")


def test_the_build_compiles_what_the_package_lists() -> None:
    sys.path.insert(0, str(ROOT / "tools"))
    try:
        import compile as build  # tools/compile.py
    finally:
        sys.path.remove(str(ROOT / "tools"))
    assert build.listed() == (compiled.MODULES, compiled.GROUP)
    assert [build.source(m) for m in compiled.MODULES] == [
        compiled.source_of(m) for m in compiled.MODULES]


def test_ucom_version_says_which_run_time() -> None:
    r = subprocess.run([sys.executable, "-m", "ucom_tools", "--version"], capture_output=True,
                       text=True, timeout=DEADLINE, cwd=ROOT,
                       env={**os.environ, compiled.PURE_ENV: "1"})
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == ("ucom, version 0.1.0, run time pure Python "
                                f"({compiled.PURE_ENV} is set)")
