"""The conformance suite is proven: run against boards with each documented defect
(ucom_tools.virtual.board.mutants), it fails, and in the case named for that defect; against
conforming boards it passes (tests/test_conformance.py: ten times in a row).  The
mutation score is printed at the end of the test run."""

from __future__ import annotations

from dataclasses import replace

import pytest

from tests.runtime_rig import robot_of
from ucom_tools.config.topology import load
from ucom_tools.conformance.runner import run_suite, select
from ucom_tools.virtual.board import mutants
from ucom_tools.virtual.fleet import Fleet

CATCHES = {
    mutants.SEQ_FROM_ZERO: "init.numbering",
    mutants.INIT_TWICE: "init.numbering",
    mutants.INFO_SWAPPED: "info.record",
    mutants.WRONG_PROGID: "program.transfer",
    mutants.ACCEPT_BAD_PROGID: "program.wrong-progid",
    mutants.IGNORE_ALIVE: "mca.watchdog",
    mutants.SO_SLOW: "mca.so-period",
    mutants.LATE_ANSWER: "info.set-status-time",
    mutants.PROMISCUOUS: "bad.other-boards",
    mutants.IGNORE_INITOUT: "init.set-init-out",
    mutants.DESCR_TRUNCATED: "mca.descr",
    mutants.NO_RANGE_CHECK: "mca.par-write",
    mutants.CI_WHILE_LATCHED: "mca.watchdog",
    mutants.AUTOSTART_LOST: "autostart.reset-keeps",
    mutants.XRESET_KEEPS_AUTOSTART: "autostart.xreset-clears",
    mutants.UNKNOWN_FUNCTION_SILENT: "bad.unknown-function",
    mutants.DUMP_OFF_BY_ONE: "mca.dump",
    mutants.READY_COUNTS_WRONG: "mca.ready",
    mutants.DIGEST_UNKNOWN: "mca.digest",
    mutants.DIGEST_WRONG: "mca.digest",
}
"""Each defect and the case that must catch it."""

SCORE: dict[str, bool] = {}
"""Defect -> caught by its case (read by conftest's summary)."""


def _head(defect: str | None) -> Fleet:
    """ARMAR-III's CAN0 (three boards), every board with ``defect``."""
    armar3 = load("armar3")
    return Fleet(replace(armar3, buses=armar3.buses[:1]), defect=defect)


def test_every_defect_has_a_case_that_catches_it() -> None:
    assert set(CATCHES) == {d.name for d in mutants.defects()}
    assert len(CATCHES) >= 15
    ids = {c.id for c in select(None)}
    assert set(CATCHES.values()) <= ids


@pytest.mark.parametrize("defect", sorted(CATCHES))
def test_the_suite_catches_the_mutant(defect: str) -> None:
    fleet = _head(defect)
    robot = robot_of(fleet)
    try:
        result = run_suite(robot, select(None))
    finally:
        robot.close()
    failed = {o.case.id for o in result.failed}
    SCORE[defect] = CATCHES[defect] in failed
    assert CATCHES[defect] in failed, (defect, sorted(failed),
                                      [(o.case.id, o.status, o.message)
                                       for o in result.outcomes if o.case.id == CATCHES[defect]])
    assert result.bus_failure is None
    failure = next(o for o in result.failed if o.case.id == CATCHES[defect])
    assert "expected" in failure.message and failure.frames  # readable: what and the frames


def test_the_correct_head_passes() -> None:
    robot = robot_of(_head(None))
    try:
        result = run_suite(robot, select(None))
    finally:
        robot.close()
    assert result.ok and not result.not_restored, [
        (o.case.id, o.message) for o in result.failed]
