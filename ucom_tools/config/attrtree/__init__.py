"""Attribute trees (dissertation B.5; ``man/ucom-tree.5``): the per-board configuration
of a UCoM program: generic edge names mapped to robot-wide unique names, with parameter and
controller-input defaults.

Pure code (no CLI):

- :func:`load` / :func:`parse` read and check a tree -> :class:`Tree` of :class:`BoardBlock` of
  :class:`Edge` (each with its :class:`TreeEdgeKind` and optional default :class:`Value`); every
  mistake is a :class:`~ucom_tools.errors.TreeError` naming ``FILE:LINE:COL``.
- :func:`dumps` / :func:`save` write the canonical form (``save`` is atomic).
- :func:`diff` lists the :class:`Change` s between two trees.
- :func:`check` / :func:`bind` load the trees a robot's topology names, per board.
"""

from ucom_tools.config.attrtree.diff import Change, ChangeKind, diff
from ucom_tools.config.attrtree.model import KIND_ORDER, BoardBlock, Edge, Tree, TreeEdgeKind, Value
from ucom_tools.config.attrtree.parser import load, parse
from ucom_tools.config.attrtree.robot import (
    BoundBoard,
    RobotTrees,
    bind,
    bind_present,
    check,
    with_files,
)
from ucom_tools.config.attrtree.writer import dumps, save

__all__ = [
    "KIND_ORDER",
    "BoardBlock",
    "BoundBoard",
    "Change",
    "ChangeKind",
    "Edge",
    "RobotTrees",
    "Tree",
    "TreeEdgeKind",
    "Value",
    "bind",
    "bind_present",
    "check",
    "diff",
    "dumps",
    "load",
    "parse",
    "save",
    "with_files",
]
