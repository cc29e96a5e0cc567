"""The conformance report as JUnit XML: one testcase per case and bus (classname = the
case's group), failures with expected vs got and the frames involved, skips with their
reason, and in system-out the case's section of the protocol page, its title and its
trace.  The report keeps the JUnit XML schema that Jenkins' xunit plugin validates
against (testcase children: skipped, error, failure, system-out, system-err; properties
only under testsuite).  CI systems (GitHub Actions, GitLab, Jenkins) show it as a test
report."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

from ucom_tools import fileio
from ucom_tools.conformance.runner import SuiteResult, Words


def to_xml(result: SuiteResult, name: str = "ucom conformance",
           words: Words = str) -> ET.ElementTree:
    """The report of ``result``; ``words`` words the error that stopped the suite."""
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
        if o.status == "failed":
            f = ET.SubElement(tc, "failure", {"message": o.message, "type": "conformance"})
            f.text = f"{o.message}\n\nframes of the case:\n{o.frames}"
        elif o.status == "error":
            ET.SubElement(tc, "error", {"message": o.message})
        elif o.status == "skipped":
            ET.SubElement(tc, "skipped", {"message": o.message})
        # what the case checks, and its trace: in system-out, the one place a testcase
        # of the JUnit schema (Jenkins' xunit) holds free text (properties belong to the
        # testsuite)
        ET.SubElement(tc, "system-out").text = "\n".join(
            [f"section: {o.case.section}", f"title: {o.case.title}"]
            + ([f"trace: {o.trace}"] if o.trace else []))
    if result.not_restored or result.bus_failure or result.stopped is not None:
        err = ET.SubElement(suite, "system-err")
        stop_text = result.describe_stop(words)
        err.text = "\n".join(([f"stopped: {stop_text}"] if stop_text else [])
                             + ([f"bus failure: {result.bus_failure}"]
                                if result.bus_failure else [])
                             + [f"not left as found: {p}" for p in result.not_restored])
    return ET.ElementTree(suite)


def write(result: SuiteResult, path: Path | fileio.Output, words: Words = str) -> None:
    """Write the report by the rules of ``ucom(1)``, FILES (a regular file atomically,
    mode 0644 under the umask or the old file's; a device or FIFO written through; ``-``
    standard output).  ``path`` may be an :class:`~ucom_tools.fileio.Output` prepared
    before the suite ran (so that an unwritable target is found before anything is sent).
    ``words`` words the error that stopped the suite.
    :class:`~ucom_tools.errors.WriteError` when writing fails."""
    tree = to_xml(result, words=words)
    ET.indent(tree)
    out = path if isinstance(path, fileio.Output) else \
        fileio.Output(path, key="junit", allow_stdout=True)
    with out:
        try:
            with out.open("wb") as fh:
                tree.write(fh, encoding="utf-8", xml_declaration=True)
        except OSError as err:
            raise out.failed(err) from None
