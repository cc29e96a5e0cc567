"""``ucom gateway``: a UCoM robot's joints as CANopen CiA 402 drives (``man/ucom-gateway.7``).

``gateway eds ROBOT -o DIR`` writes the files a CANopen master needs to drive the joints:
an EDS per joint and a ``bus.yml`` for Lely's dcfgen and ros2_canopen, and prints the
node table.  The logic is :mod:`ucom_tools.gateway` (joints, dictionary, eds).
"""

from __future__ import annotations

from pathlib import Path

import click
from rich.markup import escape
from rich.table import Table

from ucom_tools.cli.options import json_option
from ucom_tools.cli.output import emit_json, stderr, stdout
from ucom_tools.gateway import eds, joints
from ucom_tools.gateway.joints import RobotJoints


@click.group("gateway")
def gateway() -> None:
    """A UCoM robot's joints as CANopen CiA 402 drives (ucom-gateway(7))."""


def _print_table(robot: RobotJoints, directory: Path, written: eds.Written,
                 master_node: int) -> None:
    t = Table(title=f"{robot.topology.name}: CANopen nodes (master {master_node})",
              title_justify="left")
    for col in ("node", "joint", "bus", "board", "placement", "axis", "program", "eds"):
        t.add_column(col, overflow="fold")
    for j in robot.joints:
        t.add_row(f"{j.node_id}{'' if j.node_given else '*'}", escape(j.name), j.bus,
                  str(j.board.position + 1), escape(j.board.placement), j.letter,
                  escape(j.board.program.name), escape(f"{j.key}.eds"))
    out = stdout()
    out.print(t)
    if any(not j.node_given for j in robot.joints):
        out.print("* numbered in topology order (the topology gives no canopen_node)")
    out.print(f"[green]ok[/] {len(robot.joints)} joints: {len(written.written)} files "
              f"written, {len(written.unchanged)} unchanged in {escape(str(directory))}",
              soft_wrap=True)


@gateway.command("eds")
@click.argument("robot_name", metavar="ROBOT")
@click.option("-o", "--output", "directory", required=True, metavar="DIR",
              type=click.Path(path_type=Path),
              help="Directory for the EDS files and bus.yml (made if missing).")
@click.option("--force", is_flag=True, help="Replace files there that differ.")
@click.option("--master-node", type=click.IntRange(1, 127), default=eds.MASTER_NODE,
              show_default=True, help="The master's node ID in bus.yml.")
@click.option("--dcf-path", metavar="PATH",
              help="bus.yml's options.dcf_path: where the master finds the .bin files "
                   "dcfgen writes (default: DIR, absolute; '' leaves it out).")
@json_option
def eds_cmd(robot_name: str, directory: Path, force: bool, master_node: int,
            dcf_path: str | None, as_json: bool) -> None:
    """Write an EDS per joint of ROBOT and the bus.yml of a CANopen master into DIR.

    ROBOT is the robot's topology (a bundled name such as armar3, or a topology file).
    A joint is an axis whose Target edge its board's attribute tree names (the unique
    name differs from the generic one); its name is that name without " Target"
    ("Right Eye").  Node IDs: canopen_node = { A = 10 } in a board's table of the
    topology, else numbered in topology order from 2 (1 is the master's).

    Per joint DIR/KEY.eds, KEY its name in lower snake case (right_eye.eds; CiA 306:
    its object dictionary, the CiA 402 objects and every edge of its board as a
    manufacturer object; ucom-gateway(7)), and DIR/bus.yml: 'master:' and one key per
    joint (KEY) with node_id and dcf, in the form Lely's dcfgen and ros2_canopen take
    ('dcfgen -r bus.yml' in DIR writes master.dcf and each joint's .bin).  The same
    robot gives the same bytes.

    All files or none; each atomically.  A file in DIR with other content is refused
    (exit code 3, nothing written) unless --force; one with the same content is left.
    The node table goes to standard output (--json: {"robot", "topology", "output",
    "master_node", "written", "unchanged", "skipped", "nodes": [{"node_id", "given",
    "name", "key", "bus", "board", "placement", "axis", "program", "eds", "target"}]})."""
    robot = joints.load(robot_name)
    path = str(directory.resolve()) if dcf_path is None else dcf_path
    files = eds.render(robot, master_node=master_node, dcf_path=path or None)
    written = eds.write(files, directory, force=force)
    for s in robot.skipped:
        stderr().print(f"[yellow]gateway: {escape(s.where)} has no joints: "
                       f"{escape(s.reason)}[/]", soft_wrap=True)
    if as_json:
        emit_json({"robot": robot.topology.name, "topology": robot.topology.source,
                   "output": str(directory), "master_node": master_node,
                   "written": [str(p) for p in written.written],
                   "unchanged": [str(p) for p in written.unchanged],
                   "skipped": [{"where": s.where, "reason": s.reason} for s in robot.skipped],
                   "nodes": [eds.node_row(j) for j in robot.joints]})
    else:
        _print_table(robot, directory, written, master_node)
