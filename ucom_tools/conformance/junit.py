"""The conformance report as JUnit XML: one testcase per case and bus (classname = the
case's group), failures with expected vs got and the frames involved, skips with their
reason.  CI systems (GitHub Actions, GitLab) show it as a test report."""

from __future__ import annotations

import os
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

from ucom_tools.conformance.runner import SuiteResult


def to_xml(result: SuiteResult, name: str = "ucom conformance") -> ET.ElementTree:
    counts = result.counts()
    suite = ET.Element("testsuite", {
        "name": name, "tests": str(len(result.outcomes)),
        "failures": str(counts["failed"]), "errors": str(counts["error"]),
        "skipped": str(counts["skipped"]),
        "time": f"{sum(o.seconds for o in result.outcomes):.3f}"})
    for o in result.outcomes:
        tc = ET.SubElement(suite, "testcase", {
            "classname": o.case.group, "name": f"{o.case.id} [{o.bus}]",
            "time": f"{o.seconds:.3f}"})
        ET.SubElement(tc, "properties").extend([
            ET.Element("property", {"name": "section", "value": o.case.section}),
            ET.Element("property", {"name": "title", "value": o.case.title})])
        if o.status == "failed":
            f = ET.SubElement(tc, "failure", {"message": o.message, "type": "conformance"})
            f.text = f"{o.message}\n\nframes of the case:\n{o.frames}"
        elif o.status == "error":
            ET.SubElement(tc, "error", {"message": o.message})
        elif o.status == "skipped":
            ET.SubElement(tc, "skipped", {"message": o.message})
        if o.trace:
            ET.SubElement(tc, "system-out").text = f"trace: {o.trace}"
    if result.not_restored or result.bus_failure:
        err = ET.SubElement(suite, "system-err")
        err.text = "\n".join(([f"bus failure: {result.bus_failure}"]
                              if result.bus_failure else [])
                             + [f"not left as found: {p}" for p in result.not_restored])
    return ET.ElementTree(suite)


def write(result: SuiteResult, path: Path) -> None:
    """Write the report atomically."""
    tree = to_xml(result)
    ET.indent(tree)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent or Path("."))
    try:
        with os.fdopen(fd, "wb") as fh:
            tree.write(fh, encoding="utf-8", xml_declaration=True)
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise
