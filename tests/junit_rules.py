"""The rules of the common JUnit XML schema (the one Jenkins' xunit plugin validates a
report against, ``junit-10.xsd``), as a checker for the tests: which elements may hold
which, the required attributes, the time format.  Returns every breach, empty when the
report keeps the schema."""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET

CHILDREN = {
    "testsuites": {"testsuite"},
    "testsuite": {"testsuite", "properties", "testcase", "system-out", "system-err"},
    "properties": {"property"},
    "property": set(),
    "testcase": {"skipped", "error", "failure", "rerunFailure", "rerunError",
                 "flakyFailure", "flakyError", "system-out", "system-err"},
    "failure": set(), "error": set(), "skipped": set(),
    "system-out": set(), "system-err": set(),
}
REQUIRED = {
    "testsuite": {"name", "tests", "failures", "errors"},
    "testcase": {"name"},
    "property": {"name", "value"},
}
ALLOWED = {
    "testsuite": REQUIRED["testsuite"] | {"group", "time", "skipped", "timestamp",
                                          "hostname", "id", "package", "file", "log", "url"},
    "testcase": {"name", "time", "classname", "group"},
    "property": {"name", "value"},
    "failure": {"type", "message"}, "error": {"type", "message"},
    "skipped": {"type", "message"}, "properties": set(), "system-out": set(),
    "system-err": set(), "testsuites": {"name", "time", "tests", "failures", "errors"},
}
TIME = re.compile(r"(([0-9]{0,3},)*[0-9]{3}|[0-9]{0,3})*(\.[0-9]*)?\Z")
"""A testsuite's time (the schema's SUREFIRE_TIME)."""


def breaches(root: ET.Element) -> list[str]:
    out: list[str] = []
    if root.tag not in ("testsuite", "testsuites"):
        out.append(f"root element {root.tag!r}")

    def walk(e: ET.Element, path: str) -> None:
        where = f"{path}/{e.tag}"
        if e.tag not in CHILDREN:
            out.append(f"{where}: unknown element")
            return
        missing = REQUIRED.get(e.tag, set()) - set(e.attrib)
        if missing:
            out.append(f"{where}: lacks {sorted(missing)}")
        extra = set(e.attrib) - ALLOWED.get(e.tag, set())
        if extra:
            out.append(f"{where}: attributes {sorted(extra)} are not in the schema")
        if e.tag in ("testsuite", "testsuites") and "time" in e.attrib and \
                not TIME.match(e.attrib["time"]):
            out.append(f"{where}: time {e.attrib['time']!r}")
        for child in e:
            if child.tag not in CHILDREN[e.tag]:
                out.append(f"{where}: {child.tag!r} may not be inside {e.tag!r}")
            walk(child, where)

    walk(root, "")
    return out
