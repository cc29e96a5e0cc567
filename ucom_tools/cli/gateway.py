"""``ucom gateway``: a UCoM robot's joints as CANopen CiA 402 drives (``man/ucom-gateway.7``).

``gateway canopen ROBOT --canopen SPEC`` runs the robot as ``remote run`` does and presents
every joint as a CiA 402 node on the CANopen bus (the gateway runs in the consumers'
process, :mod:`ucom_tools.cli.consumers`, fed by the loop's snapshots);
``gateway eds ROBOT -o DIR`` writes the files a CANopen master needs to drive the joints:
an EDS per joint and a ``bus.yml`` for Lely's dcfgen and ros2_canopen, and prints the
node table.  The logic is :mod:`ucom_tools.gateway` (joints, dictionary, eds, bridge).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import click
from rich.markup import escape

from ucom_tools.cli.consumers import ExtraConsumer
from ucom_tools.cli.options import connection_options, json_option
from ucom_tools.cli.output import emit_json, stderr, stdout
from ucom_tools.cli.remote import run_options
from ucom_tools.cli.remote_run import run_robot
from ucom_tools.cli.tables import FitTable
from ucom_tools.config import topology as topo
from ucom_tools.errors import InputError
from ucom_tools.gateway import buses, eds, joints
from ucom_tools.gateway.joints import RobotJoints
from ucom_tools.ops.robot import ConnectSpec

VALUES_HZ = 250.0
"""How often the loop hands its snapshot to the gateway (a joint's 0x6064 is at most 4 ms
older than the board's latest frame; each snapshot costs the loop ~0.1 ms, so at 500 Hz
the loop paid for its consumers 5 % of its time)."""
CYCLE_S = 0.002
"""The CANopen node runtime's cycle (its longest wait for a frame)."""


@click.group("gateway")
def gateway() -> None:
    """A UCoM robot's joints as CANopen CiA 402 drives (ucom-gateway(7))."""


def _print_table(robot: RobotJoints, directory: Path, written: eds.Written,
                 master_node: int) -> None:
    t = FitTable(f"{robot.topology.name}: CANopen nodes (master {master_node})")
    for col, drop in (("node", 0), ("joint", 0), ("bus", 0), ("board", 0), ("placement", 1),
                      ("axis", 0), ("program", 2), ("eds", 0)):
        t.add_column(col, drop=drop)
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


CANOPEN_HELP = """Run ROBOT's boards and present each joint as a CiA 402 drive on a CANopen bus.

ROBOT is the robot's topology (a bundled name such as armar3, or a topology file; not
needed with --virtual or --topology).  The UCoM side is 'ucom remote run' with every
one of its options (start, tree check, 1 kHz loop, watchdog, --on-fault, --rejoin,
--record, --zenoh); the gateway runs apart from the loop, in the consumers' process,
and reads the loop's snapshots (250 Hz) and hands it the joints' commands.

--canopen [UCOM_BUS[,UCOM_BUS]=]INTERFACE:CHANNEL (repeatable): the CANopen bus, any
python-can interface (socketcan:vcan0, pcan:PCAN_USBBUS1) or socketcand:CHANNEL@HOST:PORT
(a bus 'ucom fleet serve ROBOT --extra-bus CHANNEL' serves); with UCoM buses in front,
only their joints (CAN0=socketcan:vcan0 --canopen CAN1=socketcan:vcan1 ...).

One node per joint, node IDs as 'ucom gateway eds' writes them (printed at the start);
with --bus NAME (the run opens that bus alone) the joints of that bus.
Each sends its boot-up and a heartbeat every 100 ms (0x1017); CiA 402 modes profile
position, profile velocity, homing and cyclic synchronous position; every edge of the
board by SDO as a manufacturer object.  A joint whose board is lost, latched by its
watchdog or sends an Error goes to FAULT with an EMCY.  The joints run only while their
master lives: its heartbeat (0x1016) or, without, its SYNC (3 periods, at most
100 ms); a master that goes switches every joint off and its node to FAULT
(ucom-gateway(7)).  --json adds 'gateway': each CANopen bus's figures and each node's
state at the end."""


def _announce(robot: RobotJoints, specs: list[buses.CanopenSpec]) -> Any:
    def show(ready: Any) -> None:
        out = stderr()
        fits = (ready or {}).get("fits_hz", {})
        for i, mine in buses.by_bus(specs, robot.joints, lambda j: j.bus).items():
            spec = specs[i]
            nodes = ", ".join(f"{j.node_id} {escape(j.name)}" for j in mine)
            fit = fits.get(spec.text)
            rate = (f"; their PDOs fit SYNC up to {fit:.0f} Hz at 1 Mbit/s" if fit
                    and fit != float("inf") else "")
            out.print(f"[dim]gateway: {escape(spec.where)}: {len(mine)} nodes{rate}: "
                      f"{nodes}[/]", soft_wrap=True)
    return show


@gateway.command("canopen", help=CANOPEN_HELP)
@click.argument("robot_name", metavar="[ROBOT]", required=False)
@click.option("--canopen", "canopen_specs", multiple=True, required=True,
              metavar="[UCOM_BUS=]INTERFACE:CHANNEL",
              help="The CANopen bus (repeatable, one per UCoM bus or group of them): "
                   "socketcan:vcan0, socketcand:CO0@127.0.0.1:29536, CAN0=socketcan:vcan0.")
@run_options
@connection_options
@json_option
@click.pass_context
def canopen_cmd(ctx: click.Context, robot_name: str | None, canopen_specs: tuple[str, ...],
                spec: ConnectSpec, **options: Any) -> None:
    specs = [buses.parse(text) for text in canopen_specs]
    for s in specs:
        if s.interface == "virtual":
            raise InputError(f"'{s.text}': python-can's virtual buses live in one process, "
                             "and the gateway runs in a process of its own: use "
                             "socketcand:CHANNEL@HOST:PORT over 'ucom fleet serve ROBOT "
                             "--extra-bus CHANNEL' (in one Python program: "
                             "ucom_tools.gateway.bridge.Gateway.serve)", key="--canopen")
    name = robot_name or spec.virtual or spec.topology
    if not name:
        raise InputError("which robot? give it (e.g. 'armar3'), --topology FILE or "
                         "--virtual ROBOT", key="ROBOT")
    robot = joints.load(name)
    bus_names = [b.name for b in topo.load(name).buses]
    only = options.get("bus_name")
    if only in bus_names:  # --bus: the run opens that bus alone, the gateway its joints
        robot = replace(robot, joints=tuple(j for j in robot.joints if j.bus == only))
        bus_names = [only]
    buses.check(specs, bus_names)
    for skipped in robot.skipped:
        stderr().print(f"[yellow]gateway: {escape(skipped.where)} has no joints: "
                       f"{escape(skipped.reason)}[/]", soft_wrap=True)
    extra = ExtraConsumer("gateway", {"joints": robot.joints, "buses": specs,
                                      "cycle": CYCLE_S}, VALUES_HZ,
                          _announce(robot, specs))
    run_robot(ctx, (robot_name,) if robot_name else (), spec=spec, extra=extra, **options)
