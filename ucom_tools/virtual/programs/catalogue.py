"""The DSP programs the virtual fleet has models of, each found by the program name of an
image's descriptor (:func:`make`); a program without a model runs idle."""

from __future__ import annotations

from collections.abc import Callable

from ucom_tools.edgelists import by_name
from ucom_tools.edgelists.model import ProgramSpec
from ucom_tools.virtual.programs.base import Hardware, Plant, ProgramModel
from ucom_tools.virtual.programs.idle import IdleModel

Factory = Callable[[Hardware, str, Plant | None], tuple[ProgramModel, Plant | None]]


def _factories() -> dict[str, Factory]:
    out: dict[str, Factory] = {}
    try:
        from ucom_tools.virtual.programs import armar3
        out[armar3.SPEC.name] = armar3.make
    except ImportError:  # pragma: no cover - while a model is being written
        pass
    try:
        from ucom_tools.virtual.programs import lauron4
        out[lauron4.SPEC.name] = lauron4.make
    except ImportError:  # pragma: no cover
        pass
    return out


def make(name: str, hardware: Hardware, placement: str = "", plant: Plant | None = None,
         ) -> tuple[ProgramSpec, ProgramModel, Plant | None]:
    """The model of the program called ``name`` (an image descriptor's name), running on
    ``hardware`` of a board at ``placement`` (the topology's word for what it drives);
    a program without a model runs idle, with no edges.  ``plant``: the board's plant
    from a program before (the board's hardware): the model keeps it if it drives that
    kind, and the caller resumes it (:meth:`Plant.resume`)."""
    factory = _factories().get(name)
    spec = by_name(name)
    if factory is None or spec is None:
        idle = IdleModel()
        return idle.spec, idle, None
    model, made = factory(hardware, placement, plant)
    return spec, model, made
