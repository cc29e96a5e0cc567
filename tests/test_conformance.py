"""``ucom conformance`` on the bundled fleet: every case passes, again and again, the
boards are left as found, the report is JUnit, the traces are python-can logs."""

from __future__ import annotations

import json
import re
import stat
import xml.etree.ElementTree as ET
from pathlib import Path

import can
from click.testing import CliRunner

from tests import junit_rules
from ucom_tools.cli.main import cli
from ucom_tools.conformance.case import GROUPS
from ucom_tools.conformance.catalogue import all_cases
from ucom_tools.fileio import new_file_mode
from ucom_tools.wire.ids import Function

ROOT = Path(__file__).resolve().parent.parent
PAGE = (ROOT / "man/ucom-protocol.7").read_text()


def ucom(*args: str) -> tuple[int, str, str]:
    r = CliRunner().invoke(cli, list(args))
    return r.exit_code, r.stdout, r.stderr


def _plain(roff: str) -> str:
    return re.sub(r"\\f[BIRP]|\\-|\\&", lambda m: "-" if m.group(0) == "\\-" else "", roff)


def test_every_case_cites_a_section_of_the_protocol_page() -> None:
    """Each citation is 'SECTION[, what]': SECTION an .SH heading of the page, and what it
    names within that section's text (a subsection, a message, a term)."""
    page = _plain(PAGE)
    sections = dict(re.findall(r"^\.SH (.+?)\n(.*?)(?=^\.SH |\Z)", page, re.M | re.S))
    cases = all_cases()
    assert len(cases) >= 25 and {c.group for c in cases} == set(GROUPS)
    for c in cases:
        for ref in c.section.split(";"):
            section, _, what = ref.strip().partition(", ")
            assert section in sections, (c.id, section)
            what = what.split(" (")[0]
            assert not what or what.lower() in sections[section].lower(), (c.id, ref)


def test_the_correct_fleet_passes_every_case_ten_times_in_a_row() -> None:
    for run in range(10):
        code, out, err = ucom("conformance", "--virtual", "armar3", "--bus", "CAN0",
                              "--json")
        data = json.loads(out)
        bad = [c for c in data["cases"] if c["status"] != "passed"]
        assert code == 0 and not bad, (run, bad, err)
        assert data["left_as_found"]


def test_junit_report_and_traces_of_the_whole_fleet(tmp_path: Path) -> None:
    report = tmp_path / "report.xml"
    code, out, _ = ucom("conformance", "--virtual", "armar3", "--junit", str(report),
                        "--trace-dir", str(tmp_path / "traces"))
    assert code == 0
    suite = ET.parse(report).getroot()
    cases = suite.findall("testcase")
    assert suite.get("tests") == str(len(cases)) == str(4 * len(all_cases()))
    assert suite.get("failures") == "0" and suite.get("skipped") == "0"
    assert {tc.get("classname") for tc in cases} == set(GROUPS)
    assert all("section: " in (tc.findtext("system-out") or "") for tc in cases)
    assert junit_rules.breaches(suite) == []  # Jenkins' xunit takes it
    assert stat.S_IMODE(report.stat().st_mode) == new_file_mode()
    trace = tmp_path / "traces" / "CAN2" / "init.numbering.log"
    frames = list(can.LogReader(str(trace)))
    assert frames and {f.arbitration_id >> 6 for f in frames} >= {
        Function.INIT_REQUEST, Function.INIT_ACK}
    assert "112 passed, 0 failed, 0 skipped" in out


def test_list_and_only_select_cases() -> None:
    code, out, _ = ucom("conformance", "--list", "--json")
    listed = json.loads(out)["cases"]
    assert code == 0 and [c["id"] for c in listed] == [c.id for c in all_cases()]
    assert all(c["section"] for c in listed)
    assert any(c["writes"] for c in listed) and any(not c["writes"] for c in listed)
    code, out, _ = ucom("conformance", "--virtual", "armar3", "--bus", "CAN3", "--only",
                        "init.*", "--json")
    ids = {c["id"] for c in json.loads(out)["cases"]}
    assert code == 0 and ids == {c.id for c in all_cases() if c.id.startswith("init.")}
    code, _, err = ucom("conformance", "--virtual", "armar3", "--only", "nothing-like-this")
    assert code == 3 and "no case matches" in err


def test_a_flashed_robot_is_left_as_it_was(tmp_path: Path) -> None:
    state = tmp_path / "state"
    code, _, err = ucom("flash", str(ROOT / "firmware_images/armar3.fl.S"), "--virtual",
                        "armar3", "--state", str(state), "--bus", "CAN1", "--autostart")
    assert code == 0, err
    code, out, _ = ucom("conformance", "--virtual", "armar3", "--state", str(state),
                        "--bus", "CAN1", "--json")
    data = json.loads(out)
    assert code == 0 and data["left_as_found"], data["not_restored"]
    code, out, _ = ucom("info", "all", "--virtual", "armar3", "--state", str(state),
                        "--bus", "CAN1", "--init", "--json")
    boards = json.loads(out)["boards"]
    assert all(b["autostart"] and b["progid"] for b in boards)
