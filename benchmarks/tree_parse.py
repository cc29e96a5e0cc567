#!/usr/bin/env python3
"""Attribute trees: parse time per 1,000 mapping lines, and loading a whole robot.

1. A generated tree of 10,000 mapping lines (one board, CI / SO / PAR thirds, no defaults)
   is parsed and checked; the baseline, measured in the same run, is Python's own
   ``tomllib`` (pure Python, like ours) reading the same 10,000 mappings written as TOML,
   one inline table per line: syntax only, with no name, index or kind checks.
2. Loading ARMAR-III: the topology and all 11 trees it binds, parsed, checked and bound
   (``attrtree.check(topology.load("armar3"))``).  Target: well under 100 ms.

``--json`` prints the figures as one JSON object.
"""

from __future__ import annotations

import json
import statistics
import sys
import time
import tomllib
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from ucom_tools.config import attrtree, topology  # noqa: E402

LINES = 10_000
RUNS = 7
TARGET_MS = 100.0


def kind_of(i: int, n: int) -> str:
    return ("CI", "SO", "PAR")[3 * i // n]


def tree_text(n: int) -> str:
    out = ["DSP{", "  0{", "    Prefix : Bench", "    MappingTable{"]
    for i in range(n):
        if i == 0 or kind_of(i, n) != kind_of(i - 1, n):
            out.append("      # " + kind_of(i, n))
        out.append(f"      {i}:Motor{i % 3} Generic Edge {i} ==> Joint {i} Unique Edge Name")
    out += ["    }MappingTable", "  }0", "}DSP", ""]
    return "\n".join(out)


def toml_text(n: int) -> str:
    out = ['[[dsp]]', 'number = 0', 'prefix = "Bench"', '[dsp.mapping]']
    for i in range(n):
        out.append(f'"{i}" = {{ kind = "{kind_of(i, n)}", '
                   f'generic = "Motor{i % 3} Generic Edge {i}", '
                   f'unique = "Joint {i} Unique Edge Name" }}')
    return "\n".join(out) + "\n"


def best(fn: Callable[[], object]) -> tuple[float, list[float]]:
    times = []
    for _ in range(RUNS):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times), times


def main() -> int:
    as_json = "--json" in sys.argv[1:]
    text, toml = tree_text(LINES), toml_text(LINES)
    data = text.encode("utf-8")
    assert len(attrtree.parse(data, "bench").boards[0].edges) == LINES
    assert len(tomllib.loads(toml)["dsp"][0]["mapping"]) == LINES
    ours, _ = best(lambda: attrtree.parse(data, "bench"))
    base, _ = best(lambda: tomllib.loads(toml))
    per_k_ours = ours / LINES * 1000 * 1e6
    per_k_base = base / LINES * 1000 * 1e6

    def load_armar3() -> attrtree.RobotTrees:
        result = attrtree.check(topology.load("armar3"))
        assert result.ok and len(result.boards) == 11
        return result

    t0 = time.perf_counter()
    load_armar3()
    cold_ms = (time.perf_counter() - t0) * 1e3
    _, runs = best(load_armar3)
    load_ms = statistics.median(runs) * 1e3
    mappings = sum(len(b.board.edges) for b in load_armar3().boards)
    figures = {
        "parse_us_per_1000_lines": round(per_k_ours, 1),
        "baseline_tomllib_us_per_1000_lines": round(per_k_base, 1),
        "ratio_ours_to_tomllib": round(per_k_ours / per_k_base, 2),
        "armar3_load_ms": round(load_ms, 2),
        "armar3_first_load_ms": round(cold_ms, 2),
        "armar3_boards": 11,
        "armar3_mappings": mappings,
        "target_ms": TARGET_MS,
    }
    if as_json:
        print(json.dumps(figures, indent=2))
    else:
        print(f"parse     {LINES} mapping lines, checked: {per_k_ours:.0f} us per 1,000 lines "
              f"(best of {RUNS})")
        print(f"baseline  tomllib, the same mappings as TOML, syntax only: {per_k_base:.0f} us "
              f"per 1,000 lines; ratio ours / tomllib = {per_k_ours / per_k_base:.2f}")
        print(f"armar3    topology + 11 trees ({mappings} mappings) loaded, checked, bound: "
              f"median {load_ms:.1f} ms, first {cold_ms:.1f} ms (target < {TARGET_MS:.0f} ms): "
              f"{'MET' if load_ms < TARGET_MS else 'NOT MET'}")
    return 0 if load_ms < TARGET_MS else 1


if __name__ == "__main__":
    sys.exit(main())
