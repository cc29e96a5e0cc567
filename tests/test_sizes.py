"""Small units (issue 37): no module of the package or of the benchmarks over 600 lines,
no function over 80.

The units still over a bound are listed in :data:`OVER` with their size today: none may
grow, a new one fails, and one that shrinks under its bound must leave the list (so the
list only ever gets shorter).
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
MODULE_LINES = 600
FUNCTION_LINES = 80

OVER: dict[str, int] = {}
"""What is still too long, and how long it is: the debt to pay (none left: a unit that
grows over its bound fails, none may be added here)."""


def _units() -> dict[str, int]:
    """Every module's lines and every function's (``path:Class.function``)."""
    out: dict[str, int] = {}
    for path in sorted([*(ROOT / "ucom_tools").rglob("*.py"),
                        *(ROOT / "benchmarks").rglob("*.py")]):
        rel = path.relative_to(ROOT).as_posix()
        text = path.read_text(encoding="utf-8")
        out[rel] = len(text.splitlines())

        _functions(ast.parse(text), f"{rel}:", out)
    return out


def _functions(node: ast.AST, prefix: str, out: dict[str, int]) -> None:
    for child in ast.iter_child_nodes(node):
        if isinstance(child, ast.ClassDef):
            _functions(child, f"{prefix}{child.name}.", out)
        elif isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
            assert child.end_lineno is not None
            out[f"{prefix}{child.name}"] = child.end_lineno - child.lineno + 1
            _functions(child, f"{prefix}{child.name}.", out)


def _bound(unit: str) -> int:
    return FUNCTION_LINES if ":" in unit else MODULE_LINES


def test_no_unit_over_its_bound_but_the_listed_ones() -> None:
    units = _units()
    new = {u: n for u, n in units.items() if n > _bound(u) and u not in OVER}
    assert not new, f"over {MODULE_LINES} lines a module / {FUNCTION_LINES} a function: {new}"


def test_the_listed_ones_do_not_grow_and_leave_the_list_when_small() -> None:
    units = _units()
    grown = {u: (units[u], n) for u, n in OVER.items() if u in units and units[u] > n}
    assert not grown, f"grown (now, listed): {grown}"
    done = [u for u in OVER if units.get(u, 0) <= _bound(u)]
    assert not done, f"within the bound now (or gone): take them off OVER: {done}"
