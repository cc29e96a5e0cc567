"""``--realtime``: the PC loop's thread under SCHED_FIFO, or a reason why not; without it,
a short time slice at normal priority."""

from __future__ import annotations

import os
import threading

import pytest

from ucom_tools.ops.realtime import (
    PRIORITY,
    SLICE_NS,
    RealtimeScheduling,
    restore_slice,
    short_slice,
    thread_slice,
)

linux = pytest.mark.skipif(not hasattr(os, "sched_setscheduler"), reason="Linux scheduling")


@linux
def test_enter_switches_the_calling_thread_and_leave_restores_it() -> None:
    outcome: dict[str, object] = {}

    def loop_thread() -> None:  # a thread of its own: the test runner's keeps its policy
        before = os.sched_getscheduler(0)
        rt = RealtimeScheduling()
        ok = rt.enter()
        outcome["ok"] = ok
        outcome["during"] = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)
        outcome["describe"] = rt.describe()
        outcome["refused"] = rt.refused
        rt.leave()
        outcome["after"] = os.sched_getscheduler(0)
        outcome["before"] = before

    t = threading.Thread(target=loop_thread)
    t.start()
    t.join(timeout=10)
    if outcome["ok"]:
        assert outcome["during"] == (os.SCHED_FIFO, PRIORITY)
        assert outcome["describe"] == f"SCHED_FIFO {PRIORITY}"
    else:  # not permitted here: the reason is given, nothing changed
        assert "SCHED_FIFO" in str(outcome["refused"])
        assert outcome["during"][0] == outcome["before"]  # type: ignore[index]
        assert str(outcome["describe"]).startswith("normal (")
    assert outcome["after"] == outcome["before"]
    # the runner's thread was never touched
    assert os.sched_getscheduler(0) == os.SCHED_OTHER


@linux
def test_a_refusal_is_a_reason_not_an_error(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*args: object) -> None:
        raise PermissionError(1, "Operation not permitted")
    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    rt = RealtimeScheduling()
    assert rt.enter() is False and not rt.active and not rt.used
    assert "CAP_SYS_NICE" in rt.refused and "rtprio" in rt.refused
    assert rt.describe() == f"normal ({rt.refused})"
    rt.leave()  # nothing to undo


def test_leave_from_another_thread_does_nothing() -> None:
    rt = RealtimeScheduling()
    rt.active, rt._thread = True, -1  # entered by some other thread
    rt.leave()
    assert rt.active


def _slice_in_a_thread() -> dict[str, int | None]:
    """short_slice and restore_slice in a thread of its own, the slices seen on the way."""
    seen: dict[str, int | None] = {}

    def loop_thread() -> None:
        seen["before"] = thread_slice()
        seen["given"] = short_slice()
        seen["during"] = thread_slice()
        if seen["given"] is not None:
            restore_slice(seen["given"])
        seen["after"] = thread_slice()

    t = threading.Thread(target=loop_thread)
    t.start()
    t.join(timeout=10)
    return seen


@linux
def test_a_short_time_slice_for_the_calling_thread_and_back() -> None:
    runner = thread_slice()
    seen = _slice_in_a_thread()
    assert thread_slice() == runner  # the runner's thread was never touched
    if seen["given"] is None:  # nothing changed where the kernel keeps its own
        assert seen["during"] == seen["before"] == seen["after"]
        pytest.skip("this kernel keeps its own time slice (a thread's own: Linux 6.12)")
    assert seen["given"] == seen["before"] != SLICE_NS
    assert seen["during"] == SLICE_NS
    assert seen["after"] == seen["before"]


@linux
def test_no_slice_is_asked_for_under_sched_fifo() -> None:
    outcome: dict[str, object] = {}

    def loop_thread() -> None:
        rt = RealtimeScheduling()
        if not rt.enter():
            outcome["refused"] = rt.refused
            return
        outcome["given"] = short_slice()
        outcome["slice"] = thread_slice()
        rt.leave()

    t = threading.Thread(target=loop_thread)
    t.start()
    t.join(timeout=10)
    if "refused" in outcome:
        pytest.skip(f"SCHED_FIFO: {outcome['refused']}")
    assert outcome == {"given": None, "slice": None}
