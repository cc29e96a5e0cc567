"""The DSP programs ucom-tools knows: their edges (what the board reports with MCA DumpIO
Descr), found by the program name in an image's descriptor.  Pure data, no I/O; the
virtual boards run models of them (:mod:`ucom_tools.virtual.programs`)."""

from __future__ import annotations

from ucom_tools.edgelists.model import EdgeKind, EdgeSpec, ProgramSpec

__all__ = ["EdgeKind", "EdgeSpec", "ProgramSpec", "by_name", "known"]


def known() -> dict[str, ProgramSpec]:
    """Every program, by the name its image descriptor carries."""
    from ucom_tools.edgelists import armar3, lauron4

    return {p.name: p for p in (armar3.SPEC, lauron4.SPEC)}


def by_name(name: str) -> ProgramSpec | None:
    return known().get(name)
