"""A robot's manifest: per board the image it should run and whether it starts by
itself (its topology's ``image =`` and ``autostart =``), checked against the boards'
plug-on boards and FPGAs before anything is sent (``ucom deploy``, ``tree check
--topology``)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ucom_tools.config import attrtree
from ucom_tools.config.attrtree import RobotTrees
from ucom_tools.config.topology import BoardSpec, Topology
from ucom_tools.errors import ImageError, InputError, TopologyError, UcomError
from ucom_tools.image.formats import load_image
from ucom_tools.image.model import Image
from ucom_tools.ops.compat import fits
from ucom_tools.plugons import PLUG_ON_BOARDS
from ucom_tools.wire.transfer import TransferPlan


# ----------------------------------------------------------------------------- manifest
@dataclass(frozen=True)
class Wanted:
    """One board of the manifest: where it is and what it should run."""

    bus: str
    spec: BoardSpec
    image: Image
    plan: TransferPlan

    @property
    def key(self) -> str:
        """``BUS:position`` (1-based, the seq ID of a sound chain)."""
        return f"{self.bus}:{self.spec.position + 1}"

    @property
    def image_path(self) -> Path:
        assert self.spec.image is not None
        return self.spec.image


@dataclass(frozen=True)
class Manifest:
    topology: Topology
    boards: tuple[Wanted, ...]
    trees: RobotTrees | None
    """The trees of the boards that have one (their parameters are kept); None: no
    board has one."""

    def on(self, bus: str) -> list[Wanted]:
        return [w for w in self.boards if w.bus == bus]

    def board(self, bus: str, position: int) -> Wanted | None:
        for w in self.boards:
            if w.bus == bus and w.spec.position == position:
                return w
        return None


def image_problems(topology: Topology) -> list[TopologyError]:
    """Every board's image checked without a bus: it exists (the topology did that), it
    parses, and its descriptor fits the plug-on board and FPGA the topology gives the
    board (:func:`~ucom_tools.ops.compat.fits`; a minor version or a missing descriptor
    is fine).  One error per board, naming the topology's line and key."""
    problems: list[TopologyError] = []
    images: dict[Path, Image | ImageError] = {}
    for bus in topology.buses:
        for spec in bus.boards:
            if spec.image is None:
                continue
            if spec.image not in images:
                try:
                    images[spec.image] = load_image(spec.image)
                except ImageError as err:
                    images[spec.image] = err
            img = images[spec.image]
            where = f"{bus.name} board {spec.position + 1} ({spec.placement})"
            if isinstance(img, ImageError):
                problems.append(TopologyError(f"{where}: image {spec.image}: {err_text(img)}",
                                              file=topology.source, line=spec.line or None,
                                              key="image"))
                continue
            errors = [f for f in fits(img.descriptor, PLUG_ON_BOARDS[spec.board].board_id,
                                      spec.fpga) if f.severity == "error"]
            if errors:
                why = "; ".join(f.message for f in errors)
                problems.append(TopologyError(
                    f"{where}: image {spec.image.name} does not fit the board: {why}",
                    file=topology.source, line=spec.line or None, key="image"))
    return problems


def err_text(err: UcomError) -> str:
    return getattr(err, "reason", None) or str(err)


def load_manifest(topology: Topology) -> Manifest:
    """The manifest of ``topology``: TopologyError (exit code 3, nothing sent) for the
    first board whose image cannot be used, or whose tree cannot; InputError when no
    board names an image."""
    problems = image_problems(topology)
    if problems:
        raise problems[0]
    images: dict[Path, Image] = {}
    plans: dict[Path, TransferPlan] = {}
    boards = []
    for bus in topology.buses:
        for spec in bus.boards:
            if spec.image is None:
                continue
            if spec.image not in images:
                images[spec.image] = load_image(spec.image)
                plans[spec.image] = images[spec.image].plan()
            boards.append(Wanted(bus.name, spec, images[spec.image], plans[spec.image]))
    if not boards:
        raise InputError(f"no board of {topology.name} names an image (set image = "
                         "\"FILE\" in its [[bus.board]] tables)", file=topology.source)
    trees = None
    if any(w.spec.tree is not None for w in boards):
        trees = attrtree.bind_present(topology)  # TreeError: exit code 3
    return Manifest(topology, tuple(boards), trees)


