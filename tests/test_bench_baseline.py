"""The 1 kHz benchmark's yardstick: python-can's ``send_periodic`` catches up on a late
frame instead of skipping it, so its missed share must be counted as periods without a
frame (what the PC's loop counts as missed), not as frames short of the total."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

PATH = Path(__file__).resolve().parent.parent / "benchmarks" / "runtime.py"


@pytest.fixture(scope="module")
def runtime_bench():
    spec = importlib.util.spec_from_file_location("bench_runtime", PATH)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_regular_schedule_misses_nothing(runtime_bench) -> None:
    times = [10.0 + k * 0.001 + 0.00003 for k in range(1000)]
    f = runtime_bench.baseline_figures(times, 1.0)
    assert f["baseline_missed_pct"] == 0.0
    assert f["baseline_jitter_p99_ms"] == pytest.approx(0.0, abs=0.001)


def test_a_stall_and_its_catch_up_burst_count_the_empty_periods(runtime_bench) -> None:
    # frames 0..99 on time, then the thread is off the processor for 3.5 ms: frames
    # 100..103 go out together at 103.5 ms (python-can's catch-up), the rest on time
    times = [k * 0.001 for k in range(100)]
    times += [0.1035 + i * 1e-6 for i in range(4)]
    times += [k * 0.001 for k in range(104, 1000)]
    f = runtime_bench.baseline_figures(times, 1.0)
    assert len(times) == 1000  # no frame short: the old count said 0 %
    assert f["baseline_missed_pct"] == pytest.approx(0.3)  # periods 100, 101, 102
    assert f["baseline_rate_hz"] == 1000.0


def test_frames_that_stop_early_leave_the_rest_of_the_periods_empty(runtime_bench) -> None:
    times = [k * 0.001 for k in range(500)]
    assert runtime_bench.baseline_figures(times, 1.0)["baseline_missed_pct"] == 50.0
    assert runtime_bench.baseline_figures([], 1.0)["baseline_missed_pct"] == 100.0
